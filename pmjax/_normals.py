"""Normals of the hierarchy: every vertex's normal from the original surface it stands for."""

from __future__ import annotations

import numpy as np

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
    V0 = pm.n_original_vertices
    vertices = np.asarray(pm.vertices, np.float64)
    faces = np.asarray(pm.faces, np.int64)
    parent = np.asarray(pm.parent)
    # Area-weighted sums around the original vertices (cross products are 2·area·normal).
    total = np.zeros_like(vertices)
    if len(faces):
        cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
        for k in range(3):
            np.add.at(total, faces[:, k], cross)
    # Up the batches: a created vertex sums its two children (children are
    # finished before their parent's batch).
    order = np.argsort(parent, kind="stable")
    consumed = order[parent[order] >= 0]
    starts = np.searchsorted(parent[consumed], pm.batch_offsets)
    for b in range(len(pm.batch_offsets) - 1):
        kids = consumed[starts[b]:starts[b + 1]]
        np.add.at(total, V0 + parent[kids], total[kids])
    length = np.linalg.norm(total, axis=1, keepdims=True)
    return (total / np.where(length > 0, length, 1.0)).astype(np.float32)
