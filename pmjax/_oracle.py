"""The sequential oracle: the Visualizer's Fig. 6 loop, plain Python, for clarity.

Used by the tests (engine == oracle) and by the benchmarks (speed ratio). It
shares only the per-pcol decision with the engine (``collapse``, from
:func:`pmjax.collapse_mask`); faces are found from the representatives alone,
without ``killer``.
"""

from __future__ import annotations

import numpy as np

from ._pmfile import PMData


def oracle_refine(pm: PMData, collapse: np.ndarray):
    """Sequential inverse traversal.

    For each pcol in order: if both vertices are active and ``collapse[p]``,
    execute it (both inactive, the new vertex active, ``vref`` of both set to
    it). Faces are active when their corners' representatives are pairwise
    distinct.

    Args:
        pm: host progressive mesh.
        collapse: ``bool[P]`` per-pcol decision for the view.

    Returns:
        ``(executed bool[P], faces int[m, 3])``: faces as representative ids.
    """
    V0, P = pm.n_original_vertices, pm.n_pcols
    v1, v2 = pm.v1.tolist(), pm.v2.tolist()
    decide = np.asarray(collapse, bool).tolist()
    active = [True] * V0 + [False] * P
    vref = list(range(V0 + P))
    executed = np.zeros(P, bool)
    for p in range(P):
        a, b = v1[p], v2[p]
        if active[a] and active[b] and decide[p]:
            executed[p] = True
            active[a] = active[b] = False
            active[V0 + p] = True
            vref[a] = vref[b] = V0 + p
    rep = np.array(vref)
    while True:  # follow vref chains to the active vertex
        nxt = rep[rep]
        if np.array_equal(nxt, rep):
            break
        rep = nxt
    corners = rep[pm.faces]
    alive = (corners[:, 0] != corners[:, 1]) & (corners[:, 1] != corners[:, 2]) & (corners[:, 0] != corners[:, 2])
    return executed, corners[alive]
