"""Scale and translation invariance: the same model at any size gives the same answers.

The tests run in model units (pmjax._units): a model scaled by a power of two
is refined bit for bit as the original; any other uniform scale or offset
changes only float32 rounding, and on the cow not one face count. Each check
compares against the same model at unit scale, cameras moved with the model.
"""

import dataclasses

import numpy as np
import pytest

import pmjax
from pmjax._model import ProgressiveMesh
from pmjax.builders import build_pm

TAUS = (0.5, 1.0, 4.0, np.inf)
# (scale, offset in model sizes): from 1e-12 to 1e12 and beyond, with and
# without an offset from the origin.
PLACES = [(1e-12, 0.0), (2.0 ** -40, 3.0), (1e-9, 5.0), (1e-6, 0.0), (1e3, -7.0), (1e6, 0.0), (1e9, 5.0),
          (2.0 ** 40, 0.0), (1e12, 2.0), (1e-30, 0.0), (1e30, 0.0)]


def _moved(data, scale, offset):
    """``data`` scaled about the origin, then moved by ``offset`` model sizes."""
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    size = scale * float(np.ptp(data.vertices[: data.n_original_vertices], axis=0).max())
    lengths = {k: (f64(getattr(data, k)) * scale).astype(np.float32) for k in ("radius", "delta", "mu")}
    return dataclasses.replace(data, vertices=(f64(data.vertices) * scale + offset * size).astype(np.float32),
                               **lengths)


def _cameras(data, scale, offset, n=24):
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], n)
    size = scale * float(np.ptp(data.vertices[: data.n_original_vertices], axis=0).max())
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    return pmjax.Camera(f64(cams.eye) * scale + offset * size, np.asarray(cams.rotation), np.asarray(cams.fov_y),
                        f64(cams.near) * scale, f64(cams.far) * scale, f64(cams.ortho_height) * scale,
                        np.asarray(cams.width), np.asarray(cams.height), cams.orthographic)


@pytest.fixture(scope="module")
def cow_data(built):
    return built("cow.ply")


@pytest.fixture(scope="module")
def unit_counts(cow_data):
    pm = ProgressiveMesh.from_data(cow_data)
    cams = _cameras(cow_data, 1.0, 0.0)
    return {(m, t): pmjax.refine_batch(pm, cams, t, method=m)["faces"] for m in ("dense", "front") for t in TAUS}


@pytest.mark.parametrize("scale,offset", PLACES)
@pytest.mark.slow
def test_face_counts_do_not_depend_on_scale_or_offset(cow_data, unit_counts, scale, offset):
    pm = ProgressiveMesh.from_data(_moved(cow_data, scale, offset))
    cams = _cameras(cow_data, scale, offset)
    for (method, tau), want in unit_counts.items():
        got = pmjax.refine_batch(pm, cams, tau, method=method)["faces"]
        np.testing.assert_array_equal(got, want, err_msg=f"{method}, tau={tau}")
    # One camera at a time (the eager paths), and the budget search.
    one = pmjax.index_camera(cams, 3)
    for method in ("dense", "front"):
        assert int(pmjax.refine(pm, one, 1.0, method=method).n_faces) == unit_counts[(method, 1.0)][3]
    tau, faces = pmjax.faces_for_budget(pm, one, 1000)
    assert faces <= 1000 and np.isfinite(tau)


@pytest.mark.slow
def test_power_of_two_scale_gives_the_same_bits(cow_data):
    """Exact scaling: critical tolerances, soft counts and path counts are equal, not close."""
    unit = ProgressiveMesh.from_data(cow_data)
    cams = _cameras(cow_data, 1.0, 0.0, n=8)
    one = pmjax.index_camera(cams, 1)
    for scale in (2.0 ** -60, 2.0 ** 50):
        pm = ProgressiveMesh.from_data(_moved(cow_data, scale, 0.0))
        moved = _cameras(cow_data, scale, 0.0, n=8)
        moved_one = pmjax.index_camera(moved, 1)
        np.testing.assert_array_equal(np.asarray(pmjax.critical_tau(pm.attributes, moved_one)),
                                      np.asarray(pmjax.critical_tau(unit.attributes, one)))
        assert float(pmjax.soft_refine(pm, moved_one, 1.0).faces) == float(pmjax.soft_refine(unit, one, 1.0).faces)
        np.testing.assert_array_equal(pmjax.path_counts(pm, moved, 1.0)["faces"],
                                      pmjax.path_counts(unit, cams, 1.0)["faces"])


@pytest.mark.parametrize("distance", [1e8, 1e20, 1e30])
def test_a_distant_camera_gets_the_coarsest_mesh(cow_data, distance):
    """Beyond float32's reach of the model the eye is brought in along its line:
    the model is far below a pixel, so every collapse runs (not, as an
    overflowed distance would give, none)."""
    pm = ProgressiveMesh.from_data(cow_data)
    base = pm.n_faces - int(pm.total_kills)
    cam = pmjax.look_at(eye=[0.0, 0.0, distance], target=[0.0, 0.0, 0.0], far=10.0 * distance)
    for method in ("dense", "front"):
        assert int(pmjax.refine(pm, cam, 1.0, method=method).n_faces) == base
        assert int(pmjax.refine(pm, cam, np.inf, method=method).n_faces) == base


@pytest.mark.slow
def test_the_builder_has_no_absolute_tolerance(cow_data):
    """A mesh scaled by a power of two builds the same hierarchy, its lengths scaled exactly."""
    V0 = cow_data.n_original_vertices
    vertices = cow_data.vertices[:V0].astype(np.float64)
    faces = cow_data.faces
    unit = build_pm(vertices, faces)
    for scale in (2.0 ** -40, 2.0 ** 40):
        scaled = build_pm(vertices * scale, faces)
        for name in ("v1", "v2", "batch_offsets", "killer", "alpha"):
            np.testing.assert_array_equal(getattr(scaled, name), getattr(unit, name), err_msg=name)
        for name in ("vertices", "radius", "delta", "mu"):
            np.testing.assert_array_equal(getattr(scaled, name).astype(np.float64),
                                          getattr(unit, name).astype(np.float64) * scale, err_msg=name)


@pytest.mark.slow
def test_path_budgets_and_shading_normals_do_not_depend_on_scale_or_offset(cow_data):
    """Budgets along a path (guessed word by word) give the same faces at every
    scale and offset, and the same tolerances bit for bit at a power-of-two
    scale; the fitted shading normals are the same bits at a power-of-two
    scale and within float32 rounding of the moved positions elsewhere."""
    budgets = np.tile([[400, 1500, 3000]], (40, 1))
    unit = ProgressiveMesh.from_data(cow_data)
    want = pmjax.faces_for_budget_batch(unit, _cameras(cow_data, 1.0, 0.0, n=40), budgets, path=True)
    normals = pmjax.fitted_normals(cow_data)
    for scale, offset in ((2.0 ** -40, 0.0), (2.0 ** 40, 0.0), (1e-6, 0.0), (1e6, 2.0)):
        moved = _moved(cow_data, scale, offset)
        got = pmjax.faces_for_budget_batch(ProgressiveMesh.from_data(moved), _cameras(cow_data, scale, offset, n=40),
                                           budgets, path=True)
        np.testing.assert_array_equal(got["faces"], want["faces"], err_msg=f"scale {scale}, offset {offset}")
        fitted = pmjax.fitted_normals(moved)
        if offset == 0.0 and np.log2(scale) == round(np.log2(scale)):
            np.testing.assert_array_equal(got["tau"], want["tau"])
            np.testing.assert_array_equal(fitted, normals)
        else:
            np.testing.assert_allclose(fitted, normals, atol=1e-2)
