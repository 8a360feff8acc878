"""Hierarchies with no pcol and with one: every reader and engine works on
them and agrees with the sequential oracle."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import pmjax
from pmjax.builders import BuildOptions, build_pm


@pytest.fixture(scope="module", params=["none", "one"])
def tiny(request, data_path, tmp_path_factory):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    options = BuildOptions(target_vertices=len(v)) if request.param == "none" else \
        BuildOptions(target_vertices=len(v) - 1, linear=True)
    data = build_pm(v, f, options)
    assert data.n_pcols == (0 if request.param == "none" else 1)
    path = str(tmp_path_factory.mktemp("tiny") / f"{request.param}.pmz")
    pmjax.save_pm(data, path)
    return path, pmjax.read_pm(path)


def test_readers(tiny):
    path, data = tiny
    pmjax.check_invariants(data)
    assert pmjax.dependency_levels(data).shape == (data.n_pcols,)
    v, f, _ = pmjax.lod_mesh(data, -1)
    assert len(f) == len(data.faces)
    v, f, _ = pmjax.lod_mesh(data, data.n_batches - 1)
    assert len(f) == len(data.faces) - int(data.n_pcols > 0) * int((data.killer >= 0).sum())


@pytest.mark.slow
def test_engines_agree_with_the_oracle(tiny):
    path, data = tiny
    pm = pmjax.load(path)
    v0 = data.vertices[: data.n_original_vertices]
    cams = pmjax.random_views(v0, 6, seed=2, min_scale=0.05, max_scale=20)
    for tau in (0.0, 1.0, 1e6):
        batch = {m: pmjax.refine_batch(pm, cams, tau, method=m) for m in ("dense", "front")}
        for i in range(6):
            cam = pmjax.index_camera(cams, i)
            executed, faces = pmjax.oracle_refine(data, np.asarray(pmjax.collapse_mask(pm.attributes, cam, np.float32(tau))))
            for method in ("dense", "front"):
                r = pmjax.refine(pm, cam, tau, method=method)
                assert np.array_equal(np.asarray(r.executed), executed)
                assert int(r.n_faces) == len(faces) == batch[method]["faces"][i]
                assert int(r.n_executed) == executed.sum() == batch[method]["executed_count"][i]
                vertices, mesh_faces, ids = r.mesh()
                assert np.array_equal(ids[mesh_faces], faces)
    if data.n_pcols == 0:
        # Nothing to refine: the original mesh, whatever the view.
        assert int(r.n_vertices) == data.n_original_vertices and len(mesh_faces) == len(data.faces)
    tau, n = pmjax.faces_for_budget(pm, pmjax.index_camera(cams, 0), 10)
    assert n <= len(data.faces)
    soft = pmjax.soft_refine(pm, pmjax.index_camera(cams, 0), 1.0, 0.1)
    assert np.isfinite(float(soft.faces))
