"""The refined mesh read off the front: cost proportional to the faces drawn.

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
position, read from a table made by one prefix sum over ``[0, V0)``. Nothing
else touches all F faces or all ``V0 + P`` vertices.

This module builds the depth-first numbering and the C core's records
(``pmx_front_mesh``), and reads a mesh in NumPy where the core is not built.
"""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Int


class CoreMesh(eqx.Module):
    """The front mesh's records for the C core (``PmxMeshTables`` in
    ``pmjax/engines/core/pmx.h``), each a row of 4-byte fields: per position
    its pcol's two vertices (ids, depth-first starts, the positions of the
    pcols that made them, coordinates) and its kill list's place; per killed
    face (in kill order) and per base face, the face and its corners' starts;
    per top (a root, or an original vertex nothing consumes) its start,
    vertex and coordinates, and the root's position (-1 for the others).

    Attributes:
        pcols: ``int32 [P, 14]``; kill_data, base: ``int32 [n, 4]``;
        tops: ``int32 [T, 5]``; top_at: ``int32 [T]``.
        n_original, n_faces: static, V0 and F.
    """

    pcols: Int[Array, "P 14"]
    kill_data: Int[Array, "K 4"]
    base: Int[Array, "B 4"]
    tops: Int[Array, "T 5"]
    top_at: Int[Array, " T"]
    n_original: int = eqx.field(static=True)
    n_faces: int = eqx.field(static=True)


def _device(x: np.ndarray) -> jax.Array:
    """A record array on the default device, concrete even while a function
    is being traced (it outlives the trace)."""
    with jax.ensure_compile_time_eval():
        return jax.device_put(np.ascontiguousarray(x))


def depth_first(host: dict, children: np.ndarray, roots: np.ndarray, n_original: int, batch_offsets) -> dict:
    """The host arrays of the front mesh: base faces, kill lists, each pcol's
    two vertices and the depth-first starts of every vertex.

    Args:
        host: the mesh's arrays (``vertices``, ``faces``, ``parent``, ``killer``).
        children: ``[P, 2]`` created children; roots: the forest's roots.
    """
    V0, P = n_original, len(children)
    faces, killer = host["faces"], host["killer"]
    killed = np.flatnonzero(killer >= 0)
    out = dict(faces=faces, vertices=host["vertices"], base_faces=np.flatnonzero(killer < 0),
               kill_faces=killed[np.argsort(killer[killed], kind="stable")],
               kill_starts=np.concatenate([[0], np.cumsum(np.bincount(killer[killed], minlength=P))]))
    # Each pcol's two vertices: created ones from its child pcols, original
    # ones from the consuming pcol of each original vertex (side order is
    # immaterial here).
    children = children.astype(np.int64)
    parent = host["parent"].astype(np.int64)
    pair = np.where(children >= 0, V0 + children, -1)
    orig = np.flatnonzero(parent[:V0] >= 0)
    orig = orig[np.argsort(parent[orig], kind="stable")]
    owner = parent[orig]
    rank = np.arange(len(orig)) - np.searchsorted(owner, owner)
    pair[owner, np.where(children[owner, 0] >= 0, 1, rank)] = orig
    out["pair"] = pair
    # Leaves below each vertex, bottom-up (children come from earlier batches).
    offsets = np.asarray(batch_offsets)
    leaves = np.ones(V0 + P, np.int64)
    for lo, hi in zip(offsets[:-1], offsets[1:]):
        leaves[V0 + lo:V0 + hi] = leaves[pair[lo:hi, 0]] + leaves[pair[lo:hi, 1]]
    # Depth-first starts, top-down: the forest's tops side by side, then each
    # pcol's first vertex at its start, the second after the first's leaves.
    out["lone"] = np.flatnonzero(parent[:V0] < 0)  # original vertices nothing consumes
    out["roots"] = roots.astype(np.int64)
    tops = np.concatenate([out["lone"], V0 + out["roots"]])
    start = np.zeros(V0 + P, np.int64)
    start[tops] = np.concatenate([[0], np.cumsum(leaves[tops])[:-1]])
    for lo, hi in reversed(list(zip(offsets[:-1], offsets[1:]))):
        first = start[V0 + lo:V0 + hi]
        start[pair[lo:hi, 0]] = first
        start[pair[lo:hi, 1]] = first + leaves[pair[lo:hi, 0]]
    # Per face, its corners' starts: read in increasing face order with the
    # faces, rather than scattered over all vertices.
    out["face_start"] = start[faces].astype(np.int32)
    out["start"] = start
    out["leaves"] = leaves
    out["n_original"] = V0
    return out


# The records of the C core's front mesh (PmxPcolRecord, PmxFaceRecord,
# PmxFrontVertex in pmjax/engines/core/pmx.h): all fields 4 bytes.
PCOL_RECORD = np.dtype([("kill_first", "<i4"), ("kill_count", "<i4"), ("vertex", "<i4", 2), ("start", "<i4", 2),
                        ("made_at", "<i4", 2), ("position", "<f4", (2, 3))])
FACE_RECORD = np.dtype([("face", "<i4"), ("start", "<i4", 3)])
FRONT_VERTEX = np.dtype([("start", "<i4"), ("vertex", "<i4"), ("position", "<f4", 3)])


def core_records(df: dict, host: dict, order: np.ndarray, n_original: int, n_faces: int):
    """The C core's front-mesh records (:class:`CoreMesh`)
    by breadth-first position, kill lists concatenated in that order: a
    refinement's pcols are read in nearly increasing order."""
    P = len(order)
    pair, count = df["pair"][order], np.diff(df["kill_starts"])[order]
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    killed = df["kill_faces"][np.repeat(df["kill_starts"][:-1][order] - first, count) + np.arange(int(count.sum()))]
    records = np.zeros(P, PCOL_RECORD)
    records["kill_first"] = first
    records["kill_count"] = count
    records["vertex"] = pair
    records["start"] = df["start"][pair]
    # Where the pcol that made each vertex sits (-1: an original).
    at = np.empty(P, np.int32)
    at[order] = np.arange(P, dtype=np.int32)
    made = pair - n_original
    records["made_at"] = np.where(made >= 0, at[np.maximum(made, 0)], -1)
    records["position"] = df["vertices"][pair]
    faces = lambda ids: np.rec.fromarrays([ids, df["face_start"][ids]], dtype=FACE_RECORD)
    top_vertex = np.concatenate([n_original + df["roots"], df["lone"]])
    tops = np.rec.fromarrays([df["start"][top_vertex], top_vertex, df["vertices"][top_vertex]], dtype=FRONT_VERTEX)
    as_int = lambda a, width: _device(np.ascontiguousarray(a).view(np.int32).reshape(len(a), width))
    return CoreMesh(pcols=as_int(records, 14), kill_data=as_int(faces(killed), 4), base=as_int(faces(df["base_faces"]), 4),
                    tops=as_int(tops, 5),
                    top_at=_device(np.concatenate([at[df["roots"]], np.full(len(df["lone"]), -1)]).astype(np.int32)),
                    n_original=n_original, n_faces=n_faces)


def numpy_mesh(df: dict, n_pcols: int, visited: np.ndarray, visited_executed: np.ndarray):
    """The refined mesh from a traversal's visited pcols, in NumPy.

    Args:
        df: :func:`depth_first`.
        visited: ``int32[C]`` visited pcols, ``P`` in unused slots.
        visited_executed: ``bool[C]`` whether each ran.

    Returns:
        ``(vertices float32[n, 3], faces int32[m, 3], vertex_ids int32[n])`` as
        :meth:`pmjax.Refinement.mesh`: faces in increasing original order,
        vertex ids sorted.
    """
    V0 = df["n_original"]
    not_run = visited[(visited < n_pcols) & ~visited_executed].astype(np.int64)
    # Drawn faces: the base faces and the kill lists of the pcols that did not run.
    starts = df["kill_starts"][not_run]
    lengths = df["kill_starts"][not_run + 1] - starts
    offsets = np.repeat(starts - np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths)
    killed = df["kill_faces"][np.arange(int(lengths.sum())) + offsets]
    drawn = np.sort(np.concatenate([df["base_faces"], killed]))
    # The front: below each pcol that did not run, the child vertices that are
    # original or whose pcol ran; the roots that ran; the lone originals.
    executed = np.ones(n_pcols, bool)
    executed[not_run] = False
    below = df["pair"][not_run].reshape(-1)
    below = below[(below < V0) | executed[np.maximum(below - V0, 0)]]
    tops = V0 + df["roots"][executed[df["roots"]]]
    front = np.concatenate([below, tops, df["lone"]])
    order = np.argsort(df["start"][front])
    front, front_start = front[order], df["start"][front[order]]
    # Each corner's representative: the front vertex whose interval holds it,
    # from a table over the depth-first positions (one prefix sum of the
    # interval starts: a sequential pass over V0 integers, cheaper than a
    # binary search per corner).
    starts_at = np.zeros(V0, np.int32)
    starts_at[front_start] = 1
    slot = (np.cumsum(starts_at, dtype=np.int32) - 1)[df["face_start"][drawn].reshape(-1)]
    # Output vertices: the front vertices used, in increasing id.
    used = np.zeros(len(front), bool)
    used[slot] = True
    used = np.flatnonzero(used)
    by_id = used[np.argsort(front[used])]
    rank = np.empty(len(front), np.int32)
    rank[by_id] = np.arange(len(by_id), dtype=np.int32)
    ids = front[by_id]
    return df["vertices"][ids], rank[slot].reshape(-1, 3), ids.astype(np.int32)


def stream_tables(df: dict, parent: np.ndarray, order: np.ndarray, mesh: CoreMesh) -> tuple:
    """The tables of the C core's mesh stream (``PmxStreamTables`` in
    ``pmjax/engines/core/pmx.h``), in the order ``_pmx.mesh_stream_new``
    takes them: the front mesh's records, then per breadth-first position the
    pcol's own vertex and its position, the position of the pcol consuming
    each position's vertex and each original vertex (``up``, -1 for a top),
    and each face's original corners.

    Args:
        df: :func:`depth_first`; parent: ``[V0 + P]`` each vertex's consuming
            pcol (-1: none); order: ``int32 [P]`` the pcol at each position;
            mesh: :class:`CoreMesh` (its arrays read on the host).

    Returns:
        NumPy arrays ``(pcol_records [P, 14], kill_data [K, 4], base [B, 4],
        tops [T, 5], top_at [T], own_vertex [P], own_end [P], own_position
        [P, 3], up [P + V0], corners [F, 3])``, all int32 but ``own_position``;
        ``own_end`` the end of the pcol's depth-first interval of original
        vertices (it starts at its first child's start).
    """
    V0, P = df["n_original"], len(order)
    parent = np.asarray(parent, np.int64)
    at = np.empty(P, np.int64)
    at[order] = np.arange(P)
    own = V0 + order.astype(np.int64)
    consumer = np.concatenate([parent[own], parent[:V0]])
    up = np.where(consumer >= 0, at[np.maximum(consumer, 0)], -1).astype(np.int32)
    host = lambda a: np.ascontiguousarray(np.asarray(a))
    return (host(mesh.pcols), host(mesh.kill_data), host(mesh.base), host(mesh.tops), host(mesh.top_at),
            own.astype(np.int32), (df["start"][own] + df["leaves"][own]).astype(np.int32),
            np.ascontiguousarray(df["vertices"][own], np.float32), up,
            np.ascontiguousarray(df["faces"], np.int32))
