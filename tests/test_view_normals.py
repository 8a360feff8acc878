"""Shading normals fitted per view on the mesh drawn: the batch fit's rule on
the mesh after a batch, the original mesh drawn with its stored normals,
independent of the order of the drawn vertices, and no effect on refinement."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

import pmjax
import pmjax._normals


@pytest.fixture(scope="module")
def cow(built):
    return built("cow.ply")


def _mesh_after_first_batch(data):
    """``(vertex ids, faces)`` of the mesh just after batch 0: its pcols'
    vertices collapsed, every other original vertex kept."""
    V0 = data.n_original_vertices
    n = int(data.batch_offsets[1])
    rep = np.arange(V0 + data.n_pcols)
    rep[data.v1[:n]] = V0 + np.arange(n)
    rep[data.v2[:n]] = V0 + np.arange(n)
    corners = rep[data.faces.astype(np.int64)]
    live = corners[(corners[:, 0] != corners[:, 1]) & (corners[:, 1] != corners[:, 2])
                   & (corners[:, 0] != corners[:, 2])]
    ids = np.unique(live)
    return ids, np.searchsorted(ids, live)


def test_on_the_mesh_after_a_batch_it_is_the_batch_fit(cow):
    """Started from the subtree means on the mesh just after batch 0 (whose
    created vertices are those of batch 0, the other corners original), with
    the batch fit's plain sweeps, the per-view fit is the stored fit of
    batch 0 (up to the float32 start)."""
    V0 = cow.n_original_vertices
    ids, faces = _mesh_after_first_batch(cow)
    start = pmjax.hierarchy_normals(pmjax.ProgressiveMesh.from_data(cow))
    got = pmjax.ViewNormals(cow, start, sweeps=pmjax._normals.FIT_SWEEPS, relax=1.0)(ids, faces)
    fitted = pmjax.fitted_normals(cow)
    created = ids >= V0
    assert created.sum() == int(cow.batch_offsets[1])
    np.testing.assert_allclose(got[created], fitted[ids[created]], atol=1e-6)
    np.testing.assert_array_equal(got[~created], start[ids[~created]])
    # The fit moves them: not the start.
    assert np.abs(got[created] - start[ids[created]]).max() > 1e-2


def test_the_original_mesh_keeps_its_stored_normals(cow):
    V0 = cow.n_original_vertices
    view = pmjax.ViewNormals(cow, cow.shading_normals)
    ids = np.arange(V0)
    np.testing.assert_array_equal(view(ids, cow.faces), cow.shading_normals[:V0])
    np.testing.assert_array_equal(view(ids, cow.faces, eye=[0.0, 0.0, 5.0]), cow.shading_normals[:V0])


@pytest.mark.parametrize("with_eye", [False, True])
def test_a_refinement_s_normals_are_unit_and_independent_of_vertex_order(cow, with_eye):
    V0 = cow.n_original_vertices
    pm = pmjax.ProgressiveMesh.from_data(cow)
    cam = pmjax.index_camera(pmjax.standard_orbit(cow.vertices[:V0], 4, width=320, height=240), 1)
    _, faces, ids = pmjax.refine(pm, cam, 1.0).mesh(pm)
    ids, faces = np.asarray(ids), np.asarray(faces)
    eye = np.asarray(cam.eye) if with_eye else None
    view = pmjax.ViewNormals(cow, cow.shading_normals)
    got = view(ids, faces, eye=eye)
    created = ids >= V0
    assert created.any()
    np.testing.assert_allclose(np.linalg.norm(got[created], axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(got[~created], cow.shading_normals[ids[~created]])
    assert np.abs(got[created] - cow.shading_normals[ids[created]]).max() > 1e-2
    # The same drawn mesh, its vertices and faces listed in another order.
    shuffle = np.random.default_rng(0).permutation(len(ids))
    moved = np.empty_like(shuffle)
    moved[shuffle] = np.arange(len(ids))
    again = view(ids[shuffle], moved[faces][np.random.default_rng(1).permutation(len(faces))], eye=eye)
    np.testing.assert_allclose(again[moved], got, atol=1e-6)
    # From a ProgressiveMesh as from its PMData: the same bits.
    np.testing.assert_array_equal(pmjax.ViewNormals(pm, cow.shading_normals)(ids, faces, eye=eye), got)


def test_the_eye_weights_the_samples_by_the_area_seen(cow):
    """An eye changes the fit; one far away in a direction weights samples by
    their facing toward it alone (the distance then nearly the same for all),
    so moving it farther along that direction hardly changes the normals."""
    V0 = cow.n_original_vertices
    pm = pmjax.ProgressiveMesh.from_data(cow)
    cam = pmjax.index_camera(pmjax.standard_orbit(cow.vertices[:V0], 4, width=320, height=240), 2)
    _, faces, ids = pmjax.refine(pm, cam, 1.0).mesh(pm)
    view = pmjax.ViewNormals(cow, cow.shading_normals)
    plain = view(ids, faces)
    center = cow.vertices[:V0].mean(axis=0)
    direction = np.asarray(cam.eye) - center
    far, farther = (view(ids, faces, eye=center + k * direction) for k in (1e4, 1e5))
    assert np.abs(far - plain).max() > 1e-2
    np.testing.assert_allclose(far, farther, atol=1e-3)


def test_bad_arguments_are_refused(cow):
    V = cow.n_original_vertices + cow.n_pcols
    with pytest.raises(ValueError, match="normals must be"):
        pmjax.ViewNormals(cow, cow.shading_normals[:-1])
    view = pmjax.ViewNormals(cow, cow.shading_normals)
    with pytest.raises(ValueError, match="vertex ids"):
        view([0, 1, V], [[0, 1, 2]])
    with pytest.raises(ValueError, match="faces must index"):
        view([0, 1, 2], [[0, 1, 3]])
    for eye in ([0.0, 0.0], [0.0, np.nan, 1.0], [np.inf, 0.0, 0.0]):
        with pytest.raises(ValueError, match="eye must be"):
            view([0, 1, 2], [[0, 1, 2]], eye=eye)


def _refinement_meshes(cow, taus=(1.0, 4.0)):
    """``(ids, faces, eye)`` of a few orbit views' refinements of the cow."""
    V0 = cow.n_original_vertices
    pm = pmjax.ProgressiveMesh.from_data(cow)
    cams = pmjax.standard_orbit(cow.vertices[:V0], 6, width=320, height=240)
    meshes = []
    for i, tau in zip(range(0, 6, 2), [*taus, taus[0]]):
        cam = pmjax.index_camera(cams, i)
        _, faces, ids = pmjax.refine(pm, cam, tau).mesh(pm)
        meshes.append((np.asarray(ids), np.asarray(faces), np.asarray(cam.eye)))
    return meshes


def _native_or_skip():
    import pmjax._normals

    if pmjax._normals.native is None:
        if os.environ.get("PMJAX_REQUIRE_CORE") == "1":
            pytest.fail("pmjax._normals_native is not built (python setup.py build_ext --inplace)")
        pytest.skip("the fit's C loops (pmjax._normals_native) are not built")


def _by_numpy(monkeypatch, view, *args, **kwargs):
    import pmjax._normals

    with monkeypatch.context() as m:
        m.setattr(pmjax._normals, "native", None)
        return view(*args, **kwargs)


@pytest.mark.parametrize("snap", [False, True])
def test_the_c_loops_give_the_numpy_bits(cow, monkeypatch, snap):
    """The C loops (a created vertex's samples: the run of its leaves) and
    NumPy (a climb from every original vertex) give the same bits: on
    refinements of the cow at two taus, with and without an eye, with two and
    five plain sweeps and three weighted ones, every step split over one, two
    and three threads; also on
    the cow with its coordinates snapped to a coarse grid (degenerate faces,
    equally deep faces)."""
    import pmjax._normals

    _native_or_skip()
    data = dataclasses.replace(cow, vertices=np.round(cow.vertices * 8.0) / 8.0) if snap else cow
    for sweeps, relax in ((2, 1.0), (5, 1.0), (3, 0.6)):
        view = pmjax.ViewNormals(data, cow.shading_normals, sweeps=sweeps, relax=relax)
        for ids, faces, eye in _refinement_meshes(cow):
            for at in (None, eye):
                expected = _by_numpy(monkeypatch, view, ids, faces, eye=at)
                assert view._native(ids, faces, at) is not None  # the C loops take it
                for threads in (1, 2, 3):
                    monkeypatch.setattr(pmjax._normals, "FIT_THREADS", threads)
                    monkeypatch.setattr(pmjax._normals, "FIT_MIN_SPLIT", 1)
                    got = view(ids, faces, eye=at)
                    assert got.dtype == np.float32 and got.tobytes() == expected.tobytes()


def test_ids_that_are_not_a_front_go_to_numpy_with_its_bits(cow, monkeypatch):
    """A drawn vertex listed with its parent, or twice: not a front of the
    hierarchy, so the C loops hand it to NumPy (the same answer as with
    them switched off)."""
    _native_or_skip()
    V0 = cow.n_original_vertices
    ids, faces, eye = _refinement_meshes(cow)[0]
    view = pmjax.ViewNormals(cow, cow.shading_normals)
    parent = np.full(V0 + cow.n_pcols, -1, np.int64)
    parent[cow.v1], parent[cow.v2] = np.arange(cow.n_pcols), np.arange(cow.n_pcols)
    child = int(ids[(ids >= V0) | (parent[ids] >= 0)][0])
    extra = np.concatenate([ids, [V0 + parent[child]]]) if parent[child] >= 0 else np.concatenate([ids, [child]])
    for bad in (extra, np.concatenate([ids, ids[:1]])):
        assert view._native(bad, faces, eye) is None
        np.testing.assert_array_equal(view(bad, faces, eye=eye), _by_numpy(monkeypatch, view, bad, faces, eye=eye))


def test_sweeps_and_relax_move_the_fit_and_bad_ones_are_refused(cow):
    ids, faces, eye = _refinement_meshes(cow)[0]
    plain = pmjax.ViewNormals(cow, cow.shading_normals, sweeps=2, relax=1.0)(ids, faces, eye=eye)
    eight = pmjax.ViewNormals(cow, cow.shading_normals, sweeps=8, relax=1.0)(ids, faces, eye=eye)
    relaxed = pmjax.ViewNormals(cow, cow.shading_normals, sweeps=2, relax=0.5)(ids, faces, eye=eye)
    assert np.abs(plain - eight).max() > 1e-3 and np.abs(plain - relaxed).max() > 1e-3
    for bad in (0, -1, 2.5, True, "2"):
        with pytest.raises(ValueError, match="sweeps must be"):
            pmjax.ViewNormals(cow, cow.shading_normals, sweeps=bad)
    for bad in (0, 0.0, -0.5, 1.5, float("nan"), True, "1"):
        with pytest.raises(ValueError, match="relax must be"):
            pmjax.ViewNormals(cow, cow.shading_normals, relax=bad)
