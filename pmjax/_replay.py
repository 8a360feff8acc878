"""Replaying pcols on the host: discrete LODs and the reference semantics.

Executing a prefix of the pcol order is always legal (a pcol's vertices are
made by earlier batches), so the mesh after ``n`` pcols is fully described by
``killer`` (faces whose killer ran are gone) and by the representative of
every vertex (follow the consuming pcol while it ran).
"""

from __future__ import annotations

import numpy as np

from ._pmfile import PMData


def parents(pm: PMData) -> np.ndarray:
    """``int64[V0 + P]``: the vertex made by the pcol consuming each vertex, or -1."""
    V0, P = pm.n_original_vertices, pm.n_pcols
    parent = np.full(V0 + P, -1, np.int64)
    parent[pm.v1] = V0 + np.arange(P)
    parent[pm.v2] = V0 + np.arange(P)
    return parent


def representatives(pm: PMData, executed: np.ndarray) -> np.ndarray:
    """Current representative of every vertex for a downward-closed executed set.

    Args:
        pm: the progressive mesh.
        executed: ``bool[P]``; if a pcol ran, the pcols making its vertices ran.

    Returns:
        ``int64[V0 + P]``: ``rep(v) = rep(parent(v))`` if the pcol consuming
        ``v`` ran, else ``v`` (docs/design.md).
    """
    V0 = pm.n_original_vertices
    parent = parents(pm)
    up = np.where(parent >= 0, parent, np.arange(len(parent)))
    ran = np.zeros(len(parent), bool)
    ran[parent >= 0] = executed[parent[parent >= 0] - V0]
    rep = np.where(ran, up, np.arange(len(parent)))
    # Pointer jumping: each pass doubles the climbed distance.
    while True:
        nxt = rep[rep]
        if np.array_equal(nxt, rep):
            return rep
        rep = nxt


def active_faces(pm: PMData, executed: np.ndarray) -> np.ndarray:
    """``bool[F]``: faces whose killer did not run."""
    # Index -1 (no killer) reads the appended False: drawn. Also right with no pcols.
    return ~np.append(np.asarray(executed, bool), False)[pm.killer]


def mesh_for_executed(pm: PMData, executed: np.ndarray):
    """The refined mesh for an executed set, compacted to used vertices.

    Returns:
        ``(vertices float32[n, 3], faces int32[m, 3], vertex_ids int64[n])``,
        ``vertex_ids`` being the PM vertex id of each output vertex.
    """
    rep = representatives(pm, executed)
    faces = rep[pm.faces[active_faces(pm, executed)]]
    ids, inverse = np.unique(faces, return_inverse=True)
    return pm.vertices[ids], inverse.reshape(-1, 3).astype(np.int32), ids


def prefix_executed(pm: PMData, n: int) -> np.ndarray:
    """``bool[P]`` with the first ``n`` pcols executed."""
    if not 0 <= n <= pm.n_pcols:
        raise ValueError(f"prefix length {n} outside [0, {pm.n_pcols}]")
    executed = np.zeros(pm.n_pcols, bool)
    executed[:n] = True
    return executed


def lod_mesh(pm: PMData, batch: int):
    """Discrete LOD after batches ``0..batch`` (``-1``: the original mesh).

    Returns:
        ``(vertices, faces, vertex_ids)`` as :func:`mesh_for_executed`.
    """
    if not -1 <= batch < pm.n_batches:
        raise ValueError(f"batch {batch} outside [-1, {pm.n_batches - 1}] (the file has {pm.n_batches} batches)")
    return mesh_for_executed(pm, prefix_executed(pm, int(pm.batch_offsets[batch + 1])))


def pcols_for_faces(pm: PMData, target_faces: int) -> int:
    """Smallest pcol prefix whose mesh has at most ``target_faces`` faces
    (all pcols if the base mesh has more)."""
    kills = pm.kills
    left = len(pm.faces) - np.cumsum(kills)
    return int(min(np.searchsorted(-left, -target_faces) + 1, pm.n_pcols)) if target_faces < len(pm.faces) else 0
