"""Normals of the hierarchy: every vertex's normal from the original surface it stands for."""

from __future__ import annotations

import ctypes
import os
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ._clib import open_library

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


# Jacobi sweeps of a batch's least-squares fit: created vertices of one batch
# rarely share a face (their collapses are independent), so the first sweep
# nearly solves it and the second settles the few shared faces.
FIT_SWEEPS = 2


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
    return np.ascontiguousarray(_corner_sums(faces, _face_cross(np.ascontiguousarray(vertices.T), faces), len(vertices)).T)


def _face_cross(coordinates, faces) -> np.ndarray:
    """``[3, F]`` by axis each face's cross product of its edges from corner 0
    (2·area·normal; the arithmetic of ``np.cross``), of the vertices
    ``coordinates[3, V]``."""
    a, b, c = ([coordinates[k][faces[:, j]] for k in range(3)] for j in range(3))
    u = [b[k] - a[k] for k in range(3)]
    v = [c[k] - a[k] for k in range(3)]
    return np.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def _corner_sums(faces, values, n: int) -> np.ndarray:
    """``[C, n]`` per vertex the sum of ``values[C, F]`` over its faces, each
    vertex's terms added in the order corner 0 of every face, then corner 1,
    then corner 2 (the order of ``np.add.at`` corner by corner, so the same
    bits)."""
    at = faces.T.reshape(-1)
    return np.stack([np.bincount(at, np.tile(row, 3), minlength=n) for row in values])


def _consumed(parent) -> np.ndarray:
    """The consumed vertices in the order of the pcols consuming them (a
    pcol's two, the smaller id first)."""
    order = np.argsort(parent, kind="stable")
    return order[parent[order] >= 0]


def _consumed_by_batch(parent, offsets) -> list:
    """Per batch, the vertices its pcols consume (``parent`` in the batch)."""
    consumed = _consumed(parent)
    starts = np.searchsorted(parent[consumed], offsets)
    return [consumed[starts[b]:starts[b + 1]] for b in range(len(offsets) - 1)]


def _unit(n: np.ndarray, axis: int = 1) -> np.ndarray:
    """``n`` divided by its lengths along ``axis`` (zero rows kept)."""
    length = np.linalg.norm(n, axis=axis, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def fitted_normals(pm) -> np.ndarray:
    """Shading normal of every vertex, fitted to the original surface by least squares.

    Rule: an original vertex keeps its area-weighted vertex normal (what the
    original mesh is drawn with). The vertices created by a batch get, in
    the mesh just after that batch, the normals whose interpolation across
    the faces best matches the original surface's normals: samples are the
    original vertices ``p`` whose ancestor in that mesh is a created vertex
    ``u``, each weighted by its area (a third of its faces'), with target its
    vertex normal; ``p`` lies on the face of ``u``'s fan that its projection
    falls into most deeply (largest smallest barycentric coordinate; the
    coordinates then clamped to the face), and the fit minimizes
    ``Σ w_p |Σ_k b_k(p) n_k - n_p|²`` over the created vertices' normals
    ``n_u``, the other corners' normals fixed at their fitted values
    (:data:`FIT_SWEEPS` Jacobi sweeps from the subtree means of
    :func:`hierarchy_normals`; a vertex without samples keeps its subtree
    mean), then normalized. Interpolation across faces averages neighbouring
    vertex normals; the fit undoes that averaging where the original
    surface turns. Computed batch by batch up the hierarchy (children before
    parents): by C loops on up to two threads where the extension
    ``pmjax._normals_native`` is built, else by NumPy vectorized per batch,
    the same bits either way (each sum taken in one stated order: a
    vertex's face terms corner 0 of every face, then corner 1, then corner
    2; a slot's sample terms corner by corner, then by original vertex).
    The cone axes are not involved.

    Args:
        pm: a :class:`pmjax.PMData` or :class:`pmjax.ProgressiveMesh`.

    Returns:
        ``float32[V0 + P, 3]``, unit (zero for a vertex with no face area
        below it).
    """
    return np.ascontiguousarray(_fitted_by_axis(pm).T, dtype=np.float32)


def _load_native():
    """The fit's C loops (``pmjax/_normals_native.c``) as a ctypes library,
    or ``None`` where the extension is not built or ``PMJAX_NATIVE=0`` is set
    (the NumPy steps then run: the same bits)."""
    lib = open_library("pmjax._normals_native")
    if lib is None:
        return None
    lib.pmn_fitted_normals.restype = ctypes.c_int64
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    lib.pmn_fitted_normals.argtypes = [i64, i64, ptr, i64, i64, ptr, ptr, ptr, i64, ptr, i64, i64, i64, ptr]
    lib.pmn_leaf_order.restype = ctypes.c_int64
    lib.pmn_leaf_order.argtypes = [i64, i64, ptr, ptr, ptr, ptr, ptr]
    lib.pmn_view_normals.restype = ctypes.c_int64
    lib.pmn_view_normals.argtypes = [i64, ptr, ptr, ptr, ptr, ptr, ptr, ptr, ptr, i64, ptr, i64, ptr, ptr, i64,
                                     ctypes.c_double, i64, i64, ptr, ptr]
    lib.pmn_view_workspace.restype = ptr
    lib.pmn_view_workspace.argtypes = []
    lib.pmn_view_workspace_free.restype = None
    lib.pmn_view_workspace_free.argtypes = [ptr]
    return lib


# Tests set it to None to compare the NumPy steps with the C loops.
native = _load_native()
# Threads of the C loops (their parts write disjoint outputs: the same bits
# for any number), and the fewest slots or samples a step splits over them
# (below, a second thread costs more than it saves).
FIT_THREADS = min(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1, 2)
FIT_MIN_SPLIT = 4096


def _fitted_by_axis(pm) -> np.ndarray:
    """``float64[3, V0 + P]``: :func:`fitted_normals` by axis, before rounding
    (the C loops where they are built and the hierarchy's ids fit them, else
    NumPy: the same bits). Raises ``ValueError`` on a position that is NaN or
    infinite (no fit is defined there)."""
    vertices = np.asarray(pm.vertices)
    if not np.isfinite(vertices).all():
        bad = int(np.flatnonzero(~np.isfinite(vertices).all(axis=1))[0])
        raise ValueError(f"fitted_normals: vertex {bad} has a position that is not finite ({vertices[bad].tolist()})")
    fitted = _fitted_native(pm)
    return _fitted_numpy(pm) if fitted is None else fitted.T


def _native_hierarchy(pm):
    """``(V0, vertices, faces int32, offsets, kid_lo, kid_hi)`` as the C loops
    take them (vertices float32 or float64, each pcol's children the
    smaller id first), or ``None`` where the hierarchy's ids are outside
    what they take (faces on original vertices, each pcol consuming two
    vertices made before its batch, int32 ids)."""
    V0 = int(pm.n_original_vertices)
    vertices = np.asarray(pm.vertices)
    if vertices.dtype != np.float32:
        vertices = vertices.astype(np.float64)
    vertices = np.ascontiguousarray(vertices)
    faces = np.asarray(pm.faces)
    offsets = np.ascontiguousarray(pm.batch_offsets, np.int64)
    V = len(vertices)
    # The C loops take int32 ids: ranges are checked on the ids as given.
    if len(faces) >= 2**31 or (len(faces) and not (0 <= faces.min() and faces.max() < V0)):
        return None
    faces = np.ascontiguousarray(faces, np.int32)
    # Each pcol's children, the smaller id first (the order the subtree
    # means add them in).
    if hasattr(pm, "v1"):
        v1, v2 = np.asarray(pm.v1, np.int64), np.asarray(pm.v2, np.int64)
    else:
        parent = np.asarray(pm.parent, np.int64)
        consumed = _consumed(parent)
        if len(consumed) != 2 * (V - V0) or (parent[consumed] != np.repeat(np.arange(V - V0), 2)).any():
            return None
        v1, v2 = consumed[0::2], consumed[1::2]
    kid_lo, kid_hi = np.minimum(v1, v2), np.maximum(v1, v2)
    P = V - V0
    if not (V < 2**31 and vertices.shape == (V, 3) and faces.ndim == 2 and faces.shape[1] == 3
            and len(kid_lo) == P and len(offsets) >= 1 and offsets[0] == 0 and offsets[-1] == P
            and (np.diff(offsets) >= 0).all()):
        return None
    made = np.repeat(V0 + offsets[:-1], np.diff(offsets))
    if P and not (0 <= kid_lo.min() and (kid_lo < kid_hi).all() and (kid_hi < made).all()):
        return None
    if P and np.bincount(np.concatenate([kid_lo, kid_hi]), minlength=V).max() > 1:
        return None  # a vertex consumed twice
    return V0, vertices, faces, offsets, np.ascontiguousarray(kid_lo), np.ascontiguousarray(kid_hi)


def _fitted_native(pm) -> np.ndarray | None:
    """``float64[V0 + P, 3]``: the fit by the C loops, or ``None`` where the
    hierarchy's ids are outside what they take (:func:`_native_hierarchy`)
    or they are not built."""
    hierarchy = None if native is None else _native_hierarchy(pm)
    if hierarchy is None:
        return None
    V0, vertices, faces, offsets, kid_lo, kid_hi = hierarchy
    V = len(vertices)
    out = np.empty((V, 3))
    if native.pmn_fitted_normals(V0, V, vertices.ctypes.data, int(vertices.dtype == np.float64), len(faces),
                                 faces.ctypes.data, kid_lo.ctypes.data, kid_hi.ctypes.data, len(offsets) - 1,
                                 offsets.ctypes.data, FIT_SWEEPS, FIT_THREADS, FIT_MIN_SPLIT,
                                 out.ctypes.data):
        raise MemoryError("fitted_normals: out of memory in the fit's C loops")
    return out


def _fitted_numpy(pm) -> np.ndarray:
    """``float64[3, V0 + P]``: the fit by NumPy, batch by batch."""
    V0, vertices, faces, parent, offsets = _hierarchy_arrays(pm)
    # Arrays by axis ([3, n], each axis a contiguous row): the per-sample
    # arithmetic below is on one axis at a time.
    coordinates = np.ascontiguousarray(vertices.T)
    cross = _face_cross(coordinates, faces)
    total = _corner_sums(faces, cross, len(vertices)).T  # [V, 3]
    area = _corner_sums(faces, np.linalg.norm(cross, axis=0)[None] / 6.0, len(vertices))[0]
    # Every vertex's unit sum: the originals' vertex normals (kept, and the
    # samples' targets), the created ones' replaced batch by batch.
    out = np.ascontiguousarray(_unit(total).T)  # [3, V]
    samples = _Samples(coordinates[:, :V0], out[:, :V0], area[:V0].copy())
    vertices = cross = area = None  # memory: only what the batches need is kept
    consumed = _consumed_by_batch(parent, offsets)
    # rep[x]: the vertex that stands for x after the current batch (x itself
    # until consumed); corners[k]: corner k of the live faces after the
    # batch; ancestor[p]: the vertex standing for original vertex p.
    rep = np.arange(coordinates.shape[1])
    corners = np.ascontiguousarray(faces.T)
    faces = None
    ancestor = np.arange(V0)
    for b in range(len(offsets) - 1):
        kids = consumed[b]
        np.add.at(total, V0 + parent[kids], total[kids])
        lo, hi = V0 + offsets[b], V0 + offsets[b + 1]
        out[:, lo:hi] = _unit(total[lo:hi]).T
        rep[kids] = V0 + parent[kids]
        corners = rep[corners]
        corners = corners[:, (corners[0] != corners[1]) & (corners[1] != corners[2]) & (corners[0] != corners[2])]
        ancestor = rep[ancestor]
        out[:, lo:hi] = _fit_batch(coordinates, corners, ancestor, samples, out, lo, hi)
    return out


class _Samples(NamedTuple):
    """The original surface's samples: its vertices."""

    positions: np.ndarray  # [3, V0], by axis
    normals: np.ndarray  # [3, V0], unit area-weighted vertex normals by axis
    weights: np.ndarray  # [V0], a third of the area of each vertex's faces


# Rows of _face_geometry: what the barycentric coordinates on a face need of
# the face alone.
_A, _E0, _E1, _D00, _D01, _D11, _DET = 0, 3, 6, 9, 10, 11, 12


def _face_geometry(coordinates, tri) -> np.ndarray:
    """``[13, T]`` of the faces ``tri[3, T]`` (vertices ``coordinates[3,
    V]``): corner 0 (3 rows by axis), the edges from it to corners 1 and 2
    (3 rows each), their dot products d00, d01, d11 (summed x, y, z in that
    order) and the Gram determinant (1 for a degenerate face)."""
    a, b, c = (coordinates.take(corner, axis=1) for corner in tri)
    e0 = [b[k] - a[k] for k in range(3)]
    e1 = [c[k] - a[k] for k in range(3)]
    d00 = e0[0] * e0[0] + e0[1] * e0[1] + e0[2] * e0[2]
    d01 = e0[0] * e1[0] + e0[1] * e1[1] + e0[2] * e1[2]
    d11 = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]
    det = d00 * d11 - d01 * d01
    det = np.where(det > 0, det, 1.0)  # a degenerate face: coordinates of no use, rarely chosen
    return np.stack(list(a) + e0 + e1 + [d00, d01, d11, det])


# Samples located at a time by _own_faces: its temporaries take about 1.5 kB
# per sample (some 220 bytes for each face of a fan of about seven), so a
# block stays near 25 MB whatever the mesh.
SAMPLE_BLOCK = 1 << 14


def _own_faces(geometry, first, size, positions):
    """``(face int[S], barycentric float[3, S])`` of the face each sample
    lies on: of the ``size[s]`` faces ``first[s]:first[s] + size[s]`` of its
    fan (columns of ``geometry``, :func:`_face_geometry`), the one its
    projection (``positions[3, S]``) falls into most deeply (largest
    smallest barycentric coordinate; the first of equals), the coordinates
    clamped to the face."""
    # Each sample paired with each face of its fan.
    group = np.concatenate([[0], np.cumsum(size)[:-1]])
    pair = np.repeat(np.arange(len(size)), size)
    face = np.repeat(first - group, size) + np.arange(len(pair))
    g = geometry.take(face, axis=1)
    # Barycentric coordinates of the projection on each face's plane, the
    # dot products summed x, y, z in that order.
    e2 = [np.repeat(positions[k], size) - g[_A + k] for k in range(3)]
    d20 = e2[0] * g[_E0] + e2[1] * g[_E0 + 1] + e2[2] * g[_E0 + 2]
    d21 = e2[0] * g[_E1] + e2[1] * g[_E1 + 1] + e2[2] * g[_E1 + 2]
    b1 = (g[_D11] * d20 - g[_D01] * d21) / g[_DET]
    b2 = (g[_D00] * d21 - g[_D01] * d20) / g[_DET]
    b0 = 1.0 - b1 - b2
    # The deepest face of each sample (the first of equals: pairs are in
    # sample order, so the first pair of each sample among the deepest).
    depth = np.minimum(np.minimum(b0, b1), b2)
    deepest = np.flatnonzero(depth >= np.repeat(np.maximum.reduceat(depth, group), size))
    owner = pair[deepest]
    own = deepest[np.concatenate([[True], owner[1:] != owner[:-1]])]
    bary = np.stack([np.clip(b[own], 0.0, None) for b in (b0, b1, b2)])
    bary /= np.maximum(bary[0] + bary[1] + bary[2], np.finfo(float).tiny)
    return face[own], bary


def _fit_batch(coordinates, corners, ancestor, samples: _Samples, normals, lo: int, hi: int,
               sweeps: int = FIT_SWEEPS, relax: float = 1.0) -> np.ndarray:
    """``[3, hi - lo]`` by axis the fitted unit normals of the vertices
    ``lo:hi`` created by one batch, in the mesh of live faces ``corners[3,
    F]`` just after it (``coordinates[3, V]``: the vertices' positions;
    ``normals[3, V]``: every other vertex's, fixed; the batch's subtree
    means), by ``sweeps`` Jacobi sweeps, each moving a normal the share
    ``relax`` of the way to its step's solution (1: the whole way)."""
    # Step 1: each created vertex's fan: the live faces with it as a corner,
    # grouped by vertex; in a group the faces where it is corner 0, then
    # corner 1, then corner 2, each in mesh order (one sort of unique keys).
    touched = np.flatnonzero((corners[0] >= lo) | (corners[1] >= lo) | (corners[2] >= lo))
    start = normals[:, lo:hi]
    if not len(touched):
        return start
    tri = corners[:, touched]
    keys = []
    for k in range(3):
        on = np.flatnonzero(tri[k] >= lo)
        keys.append(((tri[k, on] - lo) * 3 + k) * len(touched) + on)
    keys = np.sort(np.concatenate(keys))
    fan = tri.take(keys % len(touched), axis=1)  # [3, fan faces] their corners
    fan_size = np.bincount(keys // (3 * len(touched)), minlength=hi - lo)
    fan_start = np.concatenate([[0], np.cumsum(fan_size)])
    # Step 2: the samples standing under a created vertex with a fan, and the
    # face of that fan each lies on, a block of samples at a time (memory
    # bounded by the block, not the mesh).
    sample = np.flatnonzero(ancestor >= lo)
    sample = sample[fan_size[ancestor[sample] - lo] > 0]
    if not len(sample):
        return start
    geometry = _face_geometry(coordinates, fan)
    parts = []
    for block in np.array_split(sample, -(-len(sample) // SAMPLE_BLOCK)):
        slot = ancestor[block] - lo
        parts.append(_own_faces(geometry, fan_start[slot], fan_size[slot], samples.positions[:, block]))
    geometry = None  # released before the sweeps' arrays
    own = fan.take(np.concatenate([f for f, _ in parts]), axis=1)  # [3, S] the corners of each sample's face
    bary = np.concatenate([b for _, b in parts], axis=1)  # [3, S]
    parts = None
    # Step 3: Jacobi sweeps of the weighted least squares over the created
    # vertices' normals, the other corners fixed. A sample's terms go to
    # the slots of its created corners, summed over the samples in order
    # corner by corner.
    weight, target = samples.weights[sample], samples.normals.take(sample, axis=1)
    on = [np.flatnonzero(own[k] >= lo) for k in range(3)]
    at = [own[k, on[k]] - lo for k in range(3)]
    diagonal = np.bincount(np.concatenate(at), np.concatenate([weight[on[k]] * bary[k, on[k]] ** 2 for k in range(3)]),
                           minlength=hi - lo)
    share = [weight[on[k]] * bary[k, on[k]] for k in range(3)]
    values = [normals.take(own[k], axis=1) for k in range(3)]  # [3, S] each, the created corners' set per sweep
    solved = diagonal > 0
    fitted = start
    for _ in range(sweeps):
        for k in range(3):
            values[k][:, on[k]] = fitted.take(at[k], axis=1)
        terms = [bary[k] * values[k] for k in range(3)]
        residual = target - (terms[0] + terms[1] + terms[2])
        # Each term: the residual without this corner, weighted.
        rhs = np.concatenate([share[k] * (residual.take(on[k], axis=1) + terms[k].take(on[k], axis=1))
                              for k in range(3)], axis=1)
        rhs = np.stack([np.bincount(np.concatenate(at), row, minlength=hi - lo) for row in rhs])
        step = rhs / np.where(solved, diagonal, 1.0)
        if relax != 1.0:
            # Weighted Jacobi: the step's share relax, the rest kept.
            step = (1.0 - relax) * fitted + relax * step
        fitted = np.where(solved, step, start)
    return _unit(fitted, axis=0)
