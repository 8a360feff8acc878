"""Evaluation columns: compilation is timed apart from refinement, camera
context on request, and the dataset folder read by name by the common
Parquet readers."""

from __future__ import annotations

import numpy as np
import pytest

import pmjax
from pmjax._eval import evaluate

pa = pytest.importorskip("pyarrow")
ds = pytest.importorskip("pyarrow.dataset")

DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
                 "vertices", "executed"]


@pytest.fixture(scope="module")
def cow(built, tmp_path_factory):
    path = str(tmp_path_factory.mktemp("models") / "cow.pmz")
    pmjax.save_pm(built("cow.ply"), path)
    return path


def table(folder):
    return ds.dataset(folder, format="parquet").to_table()


@pytest.mark.parametrize("kind", ["tau", "budget"])
def test_compilation_is_timed_apart_from_refinement(cow, tmp_path, kind):
    """A cold process compiles on its first part: that time goes to
    compile_ms on the part's first row, not into refine_ms; a warm process
    compiles nothing (compile_ms 0) and gives the same rows."""
    import jax

    # A random set (no paths: batched calls) in parts of `chunk` cameras.
    chunk = 4 if kind == "budget" else 100
    job = dict(taus=[1.0]) if kind == "tau" else dict(budgets=[500])
    n = 8 if kind == "budget" else 300
    pmjax._eval._LOADED.clear()
    jax.clear_caches()
    got = {}
    for run in ("cold", "warm"):
        evaluate([cow], [f"random:{n}:1"], str(tmp_path / run), chunk=chunk, compile_cache=None, progress=False,
                 **job)
        got[run] = table(str(tmp_path / run))
    cold, warm = (got[r].column("compile_ms").to_numpy() for r in ("cold", "warm"))
    refine = got["cold"].column("refine_ms").to_numpy()
    # Only a part's first row carries its warm-up; the first part compiles, the others reuse its kernels.
    assert np.all(cold[1:] == 0) and np.all(warm == 0)
    # Compilation takes far longer than refining a part's cameras: none of it is in refine_ms.
    assert cold[0] > 10 * refine[:chunk].sum(), (cold[0], refine[:chunk])
    for c in DETERMINISTIC:
        assert got["cold"].column(c).to_pylist() == got["warm"].column(c).to_pylist(), c


def test_camera_columns_on_request(cow, tmp_path):
    """With camera_columns, each row carries its camera's eye, distance to
    the model's box centre (model units and bounding radii), field of view
    and image size, equal to the cameras generated for the set; the setting
    is part of the job."""
    data = pmjax.read_pm(cow)
    v0 = np.asarray(data.vertices[: data.n_original_vertices], np.float64)
    lo, hi = v0.min(0), v0.max(0)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    out = str(tmp_path / "cams")
    evaluate([cow], ["orbit:40", pmjax.camera_set("random:50:3", width=320, height=200, fov_y_deg=60)], out,
             taus=[1.0], chunk=32, compile_cache=None, progress=False, camera_columns=True)
    got = table(out)
    assert got.schema.names[-8:] == ["eye_x", "eye_y", "eye_z", "distance", "distance_radii", "fov_y_deg", "width",
                                     "height"]
    eye = np.stack([got.column(c).to_numpy() for c in ("eye_x", "eye_y", "eye_z")], 1)
    expect = np.concatenate([np.asarray(pmjax.standard_orbit(v0, 40).eye),
                             np.asarray(pmjax.random_views(v0, 50, seed=3).eye)])
    assert np.allclose(eye, expect, rtol=1e-6, atol=1e-6 * radius)
    distance = got.column("distance").to_numpy()
    assert np.allclose(distance, np.linalg.norm(eye - centre, axis=1), rtol=1e-12)
    assert np.allclose(got.column("distance_radii").to_numpy(), distance / radius, rtol=1e-12)
    # The standard orbit is at r / sin 22.5 degrees; random views within [0.05, 4] r of a point near the centre.
    assert np.allclose(got.column("distance_radii").to_numpy()[:40], 1 / np.sin(np.radians(22.5)))
    assert got.column("fov_y_deg").to_pylist() == pytest.approx([45.0] * 40 + [60.0] * 50)
    assert got.column("width").to_pylist() == [800] * 40 + [320] * 50
    assert got.column("height").to_pylist() == [600] * 40 + [200] * 50
    # Without the flag the folder holds another job.
    with pytest.raises(pmjax.EvalError, match="holds another job .*camera_columns"):
        evaluate([cow], ["orbit:40", pmjax.camera_set("random:50:3", width=320, height=200, fov_y_deg=60)], out,
                 taus=[1.0], chunk=32, compile_cache=None, progress=False)
    with pytest.raises(pmjax.EvalError, match="camera_columns must be True or False, not 'yes'"):
        evaluate([cow], ["orbit:40"], out, taus=[1.0], camera_columns="yes", progress=False)
    # Orthographic cameras have no field of view: null there.
    from pmjax._eval import _camera_context

    t = pmjax._camera_table.CameraTable(
        eye=np.array([[0.0, 0.0, 5.0], [3.0, 4.0, 0.0]]), rotation=np.tile(np.eye(3), (2, 1, 1)),
        fov_y=np.radians([30.0, 45.0]), near=np.ones(2), far=np.full(2, 9.0), ortho_height=np.ones(2),
        width=np.array([640, 800], np.int32), height=np.array([480, 600], np.int32),
        orthographic=np.array([False, True]))
    context = _camera_context(t, (0.0, 0.0, 0.0), 2.5)
    assert context["fov_y_deg"].to_pylist()[0] == pytest.approx(30.0) and context["fov_y_deg"].to_pylist()[1] is None
    assert context["distance"].to_pylist() == [5.0, 5.0] and context["distance_radii"].to_pylist() == [2.0, 2.0]
