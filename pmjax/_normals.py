"""Normals of the hierarchy: every vertex's normal from the original surface it stands for."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the builder imports this module without JAX
    from ._model import ProgressiveMesh


def hierarchy_normals(pm: ProgressiveMesh) -> np.ndarray:
    """Unit normal of every vertex, original and created: the area-weighted
    normal of the original faces around the original vertices it replaces.

    Shading a coarse vertex with the normal of the fine surface it stands for
    keeps a refined mesh's shading close to the original's (appearance
    preservation), and the normals, like positions, blend along ancestor
    chains for geomorphs (:func:`pmjax.geomorph_mesh`).

    Returns:
        ``float32[V0 + P, 3]`` (zero for a vertex with no faces around it).
    """
    V0, vertices, faces, parent, offsets = _hierarchy_arrays(pm)
    total = _area_normal_sums(vertices, faces)
    # Up the batches: a created vertex sums its two children (children are
    # finished before their parent's batch).
    for kids in _consumed_by_batch(parent, offsets):
        np.add.at(total, V0 + parent[kids], total[kids])
    return _unit(total).astype(np.float32)


# Weight of the 1-ring in the fitted normal: n = (1 - SHARPEN) * own + SHARPEN *
# ring mean, with SHARPEN < 0. Interpolating vertex normals across a face
# averages each vertex's normal with its neighbours' (the hat functions
# overlap), so the least-squares fit of vertex values to a surface's normals
# undoes part of that averaging: it moves each value away from its
# neighbours' mean. -0.2 is the one-step approximation of that fit measured
# best on the bunny's standard orbit at tau 1 (docs/render.md).
SHARPEN = -0.2


def _hierarchy_arrays(pm):
    """``(V0, vertices f64, faces i64, parent, batch_offsets)`` of a
    :class:`pmjax.PMData` or a :class:`pmjax.ProgressiveMesh` (``parent[x]``:
    the pcol consuming vertex ``x``, -1 if none)."""
    V0 = int(pm.n_original_vertices)
    vertices = np.asarray(pm.vertices, np.float64)
    faces = np.asarray(pm.faces, np.int64)
    offsets = np.asarray(pm.batch_offsets, np.int64)
    if hasattr(pm, "v1"):
        parent = np.full(len(vertices), -1, np.int64)
        parent[np.asarray(pm.v1)] = np.arange(len(pm.v1))
        parent[np.asarray(pm.v2)] = np.arange(len(pm.v2))
    else:
        parent = np.asarray(pm.parent, np.int64)
    return V0, vertices, faces, parent, offsets


def _area_normal_sums(vertices, faces) -> np.ndarray:
    """``[V, 3]`` per vertex the sum of its faces' cross products (2·area·normal)."""
    total = np.zeros_like(vertices)
    if len(faces):
        cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
        for k in range(3):
            np.add.at(total, faces[:, k], cross)
    return total


def _consumed_by_batch(parent, offsets) -> list:
    """Per batch, the vertices its pcols consume (``parent`` in the batch)."""
    order = np.argsort(parent, kind="stable")
    consumed = order[parent[order] >= 0]
    starts = np.searchsorted(parent[consumed], offsets)
    return [consumed[starts[b]:starts[b + 1]] for b in range(len(offsets) - 1)]


def _unit(n: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def fitted_normals(pm) -> np.ndarray:
    """Shading normal of every vertex, fitted to the original surface it stands for.

    Rule: an original vertex keeps its area-weighted vertex normal. A created
    vertex ``u`` starts from the area-weighted mean normal of the original
    faces with a corner in its subtree, each face weighted by its area and by
    the share of its corners in the subtree (:func:`hierarchy_normals`); that
    mean is then moved away from the mean of the same normals over ``u``'s
    neighbours in the mesh just after ``u``'s batch
    (``n = (1 - SHARPEN) * mean_u + SHARPEN * ring mean``, :data:`SHARPEN`),
    the one-step least-squares correction for interpolation across faces
    averaging neighbouring vertex normals. Computed in one pass up the
    hierarchy, batch by batch (children before parents), vectorized per batch.

    Args:
        pm: a :class:`pmjax.PMData` or :class:`pmjax.ProgressiveMesh`.

    Returns:
        ``float32[V0 + P, 3]``, unit (zero for a vertex with no face area
        below it).
    """
    V0, vertices, faces, parent, offsets = _hierarchy_arrays(pm)
    total = _area_normal_sums(vertices, faces)
    consumed = _consumed_by_batch(parent, offsets)
    # rep[x]: the vertex that stands for x after the current batch (x itself
    # until consumed); corners: the live faces' corners after the batch.
    rep = np.arange(len(vertices))
    corners = faces
    base = _unit(total)  # the subtree means, updated batch by batch
    out = base.copy()
    for b in range(len(offsets) - 1):
        kids = consumed[b]
        np.add.at(total, V0 + parent[kids], total[kids])
        lo, hi = V0 + offsets[b], V0 + offsets[b + 1]
        base[lo:hi] = _unit(total[lo:hi])
        rep[kids] = V0 + parent[kids]
        corners = rep[corners]
        alive = (corners[:, 0] != corners[:, 1]) & (corners[:, 1] != corners[:, 2]) & (corners[:, 0] != corners[:, 2])
        corners = corners[alive]
        ring = np.zeros((hi - lo, 3))
        seen = np.zeros(hi - lo)
        for k in range(3):
            new = corners[:, k] >= lo
            slot = corners[new, k] - lo
            np.add.at(ring, slot, base[corners[new, (k + 1) % 3]] + base[corners[new, (k + 2) % 3]])
            np.add.at(seen, slot, 2.0)
        fitted = base[lo:hi].copy()
        has = seen > 0
        fitted[has] = (1.0 - SHARPEN) * fitted[has] + SHARPEN * ring[has] / seen[has, None]
        out[lo:hi] = _unit(fitted)
    return out.astype(np.float32)
