"""GeMS error metrics: each gives a cost and a placement per candidate pair.

| metric               | cost                                        | placement          |
|----------------------|---------------------------------------------|--------------------|
| quadric              | memory-resident Garland–Heckbert quadric    | optimal, fallback  |
| quadric-memoryless   | quadric rebuilt from the current faces      | optimal, fallback  |
| edge                 | pair length                                 | fixed midpoint     |
| pm                   | distance (memoryless quadric) + spring      | subset (v1 or v2)  |
| hybrid               | unsigned swept volume × max normal change   | subset (v1 or v2)  |
"""

from __future__ import annotations

import numpy as np

from . import _native as native
from . import _quadrics as qd
from ._threads import split_rows
from ._topology import VertexFaces

METRIC_NAMES = ("quadric", "quadric-memoryless", "edge", "pm", "hybrid")
# Metrics whose cost depends only on the pair's own endpoints (ids unchanged
# means cost unchanged), so the builder may reuse last batch's values.
CACHEABLE = ("quadric", "edge")

# Hoppe's spring constant, relative to the mean face area (keeps units of the
# distance term, area × length²).
SPRING = 1e-2


def evaluate_metric(
    metric: str,
    pos: np.ndarray,
    faces: np.ndarray,
    quadric: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    boundary_weight: float,
):
    """Cost and placement of collapsing each pair ``(a[i], b[i])``.

    Args:
        metric: one of :data:`METRIC_NAMES`.
        pos: ``(N, 3)`` positions of all vertex ids, float64, model units.
        faces: ``(F, 3)`` current faces.
        quadric: ``(N, 10)`` memory-resident quadrics (used by ``quadric``).
        a, b: candidate pairs.
        boundary_weight: weight of boundary planes in rebuilt quadrics.

    Returns:
        ``(placement (C, 3), cost (C,))``, cost ``>= 0``.
    """
    if metric == "quadric":
        # Gathers included: the halves also fetch their own rows in parallel.
        if native.available():
            return native.quadric_placement(quadric, pos, a, b)
        return split_rows(lambda a, b: qd.optimal_placement(quadric[a] + quadric[b], pos[a], pos[b]), a, b)
    pa, pb = pos[a], pos[b]
    if metric == "edge":
        return 0.5 * (pa + pb), np.linalg.norm(pb - pa, axis=1)
    if metric in ("quadric-memoryless", "pm"):
        # GeMS memoryless: quadrics of the faces as they are now.
        q = qd.vertex_quadrics(pos, faces, len(pos), boundary_weight)
        qab = q[a] + q[b]
        if metric == "quadric-memoryless":
            return qd.optimal_placement(qab, pa, pb)
        x, dist = qd.subset_placement(qab, pa, pb)
        _, area, _ = qd.face_geometry(pos, faces)
        spring = SPRING * area.mean() * np.einsum("ij,ij->i", pb - pa, pb - pa)
        return x, dist + spring
    if metric == "hybrid":
        return _hybrid(pos, faces, a, b)
    raise ValueError(f"unknown metric {metric!r}; choose from {', '.join(METRIC_NAMES)}")


def _hybrid(pos, faces, a, b):
    """GeMS E_hybrid: unsigned tetra volume swept × maximum normal deviation."""
    vf = VertexFaces(faces, len(pos))
    pair, face = vf.of_pairs(a, b)
    tri = faces[face]
    unit, _, cross = qd.face_geometry(pos, tri)
    stays = ~(np.any(tri == a[pair, None], 1) & np.any(tri == b[pair, None], 1))
    best_cost = np.full(len(a), np.inf)
    best = pos[a].copy()
    for target in (a, b):
        x = pos[target]
        moved = np.where((tri == a[pair, None]) | (tri == b[pair, None]), -1, tri)
        corners = np.where((moved >= 0)[..., None], pos[np.maximum(moved, 0)], x[pair, None, :])
        new_cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        # Volume between the old face and the moved vertex: |n·(x − p0)| / 6.
        vol = np.abs(np.einsum("ij,ij->i", cross, x[pair] - pos[tri[:, 0]])) / 6.0
        new_len = np.linalg.norm(new_cross, axis=1)
        cos = np.einsum("ij,ij->i", unit, new_cross) / np.where(new_len > 0, new_len, 1.0)
        deviation = np.where(stays, 1.0 - np.clip(cos, -1.0, 1.0), 0.0)
        volume = np.bincount(pair, np.where(stays, vol, 0.0), minlength=len(a))
        max_dev = np.zeros(len(a))
        np.maximum.at(max_dev, pair, deviation)
        cost = volume * max_dev
        better = cost < best_cost
        best[better] = x[better]
        best_cost = np.where(better, cost, best_cost)
    return best, best_cost
