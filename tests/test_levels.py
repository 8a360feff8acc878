"""Dependency levels of the pcol forest, and refinement's independence of the schedule."""

import dataclasses

import numpy as np

import pmjax
from pmjax._camera import index_camera

# The PMData arrays with one entry per pcol (besides v1, v2).
PER_PCOL = ("radius", "alpha", "delta", "mu", "cost", "metric")


def reference_levels(data):
    """Plain recursion over the pcols in order: 1 + the higher child level."""
    V0 = data.n_original_vertices
    level = {}
    for p in range(data.n_pcols):
        kids = [int(v) - V0 for v in (data.v1[p], data.v2[p]) if v >= V0]
        level[p] = 1 + max((level[k] for k in kids), default=0)
    return np.array([level[p] for p in range(data.n_pcols)], np.int32)


def test_levels_equal_the_recursion_and_are_tight(built):
    for name in ("cow.ply", "bunny.ply"):
        data = built(name)
        levels = pmjax.dependency_levels(data)
        assert levels.dtype == np.int32 and levels.shape == (data.n_pcols,)
        assert np.array_equal(levels, reference_levels(data))
        height = int(levels.max())
        # Fewer steps than batches: the builder's batches are finer than the
        # dependencies.
        assert 1 <= height < data.n_batches
        # Tight: every pcol above level 1 has a child exactly one level lower,
        # so a chain of `height` pcols exists and no schedule needs fewer steps.
        V0 = data.n_original_vertices
        kid = lambda v: np.where(v >= V0, levels[np.maximum(v - V0, 0)], 0)
        assert np.array_equal(np.maximum(kid(data.v1), kid(data.v2)), levels - 1)


def test_single_triangle_and_no_pcols():
    from pmjax.builders import build_pm

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    data = build_pm(v, np.array([[0, 1, 2]], np.int32))
    # One pcol of two original vertices; the third vertex is left alone.
    assert data.n_pcols == 1 and pmjax.dependency_levels(data).tolist() == [1]
    empty = dataclasses.replace(data, vertices=v, normals=data.normals[:3], v1=data.v1[:0], v2=data.v2[:0],
                                batch_offsets=np.zeros(1, np.int64), killer=np.full(1, -1, np.int32),
                                **{k: getattr(data, k)[:0] for k in PER_PCOL})
    assert pmjax.dependency_levels(empty).shape == (0,)


def level_ordered(data):
    """The same forest with pcols sorted by level, each level one 'batch'."""
    V0, P = data.n_original_vertices, data.n_pcols
    levels = pmjax.dependency_levels(data)
    order = np.argsort(levels, kind="stable")
    new = np.empty(P, np.int64)
    new[order] = np.arange(P)
    vertex = np.concatenate([np.arange(V0), V0 + new])
    per_pcol = {k: getattr(data, k)[order] for k in PER_PCOL}
    return dataclasses.replace(
        data,
        vertices=np.concatenate([data.vertices[:V0], data.vertices[V0:][order]]),
        normals=np.concatenate([data.normals[:V0], data.normals[V0:][order]]),
        v1=vertex[data.v1[order]].astype(np.int32),
        v2=vertex[data.v2[order]].astype(np.int32),
        killer=np.where(data.killer >= 0, new[np.maximum(data.killer, 0)], -1).astype(np.int32),
        batch_offsets=np.concatenate([[0], np.cumsum(np.bincount(levels)[1:])]).astype(np.int64),
        **per_pcol,
    ), order


def test_refinement_depends_on_the_forest_not_the_schedule(built):
    """Refined by levels (fewer, larger steps) or by batches, the executed set
    is the same, up to the renumbering, and so are the counts and the faces."""
    data = built("bunny.ply")
    by_level, order = level_ordered(data)
    assert by_level.n_batches == pmjax.dependency_levels(data).max() < data.n_batches
    pm, pm_level = pmjax.ProgressiveMesh.from_data(data), pmjax.ProgressiveMesh.from_data(by_level)
    cams = pmjax.random_views(data.vertices[: data.n_original_vertices], 12, seed=3, min_scale=0.5, max_scale=3)
    V0 = data.n_original_vertices
    for i in range(12):
        cam = index_camera(cams, i)
        a, b = pmjax.refine(pm, cam, 1.0), pmjax.refine(pm_level, cam, 1.0)
        assert np.array_equal(np.asarray(a.executed)[order], np.asarray(b.executed))
        assert (int(a.n_faces), int(a.n_vertices)) == (int(b.n_faces), int(b.n_vertices))
        # The same faces, on the same vertices once renumbered to the file's ids.
        _, fa, ida = a.mesh(pm)
        _, fb, idb = b.mesh(pm_level)
        idb = np.where(idb >= V0, V0 + order[np.maximum(idb - V0, 0)], idb)
        faces = lambda ids, f: np.unique(np.sort(ids[f], axis=1), axis=0)
        assert len(fa) == len(fb) and np.array_equal(faces(ida, fa), faces(idb, fb))
