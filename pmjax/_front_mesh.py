"""The refined mesh from the front: cost proportional to the faces drawn.

A face is drawn when its killer did not run: it is a face of the base mesh
(no killer) or one that a pcol that did not run would kill. The pcols that
did not run are exactly the visited pcols the traversal flagged, so the drawn
faces are the base faces plus those pcols' kill lists (an index built once).

The front, the vertices drawn, is read off the same pcols: a child vertex of a
pcol that did not run is on the front if it is original or its own pcol ran;
so is the vertex of a root that ran, and an original vertex nothing consumes.
Every original vertex lies below exactly one front vertex, its representative.
With the original vertices numbered in depth-first order of the forest, the
ones below any vertex form an interval, and the front's intervals tile
``[0, V0)``: a corner's representative is the front interval holding its
position, read from a table made by one prefix sum over ``[0, V0)`` (a
sequential pass over V0 integers, much cheaper than a binary search per
corner). Nothing else touches all F faces or all ``V0 + P`` vertices.
"""

from __future__ import annotations

import threading

import numpy as np

_LOCK = threading.Lock()


class _HostMesh:
    """Host arrays of one mesh, built once: faces, vertices, base faces, kill
    lists, each pcol's two vertices, the depth-first leaf intervals and a
    scratch executed mask."""

    def __init__(self, pm):
        V0, P = pm.n_original_vertices, pm.n_pcols
        self.n_original_vertices = V0
        self.faces = np.asarray(pm.faces)
        self.vertices = np.asarray(pm.vertices)
        killer = np.asarray(pm.killer)
        self.base_faces = np.flatnonzero(killer < 0)
        killed = np.flatnonzero(killer >= 0)
        self.kill_faces = killed[np.argsort(killer[killed], kind="stable")]
        self.kill_starts = np.concatenate([[0], np.cumsum(np.bincount(killer[killed], minlength=P))])
        # Each pcol's two vertices: created ones from its child pcols, original
        # ones from the consuming pcol of each original vertex (side order is
        # immaterial here).
        children = np.asarray(pm.children).astype(np.int64)
        parent = np.asarray(pm.parent).astype(np.int64)
        pair = np.where(children >= 0, V0 + children, -1)
        orig = np.flatnonzero(parent[:V0] >= 0)
        orig = orig[np.argsort(parent[orig], kind="stable")]
        owner = parent[orig]
        rank = np.arange(len(orig)) - np.searchsorted(owner, owner)
        pair[owner, np.where(children[owner, 0] >= 0, 1, rank)] = orig
        self.pair = pair
        # Leaves below each vertex, bottom-up (children come from earlier batches).
        offsets = np.asarray(pm.batch_offsets)
        leaves = np.ones(V0 + P, np.int64)
        for lo, hi in zip(offsets[:-1], offsets[1:]):
            leaves[V0 + lo:V0 + hi] = leaves[pair[lo:hi, 0]] + leaves[pair[lo:hi, 1]]
        # Depth-first starts, top-down: the forest's tops side by side, then
        # each pcol's first vertex at its start, the second after the first's leaves.
        self.lone = np.flatnonzero(parent[:V0] < 0)  # original vertices nothing consumes
        self.roots = np.asarray(pm.roots).astype(np.int64)
        tops = np.concatenate([self.lone, V0 + self.roots])
        start = np.zeros(V0 + P, np.int64)
        start[tops] = np.concatenate([[0], np.cumsum(leaves[tops])[:-1]])
        for lo, hi in reversed(list(zip(offsets[:-1], offsets[1:]))):
            first = start[V0 + lo:V0 + hi]
            start[pair[lo:hi, 0]] = first
            start[pair[lo:hi, 1]] = first + leaves[pair[lo:hi, 0]]
        # Per face, its corners' starts: read in increasing face order with the
        # faces, rather than scattered over all vertices.
        self.face_start = start[self.faces].astype(np.int32)
        self.start = start
        # All executed; a call clears the pcols that did not run, then restores them.
        self.executed = np.ones(P, bool)


def _host(pm) -> _HostMesh:
    with _LOCK:
        host = pm.plan.host.get("mesh")
        if host is None or host.faces.shape[0] != pm.n_faces:
            host = pm.plan.host["mesh"] = _HostMesh(pm)
        return host


def front_mesh(pm, visited: np.ndarray, visited_executed: np.ndarray):
    """The refined mesh from a traversal's visited pcols.

    Args:
        pm: :class:`pmjax.ProgressiveMesh`.
        visited: ``int32[C]`` visited pcols, ``P`` in unused slots.
        visited_executed: ``bool[C]`` whether each ran.

    Returns:
        ``(vertices float32[n, 3], faces int32[m, 3], vertex_ids int32[n])`` as
        :meth:`pmjax.Refinement.mesh`: faces in increasing original order,
        vertex ids sorted.
    """
    host = _host(pm)
    V0 = host.n_original_vertices
    not_run = visited[(visited < pm.n_pcols) & ~visited_executed].astype(np.int64)
    # Drawn faces: the base faces and the kill lists of the pcols that did not run.
    starts, lengths = host.kill_starts[not_run], host.kill_starts[not_run + 1] - host.kill_starts[not_run]
    offsets = np.repeat(starts - np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths)
    killed = host.kill_faces[np.arange(int(lengths.sum())) + offsets]
    drawn = np.sort(np.concatenate([host.base_faces, killed]))
    # The front: below each pcol that did not run, the child vertices that are
    # original or whose pcol ran; the roots that ran; the lone originals.
    with _LOCK:  # the scratch mask is shared by the calls on this mesh
        host.executed[not_run] = False
        try:
            below = host.pair[not_run].reshape(-1)
            below = below[(below < V0) | host.executed[np.maximum(below - V0, 0)]]
            tops = V0 + host.roots[host.executed[host.roots]]
        finally:
            host.executed[not_run] = True
    front = np.concatenate([below, tops, host.lone])
    order = np.argsort(host.start[front])
    front, front_start = front[order], host.start[front[order]]
    # Each corner's representative: the front vertex whose interval holds it.
    # A table over the depth-first positions, one prefix sum of the interval
    # starts: one cheap sequential pass over V0 integers, 8x faster here than
    # a binary search per corner (dragon, 52,000 corners: 0.43 vs 3.4 ms).
    starts_at = np.zeros(V0, np.int32)
    starts_at[front_start] = 1
    slot = (np.cumsum(starts_at, dtype=np.int32) - 1)[host.face_start[drawn].reshape(-1)]
    # Output vertices: the front vertices used, in increasing id.
    used = np.zeros(len(front), bool)
    used[slot] = True
    used = np.flatnonzero(used)
    by_id = used[np.argsort(front[used])]
    rank = np.empty(len(front), np.int32)
    rank[by_id] = np.arange(len(by_id), dtype=np.int32)
    ids = front[by_id]
    return host.vertices[ids], rank[slot].reshape(-1, 3), ids.astype(np.int32)
