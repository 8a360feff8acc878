"""Deep checks of the hierarchy rules of docs/format.md (beyond :func:`validate_pm`).

:func:`check_invariants` recomputes what the builder claims, by other means:

- ``killer`` from the vertex forest alone: two corners of a face merge at the
  lowest common ancestor of the two, so a face's killer is the lowest such
  pcol over its three corner pairs;
- batch independence on the mesh as it is when the batch starts;
- monotone attributes: each pcol's sphere contains its children's spheres
  (hence every original vertex below), its cone contains theirs, and its
  deviations are at least theirs.
"""

from __future__ import annotations

import numpy as np

from ._pmfile import PMData, PMFormatError, validate_pm
from ._structure import CONE_SLACK, sphere_slack
from ._replay import parents, prefix_executed, representatives


def direct_killers(pm: PMData) -> np.ndarray:
    """``int32[F]``: per face, the first pcol merging two of its corners (-1: none)."""
    V0 = pm.n_original_vertices
    parent = parents(pm)
    best = np.full(len(pm.faces), np.iinfo(np.int64).max)
    for i, j in ((0, 1), (1, 2), (0, 2)):
        u = pm.faces[:, i].astype(np.int64)
        w = pm.faces[:, j].astype(np.int64)
        # Climb the lower id (ids grow up the forest) until the chains meet.
        while True:
            moving = (u != w) & (parent[np.minimum(u, w)] >= 0)
            if not moving.any():
                break
            lower_u = moving & (u < w)
            lower_w = moving & (w < u)
            u = np.where(lower_u, parent[u], u)
            w = np.where(lower_w, parent[w], w)
        met = u == w
        best = np.where(met, np.minimum(best, u - V0), best)
    return np.where(best == np.iinfo(np.int64).max, -1, best).astype(np.int32)


def check_invariants(pm: PMData) -> None:
    """Raise :class:`PMFormatError` naming the first broken invariant.

    The slow, independent twin of :func:`pmjax.check_structure` (which every
    load runs): it replays the hierarchy batch by batch. Containment tests
    allow the float32 rounding of the stored values
    (:func:`pmjax._structure.sphere_slack`, ``CONE_SLACK`` radians).
    """
    validate_pm(pm)
    V0 = pm.n_original_vertices
    P = pm.n_pcols
    x = pm.vertices.astype(np.float64)
    n = pm.normals.astype(np.float64)

    killers = direct_killers(pm)
    bad = np.flatnonzero(killers != pm.killer)
    if len(bad):
        f = int(bad[0])
        raise PMFormatError(f"face {f}: killer {int(pm.killer[f])} but its corners first merge at pcol {int(killers[f])}")

    # Batch independence: at the start of each batch, no face touches the
    # endpoints of two different pcols of that batch.
    owner = np.full(V0 + P, -1, np.int64)
    for b in range(pm.n_batches):
        lo, hi = int(pm.batch_offsets[b]), int(pm.batch_offsets[b + 1])
        executed = prefix_executed(pm, lo)
        rep = representatives(pm, executed)
        alive = (pm.killer < 0) | (pm.killer >= lo)
        cur = rep[pm.faces[alive]]
        ids = np.arange(lo, hi)
        for name in ("v1", "v2"):
            v = getattr(pm, name)[ids]
            if np.any(rep[v] != v):
                raise PMFormatError(f"batch {b}: pcol uses a vertex already consumed")
        owner[pm.v1[ids]] = ids
        owner[pm.v2[ids]] = ids
        o = owner[cur]
        touched = np.where(o >= 0, o, np.iinfo(np.int64).max)
        lo_owner = touched.min(axis=1)
        hi_owner = o.max(axis=1)
        clash = (hi_owner >= 0) & (lo_owner != hi_owner)
        if clash.any():
            f = int(np.flatnonzero(clash)[0])
            raise PMFormatError(
                f"batch {b}: pcols {int(lo_owner[f])} and {int(hi_owner[f])} share a face in their domains"
            )
        owner[pm.v1[ids]] = -1
        owner[pm.v2[ids]] = -1

    # Monotone attributes, parent against each child.
    radius = np.concatenate([np.zeros(V0), pm.radius.astype(np.float64)])
    alpha_all = np.concatenate([np.zeros(V0), pm.alpha.astype(np.float64)])
    slack = sphere_slack(pm.vertices, pm.radius)
    for name in ("v1", "v2"):
        c = getattr(pm, name).astype(np.int64)
        p = V0 + np.arange(P)
        reach = np.linalg.norm(x[p] - x[c], axis=1) + radius[c]
        _fail(reach > radius[p] + slack, "sphere does not contain its child's sphere")
        created = c >= V0
        cos = np.clip(np.einsum("ij,ij->i", n[p], n[c]), -1, 1)
        spread = np.arccos(cos) + alpha_all[c]
        _fail(created & (spread > alpha_all[p] + CONE_SLACK) & (alpha_all[p] < np.pi - CONE_SLACK),
              "normal cone does not contain its child's cone")
        for attr in ("delta", "mu", "alpha"):
            a = getattr(pm, attr)
            child = np.where(created, a[np.maximum(c - V0, 0)], 0)
            _fail(created & (child > a), f"{attr} smaller than its child's")


def _fail(mask: np.ndarray, what: str) -> None:
    bad = np.flatnonzero(mask)
    if len(bad):
        raise PMFormatError(f"pcol {int(bad[0])}: {what}")
