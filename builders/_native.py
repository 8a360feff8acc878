"""The builder's C loops (``builders/_build_native.c``), called through ctypes.

The steps of a batch that walk the mesh: the faces around each vertex, the
edges (keys counted around NumPy's sort), known costs carried by key and the
quadric placement of fresh pairs, the cheapest share, the validity checks,
the greedy choice of independent collapses, applying the batch, and the new
vertices' normals. Each is the NumPy step's arithmetic in its order, and the
greedy works out each candidate's round of the NumPy builder's parallel
rounds, so that their round cap takes the same set: the hierarchy is bit for
bit the NumPy builder's (tests/test_build_native.py). The library is the
optional extension ``pmjax.builders._build_native``; where it is missing, or
``PMJAX_NATIVE=0`` is set, the builder runs as NumPy.
"""

from __future__ import annotations

import ctypes

import numpy as np

from pmjax._clib import open_library

from ._threads import split_range

# What a candidate became (the C enum).
DEAD, TAKEN, INVALID, UNCHECKED = 0, 1, 2, 3

_p = ctypes.c_void_p
_i64 = ctypes.c_int64


def _load():
    lib = open_library("pmjax.builders._build_native")
    if lib is None:
        return None
    lib.pmx_vertex_faces.restype = None
    lib.pmx_vertex_faces.argtypes = [_i64, _p, _p, _p]
    lib.pmx_edge_keys.restype = None
    lib.pmx_edge_keys.argtypes = [_i64, _p, _p]
    lib.pmx_sort_keys.restype = ctypes.c_int
    lib.pmx_sort_keys.argtypes = [_i64, _p, _p, _p]
    lib.pmx_key_runs.restype = _i64
    lib.pmx_key_runs.argtypes = [_i64, _p, _p, _p, _p, _p]
    lib.pmx_carry_costs.restype = _i64
    lib.pmx_carry_costs.argtypes = [_i64, _p, _p, _p, _i64, _p, _p, _p, _p]
    mesh = [_i64, _p, _i64, _p, _p, ctypes.c_double] + [_p] * 6  # Mesh._args
    lib.pmx_collapse_valid.restype = None
    lib.pmx_collapse_valid.argtypes = [_i64] + [_p] * 5 + mesh + [_p]
    lib.pmx_select_independent.restype = _i64
    lib.pmx_select_independent.argtypes = [_i64] + [_p] * 5 + mesh + [ctypes.c_int, _i64, _p, _p]
    lib.pmx_pick_cheapest.restype = _i64
    lib.pmx_pick_cheapest.argtypes = [_i64, _p, _i64, ctypes.c_double, _p]
    lib.pmx_stable_ties.restype = None
    lib.pmx_stable_ties.argtypes = [_i64, _p, _p]
    lib.pmx_scatter_add.restype = None
    lib.pmx_scatter_add.argtypes = [_i64, _p, _i64, _p, _i64, _i64, _p]
    lib.pmx_new_vertex_normals.restype = None
    lib.pmx_new_vertex_normals.argtypes = [_i64, _p, _p, _i64, _p]
    lib.pmx_climb_leaves.restype = _i64
    lib.pmx_climb_leaves.argtypes = [_i64, _p, _p, _i64] + [_p] * 5
    lib.pmx_uncovered_distance.restype = None
    lib.pmx_uncovered_distance.argtypes = [_i64, _p, _p, _p, _p, _i64, _i64, _i64] + [_p] * 8
    lib.pmx_apply_batch.restype = _i64
    lib.pmx_apply_batch.argtypes = [_i64, _p, _p, _i64, _p, _p, _i64, _p, _i64, _p, _p, _p, _p]
    lib.pmx_quadric_scale.restype = None
    lib.pmx_quadric_scale.argtypes = [_i64, _p, _p, _p, _p]
    lib.pmx_quadric_placement.restype = _i64
    lib.pmx_quadric_placement.argtypes = [_i64] + [_p] * 9
    return lib


_LIB = _load()
# Tests switch the C loops off to compare with the NumPy path (use_native).
_enabled = True


def available() -> bool:
    """Whether the builder's per-batch steps run as the compiled C loops."""
    return _LIB is not None and _enabled


class use_native:
    """``with use_native(False): ...`` builds with NumPy alone; ``True``
    restores the C loops where they are built."""

    def __init__(self, on: bool):
        self.on = on

    def __enter__(self):
        global _enabled
        self.before, _enabled = _enabled, self.on
        return self

    def __exit__(self, *exc):
        global _enabled
        _enabled = self.before


class Scratch:
    """Buffers of the C loops for one build, allocated once (``int32``
    each): the faces around each vertex (first slot and count per vertex,
    and the slots), the greedy's state per vertex (round blocked from, last
    removal round), two arrays of link-test stamps with the last stamp
    used (stamps only grow, so the arrays are never cleared), and an
    identity map of vertex ids that a batch renames and restores.

    Args:
        n_vertices: bound on the build's vertex ids; n_faces: its face count.
    """

    def __init__(self, n_vertices: int, n_faces: int):
        self.around = np.empty((n_vertices, 2), np.int32)
        self.face = np.empty(3 * n_faces, np.int32)
        self.vertex = np.empty((n_vertices, 2), np.int32)
        self.side_a = np.zeros(n_vertices, np.int32)
        self.side_b = np.zeros(n_vertices, np.int32)
        self.stamp = np.zeros(1, np.int32)
        self.rename = np.arange(n_vertices, dtype=np.int32)  # the identity between batches
        names = ("around", "face", "vertex", "side_a", "side_b", "stamp")
        self.pointers = tuple(getattr(self, k).ctypes.data for k in names)


class Mesh:
    """The current mesh as the C loops read it: its arrays in their dtypes
    (held, so that the pointers stay valid) and the faces around each vertex,
    built here into the scratch (so one mesh at a time per scratch).

    Args:
        faces: ``(F, 3)`` current faces; n_vertices: bound on vertex ids.
        pos: ``(N, 3)`` float64 positions, ``N >= n_vertices``.
        scratch: the build's :class:`Scratch`.
    """

    def __init__(self, faces, n_vertices, pos, scratch: Scratch):
        self.faces = np.ascontiguousarray(faces, np.int32)
        self.n_vertices = int(n_vertices)
        self.pos = np.ascontiguousarray(pos, np.float64)
        self.scratch = scratch
        if (len(scratch.vertex) < self.n_vertices or len(scratch.face) < 3 * len(self.faces)
                or len(self.pos) < self.n_vertices):
            raise ValueError("builder: the C loops' buffers are smaller than the mesh")
        if len(self.faces) and not (0 <= self.faces.min() and self.faces.max() < self.n_vertices):
            raise ValueError(f"builder: a face vertex id is outside 0 .. {self.n_vertices - 1}")
        _LIB.pmx_vertex_faces(len(self.faces), self.faces.ctypes.data, scratch.around.ctypes.data,
                              scratch.face.ctypes.data)

    def _args(self, boundary_vertex, min_area2):
        boundary = np.ascontiguousarray(boundary_vertex, np.uint8)
        if len(boundary) < self.n_vertices:
            raise ValueError("builder: a border flag is missing for some vertex")
        self._boundary = boundary  # held during the call
        return (len(self.faces), self.faces.ctypes.data, self.n_vertices, self.pos.ctypes.data,
                boundary.ctypes.data, float(min_area2), *self.scratch.pointers)


def unique_edges(faces: np.ndarray):
    """:func:`builders._topology.unique_edges` of ``int32`` faces, the same
    arrays: the keys made, radix-sorted (:func:`sort_keys`) and counted in C. The
    distinct keys overwrite the sorted ones in place and the other arrays
    are allocated at the distinct count, so the step holds the ``3 F`` keys
    and the results only."""
    faces = np.ascontiguousarray(faces, np.int32)
    keys = np.empty(3 * len(faces), np.int64)
    _LIB.pmx_edge_keys(len(faces), faces.ctypes.data, keys.ctypes.data)
    sort_keys(keys)
    n = 1 + int(np.count_nonzero(keys[1:] != keys[:-1])) if len(keys) else 0
    count = np.empty(n, np.int64)
    lo, hi = np.empty(n, np.int32), np.empty(n, np.int32)
    # A run's key is written at or before where it was read: in place is safe.
    m = _LIB.pmx_key_runs(len(keys), keys.ctypes.data, keys.ctypes.data, lo.ctypes.data, hi.ctypes.data,
                          count.ctypes.data)
    assert m == n
    return lo, hi, count, keys[:n].copy()


# Passes and digit width of the C radix sort of edge keys (its defines).
RADIX_BITS, RADIX_PASSES = 12, 6


def sort_keys(keys: np.ndarray) -> None:
    """Sort ``int64`` edge keys (:func:`builders._topology.edge_keys`, ids
    below 2**31) in place: NumPy's ``keys.sort()``, the same array, by a
    radix sort in C (a few passes over the keys where NumPy's sort compares
    them; it holds a second buffer of the keys' size meanwhile)."""
    if not (keys.dtype == np.int64 and keys.flags.c_contiguous and keys.ndim == 1):
        raise ValueError("sort_keys: keys must be contiguous 1-D int64")
    tmp = np.empty_like(keys)
    counts = np.empty(RADIX_PASSES << RADIX_BITS, np.int64)
    if _LIB.pmx_sort_keys(len(keys), keys.ctypes.data, tmp.ctypes.data, counts.ctypes.data):
        raise ValueError("sort_keys: a key is negative or holds an id of 2**31 or more (not an edge key)")


def carry_costs(old_keys: np.ndarray, old_x: np.ndarray, old_cost: np.ndarray, keys: np.ndarray):
    """Placements and costs of the pairs ``keys`` known from the last batch.

    Args:
        old_keys: ``(M,)`` ascending ``int64`` pair keys; old_x ``(M, 3)``,
            old_cost ``(M,)`` their placements and costs.
        keys: ``(C,)`` this batch's pair keys.

    Returns:
        ``(x (C, 3), cost (C,), fresh)`` with ``fresh`` the positions of the
        pairs not known (their rows unset), or ``None`` where ``keys`` are
        not ascending.
    """
    old_keys = np.ascontiguousarray(old_keys, np.int64)
    old_x = np.ascontiguousarray(old_x, np.float64)
    old_cost = np.ascontiguousarray(old_cost, np.float64)
    keys = np.ascontiguousarray(keys, np.int64)
    x, cost, fresh = np.empty((len(keys), 3)), np.empty(len(keys)), np.empty(len(keys), np.int64)
    n_fresh = _LIB.pmx_carry_costs(len(old_keys), old_keys.ctypes.data, old_x.ctypes.data, old_cost.ctypes.data,
                                   len(keys), keys.ctypes.data, x.ctypes.data, cost.ctypes.data, fresh.ctypes.data)
    if n_fresh < 0:
        return None
    return x, cost, fresh[:n_fresh].copy()


class Candidates:
    """All of a batch's candidates in the dtypes the C loops read: endpoints
    ``a, b`` ``(C,)``, placements ``x`` ``(C, 3)``, ``link_test`` ``(C,)``."""

    def __init__(self, a, b, x, link_test):
        self.a = np.ascontiguousarray(a, np.int32)
        self.b = np.ascontiguousarray(b, np.int32)
        self.x = np.ascontiguousarray(x, np.float64)
        self.link = np.ascontiguousarray(link_test, np.uint8)

    def _args(self, idx):
        return (len(idx), idx.ctypes.data, self.a.ctypes.data, self.b.ctypes.data, self.x.ctypes.data,
                self.link.ctypes.data)


def collapse_is_valid(mesh: Mesh, cand: Candidates, idx: np.ndarray, boundary_vertex, min_area2) -> np.ndarray:
    """``bool[len(idx)]``: :func:`builders._validity.collapse_is_valid` of
    the candidates ``idx`` (ids into ``cand``), with the border flags
    ``boundary_vertex`` (``bool[n_vertices]``) and degenerate-face bound
    ``min_area2`` (squared doubled area)."""
    idx = np.ascontiguousarray(idx, np.int64)
    ok = np.empty(len(idx), np.uint8)
    _LIB.pmx_collapse_valid(*cand._args(idx), *mesh._args(boundary_vertex, min_area2), ok.ctypes.data)
    return ok.view(bool)


def select_independent(mesh: Mesh, cand: Candidates, idx: np.ndarray, boundary_vertex, min_area2, *,
                       assume_valid: bool, max_rounds: int = 64):
    """The batch of :func:`builders._independent.select_independent` with
    :func:`collapse_is_valid` as its check.

    Args:
        mesh: the current mesh.
        cand: the batch's candidates.
        idx: ``(E,)`` ids of the eligible ones, cheapest first.
        boundary_vertex, min_area2: as for :func:`collapse_is_valid`.
        assume_valid: every eligible candidate is known valid (checked up front).
        max_rounds: the round cap of the parallel version.

    Returns:
        ``(chosen, invalid, checked)``: positions in ``idx`` of the chosen
        candidates, ascending; positions of the round winners found invalid;
        how many winners were checked (0 with ``assume_valid``).
    """
    idx = np.ascontiguousarray(idx, np.int64)
    state = np.empty(len(idx), np.uint8)
    rounds = np.empty(len(idx), np.int32)
    last = _LIB.pmx_select_independent(*cand._args(idx), *mesh._args(boundary_vertex, min_area2), int(assume_valid),
                                       int(max_rounds),
                                       state.ctypes.data, rounds.ctypes.data)
    within = rounds <= last
    chosen = np.flatnonzero(within & (state == TAKEN))
    invalid = np.flatnonzero(within & (state == INVALID))
    checked = 0 if assume_valid else len(chosen) + len(invalid)
    return chosen, invalid, checked


def quadric_placement(quadric: np.ndarray, pos: np.ndarray, a: np.ndarray, b: np.ndarray, rows=None, x=None,
                      cost=None):
    """:func:`builders._quadrics.optimal_placement` of ``quadric[a] +
    quadric[b]`` between ``pos[a]`` and ``pos[b]``, the same bits, on both
    cores for many pairs.

    Args:
        quadric: ``float64[N, 10]`` packed quadrics (row-major).
        pos: ``float64[N, 3]`` positions; a, b: ``(C,)`` vertex ids.
        rows: positions of the pairs to place (``None``: all); their
            results go to those rows of ``x`` and ``cost``.
        x, cost: ``(C, 3)`` and ``(C,)`` float64 outputs to fill, or
            ``None`` for new ones.

    Returns:
        ``(x, cost)``.
    """
    quadric = np.ascontiguousarray(quadric, np.float64)
    pos = np.ascontiguousarray(pos, np.float64)
    a, b = np.ascontiguousarray(a, np.int32), np.ascontiguousarray(b, np.int32)
    x = np.empty((len(a), 3)) if x is None else x
    cost = np.empty(len(a)) if cost is None else cost
    if not (x.flags.c_contiguous and cost.flags.c_contiguous and x.dtype == cost.dtype == np.float64
            and x.shape == (len(a), 3) and cost.shape == (len(a),)):
        raise ValueError("quadric_placement: x and cost must be contiguous float64 (C, 3) and (C,)")
    rows = np.arange(len(a), dtype=np.int64) if rows is None else np.ascontiguousarray(rows, np.int64)
    if len(rows) and not (0 <= rows.min() and rows.max() < len(a)):
        raise ValueError(f"quadric_placement: a row is outside 0 .. {len(a) - 1}")

    def place(lo, hi):
        part = rows[lo:hi]
        unsure = np.empty(len(part), np.int64)
        n_unsure = _LIB.pmx_quadric_placement(len(part), part.ctypes.data, a.ctypes.data, b.ctypes.data,
                                              quadric.ctypes.data, pos.ctypes.data, None, x.ctypes.data,
                                              cost.ctypes.data, unsure.ctypes.data)
        if n_unsure:
            # A determinant at the solvability threshold: the threshold as
            # optimal_placement computes it, with NumPy's power.
            at = unsure[:n_unsure]
            ua, ub = a[at], b[at]
            scale = np.empty(len(at))
            _LIB.pmx_quadric_scale(len(at), ua.ctypes.data, ub.ctypes.data, quadric.ctypes.data, scale.ctypes.data)
            threshold = 1e-9 * scale**3
            _LIB.pmx_quadric_placement(len(at), at.ctypes.data, a.ctypes.data, b.ctypes.data, quadric.ctypes.data,
                                       pos.ctypes.data, threshold.ctypes.data, x.ctypes.data, cost.ctypes.data, None)

    split_range(place, len(rows))
    return x, cost


def cheapest(cost: np.ndarray, k: int, kth: float):
    """The first ``k`` of ``np.argsort(cost, kind="stable")`` given the
    ``k``-th smallest cost ``kth`` (``1 <= k <= len(cost)``), or ``None``
    where a cost is NaN: the picked ids come in index order (C), NumPy's
    quicksort orders their costs, and runs of equal costs are put back in
    index order (C)."""
    cost = np.ascontiguousarray(cost, np.float64)
    pick = np.empty(k, np.int64)
    if _LIB.pmx_pick_cheapest(len(cost), cost.ctypes.data, k, float(kth), pick.ctypes.data):
        return None
    value = cost[pick]
    order = np.argsort(value, kind="quicksort")
    _LIB.pmx_stable_ties(len(order), value.ctypes.data, order.ctypes.data)
    return pick[order]


def scatter_add(columns: np.ndarray, index: np.ndarray, n: int, repeat: int, out: np.ndarray | None = None):
    """:func:`builders._quadrics.scatter_add` of the ``(k, N)`` contiguous
    float64 ``columns``: ``out[index[i]] += columns[:, i // repeat]``, the
    same sums in the same order, as ``(n, k)``.

    Args:
        out: contiguous ``float64[n, k]`` to add to (``None``: zeros). Sums
            made in steps over consecutive parts of ``index`` into one ``out``
            are the one step's sums, bit for bit.
    """
    columns = np.ascontiguousarray(columns, np.float64)
    index = np.ascontiguousarray(index, np.int64)
    if len(index) and not (0 <= index.min() and index.max() < n):
        raise ValueError(f"scatter_add: an index is outside 0 .. {n - 1}")
    if len(index) > repeat * columns.shape[1]:
        raise ValueError("scatter_add: more indices than values")
    if out is None:
        out = np.zeros((n, len(columns)))
    elif not (out.shape == (n, len(columns)) and out.dtype == np.float64 and out.flags.c_contiguous):
        raise ValueError(f"scatter_add: out must be a contiguous float64 ({n}, {len(columns)}) array")
    _LIB.pmx_scatter_add(len(index), index.ctypes.data, len(columns), columns.ctypes.data, columns.shape[1], repeat,
                         out.ctypes.data)
    return out


def new_vertex_normals(pos: np.ndarray, faces: np.ndarray, first: int, k: int) -> np.ndarray:
    """``(k, 3)`` sums of the doubled-area normals of ``faces`` at their
    corners ``first .. first+k-1`` (not yet unit length): the sums of
    :func:`builders._quadrics.face_cross` rows that :func:`scatter_add`
    makes, bit for bit, in one pass."""
    faces = np.ascontiguousarray(faces, np.int32)
    pos = np.ascontiguousarray(pos, np.float64)
    if len(faces) and not (faces.max() < min(first + k, len(pos)) and faces.min() >= 0):
        raise ValueError("new_vertex_normals: a face vertex id is outside the positions")
    out = np.zeros((k, 3))
    _LIB.pmx_new_vertex_normals(len(faces), faces.ctypes.data, pos.ctypes.data, first, out.ctypes.data)
    return out


def uncovered_distance(pos, normals, leaves, owner, ring, lo: int, hi: int, maybe_border, leaf_on_border):
    """:func:`builders._attributes.uncovered_distance` in one C pass, bit for
    bit (the same arguments; ``float64[M]`` distances)."""
    leaves, owner = np.ascontiguousarray(leaves, np.int64), np.ascontiguousarray(owner, np.int64)
    ring = np.ascontiguousarray(ring, np.int32).reshape(-1, 3)
    maybe_border = np.ascontiguousarray(maybe_border, np.uint8)
    leaf_on_border = np.ascontiguousarray(leaf_on_border, np.uint8)
    if not (pos.dtype == np.float64 and normals.dtype == np.float64 and pos.flags.c_contiguous
            and normals.flags.c_contiguous and len(owner) == len(leaves) == len(leaf_on_border)
            and len(maybe_border) == hi - lo):
        raise ValueError("uncovered_distance: pos, normals must be contiguous float64, one owner and border flag "
                         "per leaf, one maybe_border flag per new vertex")
    out = np.empty(len(leaves))
    if not len(leaves):
        return out
    k, corners = hi - lo, 3 * len(ring)
    start, slots = np.empty(k + 1, np.int64), np.empty(max(corners, 1), np.int32)
    around, border = np.empty(max(2 * corners, 1), np.int32), np.empty(max(k, 1), np.int8)
    _LIB.pmx_uncovered_distance(len(leaves), leaves.ctypes.data, owner.ctypes.data, leaf_on_border.ctypes.data,
                                ring.ctypes.data, len(ring), lo, hi, maybe_border.ctypes.data, pos.ctypes.data,
                                normals.ctypes.data, start.ctypes.data, slots.ctypes.data, around.ctypes.data,
                                border.ctypes.data, out.ctypes.data)
    return out


def climb_leaves(top: np.ndarray, parent: np.ndarray, lo: int, hi: int, pos: np.ndarray, normals: np.ndarray):
    """The leaves' climb of :meth:`builders._attributes.HierarchyAttributes.add_batch`
    in one pass, bit for bit: ``top`` (int64, updated in place) moves up where
    ``parent[top] >= lo``.

    Returns:
        ``(moving, owner, height)``: the leaves that moved and their new tops
        (int64, increasing leaf), and ``float64[hi - lo]`` the largest
        distance of a moved leaf from its new top's tangent plane.
    """
    if not (top.dtype == np.int64 and parent.dtype == np.int64 and top.flags.c_contiguous
            and parent.flags.c_contiguous and pos.dtype == np.float64 and normals.dtype == np.float64
            and pos.flags.c_contiguous and normals.flags.c_contiguous and hi <= len(parent) <= len(pos)):
        raise ValueError("climb_leaves: top, parent must be contiguous int64, pos, normals contiguous float64")
    moving, owner = np.empty(len(top), np.int64), np.empty(len(top), np.int64)
    height = np.zeros(hi - lo)
    m = _LIB.pmx_climb_leaves(len(top), top.ctypes.data, parent.ctypes.data, lo, pos.ctypes.data,
                              normals.ctypes.data, moving.ctypes.data, owner.ctypes.data, height.ctypes.data)
    # Copies of the moved part, so that the arrays sized for every leaf go now.
    return moving[:m].copy(), owner[:m].copy(), height


def apply_batch(scratch: Scratch, faces, fid, a, b, first: int, V0: int, killer, quadric):
    """Apply a batch of collapses: pair ``(a[i], b[i])`` becomes vertex
    ``first + i``, whose quadric row is the pair's sum; faces two of whose
    corners meet die, with ``killer[fid] = merged vertex - V0``.

    Args:
        scratch: the build's :class:`Scratch` (its identity map).
        faces: ``(F, 3)`` int32 current faces; fid: ``(F,)`` int64 their
            original ids.
        a, b: ``(k,)`` the batch's pairs; first: the first new id.
        V0: the number of original vertices.
        killer: ``int32[F0]``, written where faces die.
        quadric: ``float64[N, 10]`` (row-major), rows ``first ..`` written.

    Returns:
        ``(faces, fid)`` of the living faces, in order (new arrays).
    """
    faces = np.ascontiguousarray(faces, np.int32)
    fid = np.ascontiguousarray(fid, np.int64)
    a, b = np.ascontiguousarray(a, np.int32), np.ascontiguousarray(b, np.int32)
    if not (killer.dtype == np.int32 and killer.flags.c_contiguous and quadric.dtype == np.float64
            and quadric.flags.c_contiguous and first + len(a) <= min(len(quadric), len(scratch.rename))):
        raise ValueError("apply_batch: killer must be contiguous int32, quadric contiguous float64 with room")
    out_faces, out_fid = np.empty_like(faces), np.empty_like(fid)
    m = _LIB.pmx_apply_batch(len(faces), faces.ctypes.data, fid.ctypes.data, len(a), a.ctypes.data, b.ctypes.data,
                             first, scratch.rename.ctypes.data, V0, killer.ctypes.data, quadric.ctypes.data,
                             out_faces.ctypes.data, out_fid.ctypes.data)
    return out_faces[:m], out_fid[:m]
