"""Version 2 of the ``.pmz`` file: compact and ordered coarse to fine.

The hierarchy is written as a stream of chunks: the base mesh, then one chunk
per batch from the coarsest to the finest, then a tail that only a full read
needs. Reading the base chunk and the first ``k`` batch chunks gives a valid
progressive mesh: its original mesh is the full hierarchy's mesh after all
but those ``k`` batches ran (``pmjax lod --batch``), its pcols those of the
``k`` batches. Byte layout: ``docs/format.md``.

Faces and vertices are named by leaf ranks: the original vertices numbered
in depth-first order of the collapse forest (roots by id, ``v1`` before
``v2``), so every vertex stands for a contiguous range of ranks. A face is
stored once, in the chunk of the batch that kills it, as the ranks of its
original corners; a reader that stopped at any batch finds each corner's
vertex as the range holding its rank, and the killer as the batch's pcol
whose range holds two corners. The forest's ranges come from one count per
pcol (the leaves under ``v1``).

Every transform is exact: floats are stored as their bits, positions as the
difference of order-preserving integer images from the parent's (a child lies
near its parent), the original vertices' normals as the difference from the
area-weighted normals recomputed from the faces, the shading normals as the
difference from the normals, and each chunk's arrays
byte-planed (byte ``k`` of every element together) before compression.

Encoding 2 (the header's ``encoding``; files without it are encoding 1) also
stores predictable values as differences from a prediction the reader makes
from what it has already decoded: a made vertex's unit normal against its
parent's normal, its largest component against the unit length of the other
two; a pcol's radius and cone half-angle against its parent's less their
distance and the angle between their axes; the costs against the previous
pcol's; a made vertex's shading normal like its
normal, against its cone axis. Any prediction gives the same bits back, since
the difference is stored: a poor one only costs bytes.
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import zlib
from concurrent.futures import Future, wait
from dataclasses import dataclass

import numpy as np

from ._clib import open_library
from ._pmdata import PMData, PMFormatError

MAGIC2 = b"\x89PMZ\r\n\x1a\n"
# zstd level for writing: the highest levels take several times longer for a
# few percent of size.
ZSTD_LEVEL = 12
ZLIB_LEVEL = 6
# Each chunk starts with the SHA-256 of its compressed bytes.
SHA_BYTES = 32
# The chunks' array encoding save_pm writes (the header's ``encoding``);
# a reader takes every encoding in ENCODINGS, 1 where the header has none.
ENCODING = 2
ENCODINGS = (1, 2)


_p = ctypes.c_void_p
_i64 = ctypes.c_int64


def _load_native():
    """The decoder's C loops (``pmjax/_pmz_native.c``) as a ctypes library,
    or ``None`` where the extension is not built or ``PMJAX_NATIVE=0`` is set
    (the NumPy steps then run: the same arrays, bit for bit)."""
    lib = open_library("pmjax._pmz_native")
    if lib is None:
        return None
    lib.pmz_unplane.restype = None
    lib.pmz_unplane.argtypes = [_p, _i64, _i64, _p]
    lib.pmz_float_from_residual.restype = None
    lib.pmz_float_from_residual.argtypes = [_i64, _p, _p, _p]
    lib.pmz_read_batch.restype = _i64
    lib.pmz_read_batch.argtypes = [_p, _i64, _i64, _i64, _i64, _i64, _i64] + [_p] * 12
    lib.pmz_batch_faces.restype = _i64
    lib.pmz_batch_faces.argtypes = [_p, _i64, _i64, _i64, _i64, _p, _p, _p, _p]
    lib.pmz_unit_from_residual.restype = None
    lib.pmz_unit_from_residual.argtypes = [_i64, _p, _p, _p]
    lib.pmz_float_from_planed.restype = None
    lib.pmz_float_from_planed.argtypes = [_i64, _p, _p, _p]
    lib.pmz_unit_from_planed.restype = None
    lib.pmz_unit_from_planed.argtypes = [_i64, _p, _p, _p]
    lib.pmz_place_faces.restype = None
    lib.pmz_place_faces.argtypes = [_i64, _i64, _i64, _p, _i64, _p, _p, _p, _p, _p, _p]
    lib.pmz_area_normals.restype = None
    lib.pmz_area_normals.argtypes = [_i64, _p, _p, _i64, _p, _p]
    return lib


# ctypes releases the GIL during each call: a second thread decompresses the
# next chunk meanwhile.
native = _load_native()

# Raised whenever a change of the decoding could give other arrays for the
# same bytes: records of earlier decodings (pmjax._structure.decoding_known)
# then no longer count. The reader's identity (pmjax._pmfile.READER_IDENTITY)
# also covers this module's code and the C loops' library by their contents.
DECODER_VERSION = 1


def _ptr(a) -> int:
    """Address of a C-contiguous array's first element (``a.ctypes.data``);
    the caller keeps ``a`` referenced until the C call returns."""
    return a.ctypes.data


def zstd_available() -> bool:
    try:
        import zstandard  # noqa: F401
    except ImportError:
        return False
    return True


def compress(raw: bytes, codec: str) -> bytes:
    """``raw`` compressed with ``codec`` (``"zstd"`` or ``"zlib"``)."""
    if codec == "zstd":
        import zstandard

        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(raw)
    return zlib.compress(raw, ZLIB_LEVEL)


def decompress(data, codec: str, size: int) -> bytes:
    """``data`` expanded to exactly ``size`` bytes; a stream that holds more
    or fewer raises ``ValueError`` without expanding beyond ``size``."""
    # Read at most one byte past the counts' size: a stream that declares or
    # holds more is refused without expanding it.
    if codec == "zstd":
        try:
            import zstandard
        except ImportError as exc:
            raise ValueError("the file is zstd-compressed and the zstandard package is not installed "
                             "(pip install zstandard)") from exc
        # Read in place (bytes, or a memoryview of a chunk's bytes). The
        # decompressors' own errors are not ValueError: worded as one, so
        # that the reader names the chunk.
        try:
            with zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=False) as r:
                out = r.read(size + 1)
        except zstandard.ZstdError as exc:
            raise ValueError(f"its zstd stream is damaged ({exc})") from exc
    elif codec == "zlib":
        d = zlib.decompressobj()
        try:
            out = d.decompress(data, size + 1)
        except zlib.error as exc:
            raise ValueError(f"its zlib stream is damaged ({exc})") from exc
        if not d.eof and len(out) == size:
            raise ValueError("the compressed stream ends early")
    else:
        raise ValueError(f"unknown codec {codec!r} (this pmjax reads zstd and zlib)")
    if len(out) != size:
        raise ValueError(f"expands to {len(out)} bytes, but the counts give {size}")
    return out


# --- exact array transforms --------------------------------------------------


def planes(a: np.ndarray) -> bytes:
    """Bytes of ``a`` grouped by byte position (all first bytes, then all
    second bytes, ...): floats and small integers then compress far better."""
    a = np.ascontiguousarray(a)
    return a.reshape(-1).view(np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()


def unplanes(raw: memoryview, dtype, shape) -> np.ndarray:
    """Inverse of :func:`planes`."""
    dtype = np.dtype(dtype)
    n = math.prod(shape)
    b = np.frombuffer(raw, np.uint8, n * dtype.itemsize)
    if native is not None:
        out = np.empty(shape, dtype)
        native.pmz_unplane(_ptr(b), n, dtype.itemsize, _ptr(out))
        return out
    return np.ascontiguousarray(b.reshape(dtype.itemsize, n).T).view(dtype).reshape(shape)


def ordered(x: np.ndarray) -> np.ndarray:
    """float32 -> uint32 order-preserving image (bit-exact, invertible): a
    negative float's bits inverted, a positive one's sign bit set."""
    b = np.ascontiguousarray(x, np.float32).view(np.uint32)
    mask = (np.uint32(0) - (b >> np.uint32(31))) | np.uint32(0x80000000)
    return b ^ mask


def unordered(u: np.ndarray) -> np.ndarray:
    """Inverse of :func:`ordered`."""
    u = np.asarray(u, np.uint32)
    mask = ((u >> np.uint32(31)) - np.uint32(1)) | np.uint32(0x80000000)
    return (u ^ mask).view(np.float32)


def zigzag(d: np.ndarray) -> np.ndarray:
    """Wrapped uint32 differences -> uint32 with small magnitudes small."""
    s = d.astype(np.uint32).view(np.int32)
    return ((s.astype(np.uint32) << np.uint32(1)) ^ (s >> 31).astype(np.uint32)).astype(np.uint32)


def unzigzag(z: np.ndarray) -> np.ndarray:
    z = z.astype(np.uint32)
    return ((z >> np.uint32(1)) ^ (np.uint32(0) - (z & np.uint32(1)))).astype(np.uint32)


def float_residual(x: np.ndarray, prediction: np.ndarray) -> np.ndarray:
    """uint32 residual of float32 ``x`` against float32 ``prediction``."""
    return zigzag(ordered(x) - ordered(prediction))


def float_from_residual(r: np.ndarray, prediction: np.ndarray) -> np.ndarray:
    """Inverse of :func:`float_residual`: float32 of ``r``'s shape."""
    if native is not None and r.dtype == np.uint32 and prediction.dtype == np.float32 and r.shape == prediction.shape:
        r, prediction = np.ascontiguousarray(r), np.ascontiguousarray(prediction)
        out = np.empty(r.shape, np.float32)
        native.pmz_float_from_residual(r.size, _ptr(r), _ptr(prediction), _ptr(out))
        return out
    return unordered(unzigzag(r) + ordered(prediction))


def float_from_planed(raw: memoryview, prediction: np.ndarray, out: np.ndarray) -> None:
    """``out[...] = float_from_residual(r, prediction)`` for the uint32
    residuals ``r`` that :func:`planes` made ``raw`` (``prediction`` and
    ``out``: C-contiguous float32 of ``r``'s shape), in one pass where the C
    loops are built."""
    if native is not None:
        b = np.frombuffer(raw, np.uint8, 4 * prediction.size)
        native.pmz_float_from_planed(prediction.size, _ptr(b), _ptr(prediction), _ptr(out))
    else:
        out[...] = float_from_residual(unplanes(raw, np.uint32, prediction.shape), prediction)


def unit_from_planed(raw: memoryview, guide: np.ndarray, out: np.ndarray) -> None:
    """``out[...] = unit_from_residual(r, guide)`` for the uint32 residuals
    ``r`` (``[m, 3]``) that :func:`planes` made ``raw``, in one pass where the
    C loops are built."""
    if native is not None:
        b = np.frombuffer(raw, np.uint8, 4 * guide.size)
        native.pmz_unit_from_planed(len(guide), _ptr(b), _ptr(guide), _ptr(out))
    else:
        out[...] = unit_from_residual(unplanes(raw, np.uint32, guide.shape), guide)


def _unit_axis(guide: np.ndarray) -> np.ndarray:
    """Per row of ``guide`` (float32 ``[m, 3]``), the first component of
    largest magnitude (a NaN is never the largest, as in the C loop)."""
    g = np.abs(guide)
    k = np.where(g[:, 1] > g[:, 0], 1, 0)
    return np.where(g[:, 2] > g[np.arange(len(g)), k], 2, k)


def _unit_component(x1: np.ndarray, x2: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """float32 ``sqrt(1 - x1² - x2²)`` (0 where that is not positive) with
    ``sign``'s sign: a unit vector's third component from the two others
    (float64 arithmetic, in this order)."""
    with np.errstate(invalid="ignore", over="ignore"):  # NaN and infinite components predict 0
        x1, x2 = x1.astype(np.float64), x2.astype(np.float64)
        s = 1.0 - (x1 * x1 + x2 * x2)
        return np.copysign(np.sqrt(np.where(s > 0, s, 0.0)).astype(np.float32), sign)


def unit_residual(x: np.ndarray, guide: np.ndarray) -> np.ndarray:
    """uint32 ``[m, 3]`` residuals of unit (or zero) float32 vectors ``x``
    against ``guide`` (float32 ``[m, 3]``, a nearby unit vector): the two
    components other than the guide's largest against the guide's, the
    largest against the unit length of those two (exact for any ``x``)."""
    rows = np.arange(len(x))
    k = _unit_axis(guide)
    prediction = np.array(guide, np.float32)
    prediction[rows, k] = _unit_component(x[rows, (k + 1) % 3], x[rows, (k + 2) % 3], guide[rows, k])
    return float_residual(x, prediction)


def unit_from_residual(r: np.ndarray, guide: np.ndarray) -> np.ndarray:
    """Inverse of :func:`unit_residual`: float32 ``[m, 3]``."""
    if native is not None and r.dtype == np.uint32 and guide.dtype == np.float32 and r.shape == guide.shape:
        r, guide = np.ascontiguousarray(r), np.ascontiguousarray(guide)
        out = np.empty(r.shape, np.float32)
        native.pmz_unit_from_residual(len(r), _ptr(r), _ptr(guide), _ptr(out))
        return out
    rows = np.arange(len(r))
    k = _unit_axis(guide)
    out = unordered(unzigzag(r) + ordered(guide))  # right but for component k
    pk = _unit_component(out[rows, (k + 1) % 3], out[rows, (k + 2) % 3], guide[rows, k])
    out[rows, k] = unordered(unzigzag(r[rows, k]) + ordered(pk))
    return out


def _parent_less(parent_value: np.ndarray, parent_vec: np.ndarray, vec: np.ndarray, has_parent: np.ndarray,
                 measure) -> np.ndarray:
    """float32 ``[n]``: ``parent_value - measure(c)`` with ``c`` the distance
    between ``parent_vec`` and ``vec`` (float32 ``[n, 3]``; float64 sums in
    x, y, z order, so that every reader computes the same bits), 0 where
    that is not positive or there is no parent (``has_parent``, bool ``[n]``)."""
    d = parent_vec.astype(np.float64) - vec.astype(np.float64)
    c = np.sqrt((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2])
    p = parent_value.astype(np.float64) - measure(c)
    return np.where(has_parent & (p > 0), p, 0.0).astype(np.float32)


def radius_prediction(radius_parent: np.ndarray, parent_xyz: np.ndarray, xyz: np.ndarray,
                      has_parent: np.ndarray) -> np.ndarray:
    """float32 ``[n]``: a pcol's radius as its parent's radius less the
    distance between their vertices (the parent's sphere holds the child's
    at that distance, tightly for one of its two children), 0 where that is
    not positive or there is no parent. Arguments: the parent's radius
    (float32 ``[n]``), both positions (float32 ``[n, 3]``, model units), and
    whether the pcol's vertex has a parent (bool ``[n]``)."""
    return _parent_less(radius_parent, parent_xyz, xyz, has_parent, lambda c: c)


def alpha_prediction(alpha_parent: np.ndarray, parent_normal: np.ndarray, normal: np.ndarray,
                     has_parent: np.ndarray) -> np.ndarray:
    """float32 ``[n]``: a pcol's cone half-angle as its parent's less the
    angle between their axes (the parent's cone holds the child's turned by
    that angle, tightly for one of its two children), 0 where that is not
    positive or there is no parent. The angle is taken from the chord ``c``
    between the unit axes as ``c + c³/24`` (square roots only, so that every
    reader computes the same bits). Arguments: the parent's half-angle
    (float32 ``[n]``, radians), both axes (float32 ``[n, 3]``), and whether
    the pcol's vertex has a parent (bool ``[n]``)."""
    return _parent_less(alpha_parent, parent_normal, normal, has_parent, lambda c: c + c * c * c / 24.0)


def _ordered64(x: np.ndarray) -> np.ndarray:
    b = np.ascontiguousarray(x, np.float64).view(np.uint64)
    return b ^ ((np.uint64(0) - (b >> np.uint64(63))) | np.uint64(1 << 63))


def cost_code(cost: np.ndarray) -> np.ndarray:
    """float64 costs ``[n]`` as uint64: the wrapped difference of each
    cost's ordered image from the previous one's (0 before the first),
    zigzagged (costs mostly rise with the pcol order)."""
    u = _ordered64(cost)
    d = (u - np.concatenate([np.zeros(1, np.uint64), u[:-1]])).view(np.int64)
    return ((d << np.int64(1)) ^ (d >> np.int64(63))).view(np.uint64)


def cost_decode(z: np.ndarray) -> np.ndarray:
    """Inverse of :func:`cost_code`: float64 ``[n]``."""
    z = np.asarray(z, np.uint64)
    d = (z >> np.uint64(1)) ^ (np.uint64(0) - (z & np.uint64(1)))
    u = np.cumsum(d, dtype=np.uint64)
    mask = ((u >> np.uint64(63)) - np.uint64(1)) | np.uint64(1 << 63)
    return (u ^ mask).view(np.float64)


def area_normals(vertices: np.ndarray, faces: np.ndarray, n: int) -> np.ndarray:
    """``float32[n, 3]`` unit area-weighted vertex normals (zero without
    area), summed in float64 in face order as the builder sums them."""
    if (native is not None and vertices.dtype == np.float32 and faces.dtype == np.int32 and len(vertices) >= n
            and (not faces.size or (faces.min() >= 0 and faces.max() < n))):
        vertices, faces = np.ascontiguousarray(vertices), np.ascontiguousarray(faces)
        out, total = np.empty((n, 3), np.float32), np.empty((n, 3))
        native.pmz_area_normals(len(faces), _ptr(faces), _ptr(vertices), n, _ptr(total), _ptr(out))
        return out
    x, y, z = (vertices[:, k].astype(np.float64) for k in range(3))
    f0, f1, f2 = faces[:, 0], faces[:, 1], faces[:, 2]
    ax, ay, az = x[f1] - x[f0], y[f1] - y[f0], z[f1] - z[f0]
    bx, by, bz = x[f2] - x[f0], y[f2] - y[f0], z[f2] - z[f0]
    corner = faces.reshape(-1)
    total = np.empty((n, 3))
    for k, cross in enumerate((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx)):
        # Each face's cross product once per corner, in corner order: every
        # vertex sums its faces in face order.
        weights = np.empty((len(faces), 3))
        weights[:] = cross[:, None]
        total[:, k] = np.bincount(corner, weights.reshape(-1), minlength=n)
    length = np.sqrt(total[:, 0] * total[:, 0] + total[:, 1] * total[:, 1] + total[:, 2] * total[:, 2])
    return (total / np.where(length > 0, length, 1.0)[:, None]).astype(np.float32)


# --- the collapse forest's leaf ranges ---------------------------------------


def leaf_ranges(V0: int, v1: np.ndarray, v2: np.ndarray, offsets: np.ndarray):
    """Depth-first leaf ranges of every vertex.

    Returns:
        ``(roots int64[R], start int64[V], count int64[V])``: vertex ``v``
        stands for the original vertices of ranks ``start[v] .. start[v] +
        count[v] - 1``; roots (vertices no pcol consumes) in id order.
    """
    P = len(v1)
    V = V0 + P
    count = np.ones(V, np.int64)
    for b in range(len(offsets) - 1):
        lo, hi = int(offsets[b]), int(offsets[b + 1])
        count[V0 + lo:V0 + hi] = count[v1[lo:hi]] + count[v2[lo:hi]]
    consumed = np.zeros(V, bool)
    consumed[v1] = True
    consumed[v2] = True
    roots = np.flatnonzero(~consumed)
    start = np.zeros(V, np.int64)
    start[roots] = np.cumsum(count[roots]) - count[roots]
    for b in range(len(offsets) - 2, -1, -1):
        lo, hi = int(offsets[b]), int(offsets[b + 1])
        s = start[V0 + lo:V0 + hi]
        start[v1[lo:hi]] = s
        start[v2[lo:hi]] = s + count[v1[lo:hi]]
    return roots, start, count


def face_killers(ranks: np.ndarray, starts: np.ndarray, counts: np.ndarray, first: int) -> np.ndarray:
    """Per face (corner ranks ``int64[n, 3]``), the pcol among ``first ..
    first + len(starts) - 1`` (one batch: disjoint ranges) whose range holds
    two of its corners, or -1 where none does."""
    if not len(starts):  # a batch without pcols kills no face (as the C loop finds)
        return np.full(len(ranks), -1, np.int32)
    order = np.argsort(starts, kind="stable")
    s = starts[order]
    i = np.searchsorted(s, ranks, side="right") - 1
    ok = (i >= 0) & (ranks < s[np.maximum(i, 0)] + counts[order][np.maximum(i, 0)])
    cand = np.where(ok, order[np.maximum(i, 0)] + first, -1)
    c0, c1, c2 = cand[:, 0], cand[:, 1], cand[:, 2]
    k = np.where((c0 >= 0) & ((c0 == c1) | (c0 == c2)), c0, np.where((c1 >= 0) & (c1 == c2), c1, -1))
    return k.astype(np.int32)


def rank_owner(ranks: np.ndarray, starts: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Per rank, the vertex of ``ids`` whose range holds it (ranges disjoint,
    covering every rank)."""
    order = np.argsort(starts, kind="stable")
    return ids[order][np.searchsorted(starts[order], ranks, side="right") - 1]


# --- writing -------------------------------------------------------------------


def encode(pm: PMData, codec: str, encoding: int = ENCODING) -> tuple[dict, list[tuple[str, bytes, int]]]:
    """Chunks of ``pm`` (already validated and structure-checked), arrays
    stored in ``encoding`` (one of :data:`ENCODINGS`).

    Returns:
        ``(fields, chunks)``: header fields (``roots``, ``group_faces``) and
        per chunk ``(name, compressed bytes, raw size)``, coarse to fine.
    """
    fields, table = chunk_arrays(pm, encoding)
    chunks = []
    for name, parts in table:
        raw = b"".join(planes(a) for _, a in parts)
        chunks.append((name, compress(raw, codec), len(raw)))
    fields["codec"] = codec
    return fields, chunks


def chunk_arrays(pm: PMData, encoding: int = ENCODING) -> tuple[dict, list]:
    """The arrays each chunk of ``pm`` stores, before planing.

    Returns:
        ``(fields, table)``: header fields but ``codec``, and per chunk
        ``(name, [(part, array), ...])`` coarse to fine, ``part`` naming
        what the array holds (``"positions"``, ``"faces"``, ...).
    """
    V0, P, B = pm.n_original_vertices, pm.n_pcols, pm.n_batches
    off = pm.batch_offsets
    v1, v2 = pm.v1.astype(np.int64), pm.v2.astype(np.int64)
    roots, start, count = leaf_ranges(V0, v1, v2, off)
    ranks = start[pm.faces]
    # Group of each face: the batch of its killer, B for the base mesh.
    batch_of = np.repeat(np.arange(B), np.diff(off))
    group = np.where(pm.killer >= 0, batch_of[np.maximum(pm.killer, 0)] if P else 0, B)
    by_group = np.argsort(group, kind="stable")
    bounds = np.searchsorted(group[by_group], np.arange(B + 2))
    faces_of = lambda g: ranks[by_group[bounds[g]:bounds[g + 1]]]

    # The killers a reader derives must be the stored ones (check_structure
    # guarantees it; checked here so a file never depends on it silently).
    for b in range(B):
        lo, hi = int(off[b]), int(off[b + 1])
        sel = by_group[bounds[b]:bounds[b + 1]]
        got = face_killers(ranks[sel], start[V0 + lo:V0 + hi], count[V0 + lo:V0 + hi], lo)
        if not np.array_equal(got, pm.killer[sel]):
            raise PMFormatError("killers are not the first pcols merging two corners of their faces")

    created = roots >= V0
    table = [("base", [("roots", np.diff(roots, prepend=0).astype(np.int32)), ("counts", count[roots].astype(np.int32)),
                       ("positions", ordered(pm.vertices[roots])), ("normals", pm.normals[roots[created]]),
                       ("faces", ranks_code(faces_of(B)))])]
    # Each made vertex's parent, for encoding 2's predictions.
    parent = np.full(V0 + P, -1, np.int64)
    parent[v1], parent[v2] = np.arange(V0, V0 + P), np.arange(V0, V0 + P)
    for b in range(B - 1, -1, -1):
        lo, hi = int(off[b]), int(off[b + 1])
        a, c = v1[lo:hi], v2[lo:hi]
        here = pm.vertices[V0 + lo:V0 + hi]
        if encoding == 1:
            radius, alpha, cost = pm.radius[lo:hi], pm.alpha[lo:hi], pm.cost[lo:hi]
            normals = [pm.normals[a[a >= V0]], pm.normals[c[c >= V0]]]
        else:
            w = parent[V0 + lo:V0 + hi]
            up = np.maximum(w, V0)
            radius = float_residual(pm.radius[lo:hi], radius_prediction(
                pm.radius[up - V0], pm.vertices[up], here, w >= 0))
            alpha = float_residual(pm.alpha[lo:hi], alpha_prediction(
                pm.alpha[up - V0], pm.normals[up], pm.normals[V0 + lo:V0 + hi], w >= 0))
            cost = cost_code(pm.cost[lo:hi])
            normals = [unit_residual(pm.normals[x[x >= V0]], pm.normals[V0 + lo:V0 + hi][x >= V0]) for x in (a, c)]
        table.append((f"batch {b}", [
            ("v1, v2", pm.v1[lo:hi]), ("v1, v2", pm.v2[lo:hi]), ("counts", count[a].astype(np.int32)),
            ("radius", radius), ("alpha", alpha), ("delta", pm.delta[lo:hi]), ("mu", pm.mu[lo:hi]), ("cost", cost),
            ("metric", pm.metric[lo:hi]),
            ("positions", float_residual(pm.vertices[a], here)), ("positions", float_residual(pm.vertices[c], here)),
            *(("normals", x) for x in normals), ("faces", ranks_code(faces_of(b)))]))
    tail = [("face groups", group.astype(group_dtype(B))),
            ("original normals", float_residual(pm.normals[:V0], area_normals(pm.vertices[:V0], pm.faces, V0)))]
    if pm.shading_normals is not None:
        # An original vertex's shading normal is its area-weighted normal, a
        # created one's is near its cone axis: residuals against the normals.
        if encoding == 1:
            tail.append(("shading normals", float_residual(pm.shading_normals, pm.normals)))
        else:
            tail += [("shading normals", float_residual(pm.shading_normals[:V0], pm.normals[:V0])),
                     ("shading normals", unit_residual(pm.shading_normals[V0:], pm.normals[V0:]))]
    table.append(("tail", tail))
    fields = dict(roots=int(len(roots)), batch_offsets=[int(o) for o in off],
                  group_faces=[int(bounds[g + 1] - bounds[g]) for g in range(B, -1, -1)],
                  shading_normals=pm.shading_normals is not None)
    if encoding != 1:
        fields["encoding"] = encoding
    return fields, table


# Bytes per pcol of a batch chunk, whatever its children: v1, v2 and the
# count under v1 (int32 each), radius, alpha, delta, mu (4 each), cost (8),
# metric (1) and both children's positions (12 each).
PCOL_BYTES = 12 + 16 + 8 + 1 + 24


def batch_bytes(n: int, made: int, n_faces: int) -> int:
    """Raw bytes of a batch chunk of ``n`` pcols whose children include
    ``made`` made vertices (each with its normal, 12 bytes) and that stores
    ``n_faces`` faces (12 bytes each); the C loops' ``pmz_read_batch``
    computes the same."""
    return PCOL_BYTES * n + 12 * made + 12 * n_faces


def group_dtype(B: int):
    return np.uint8 if B < 256 else np.uint16 if B < 65536 else np.uint32


def ranks_code(r: np.ndarray) -> np.ndarray:
    """Corner ranks ``[n, 3]`` as uint32: the first corner's difference from
    the previous face's first corner, the others' from the first (zigzag)."""
    r = r.astype(np.int64)
    first = np.diff(r[:, 0], prepend=0)
    out = np.stack([first, r[:, 1] - r[:, 0], r[:, 2] - r[:, 0]], axis=1)
    return zigzag(out.astype(np.int32).view(np.uint32))


def ranks_decode(z: np.ndarray) -> np.ndarray:
    d = unzigzag(z).view(np.int32).astype(np.int64)
    first = np.cumsum(d[:, 0])
    return np.stack([first, first + d[:, 1], first + d[:, 2]], axis=1)


# --- reading -------------------------------------------------------------------


class _Cursor:
    """Consumes a chunk's raw bytes array by array."""

    def __init__(self, raw: bytes):
        self.raw, self.at = memoryview(raw), 0

    def take(self, dtype, shape) -> np.ndarray:
        n = math.prod(shape) * np.dtype(dtype).itemsize
        if self.at + n > len(self.raw):
            raise ValueError(f"its arrays need more than its {len(self.raw)} bytes")
        a = unplanes(self.raw[self.at:self.at + n], dtype, shape)
        self.at += n
        return a

    def planed(self, dtype, shape) -> memoryview:
        """The next array's bytes, still byte-planed."""
        n = math.prod(shape) * np.dtype(dtype).itemsize
        if self.at + n > len(self.raw):
            raise ValueError(f"its arrays need more than its {len(self.raw)} bytes")
        self.at += n
        return self.raw[self.at - n:self.at]

    def done(self) -> None:
        if self.at != len(self.raw):
            raise ValueError(f"{len(self.raw) - self.at} bytes are left over after its arrays")


# A vertex's record in the reader's state (the C loops' Range): its leaf
# range, its parent (-1 for roots), and whether it is a vertex of the mesh
# read so far; one record per vertex, so that the C loops' scattered reads
# and writes of a child touch one line. Stream's start, count, parent and
# seen are views of these fields.
RANGE_DTYPE = np.dtype([("start", np.int32), ("count", np.int32), ("parent", np.int32), ("seen", np.int32)])


@dataclass
class Stream:
    """What a reader knows after the chunks read so far (full hierarchy ids)."""

    V0: int
    P: int
    offsets: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray
    start: np.ndarray  # int[V]: each vertex's first leaf rank
    count: np.ndarray  # int[V]: its leaves
    seen: np.ndarray  # bool or int32 [V]: the vertex appeared (a root or a read pcol's child) and is not split
    v1: np.ndarray
    v2: np.ndarray
    radius: np.ndarray
    alpha: np.ndarray
    delta: np.ndarray
    mu: np.ndarray
    cost: np.ndarray
    metric: np.ndarray
    face_ranks: list  # per group read, coarse first: [n, 3] (int32 or int64)
    killers: list  # per group read: int32[n]
    encoding: int = 1  # the chunks' array encoding (ENCODINGS)
    parent: np.ndarray | None = None  # int32[V]: each read vertex's parent, -1 for roots
    ranges: np.ndarray | None = None  # RANGE_DTYPE[V] holding start, count, parent and seen (the C decoder's)
    owner: np.ndarray | None = None  # int32[V0]: the C decoder's rank -> pcol stamps
    pointers: tuple | None = None  # the C decoder's addresses of the arrays above (fixed for a read)


def new_stream(V0: int, P: int, offsets: np.ndarray, encoding: int = 1) -> Stream:
    V = V0 + P
    # Zero pages until written (a forged header's counts must not cost a
    # write over all V records): a root's parent is set to -1 as the base is
    # read, every other vertex's as its batch is, before anything reads it.
    ranges = np.zeros(V, RANGE_DTYPE)
    return Stream(V0, P, offsets, np.zeros((V, 3), np.float32), np.zeros((V, 3), np.float32),
                  ranges["start"], ranges["count"], ranges["seen"],
                  *(np.zeros(P, np.int32) for _ in range(2)), *(np.zeros(P, np.float32) for _ in range(4)),
                  np.zeros(P, np.float64), np.zeros(P, np.uint8), [], [], encoding, ranges["parent"], ranges)


def read_base(s: Stream, raw: bytes, R: int, n_faces: int) -> None:
    """Decode the base chunk into ``s`` (raises ``ValueError`` on bad content)."""
    c = _Cursor(raw)
    roots = np.cumsum(c.take(np.int32, (R,)).astype(np.int64))
    count = c.take(np.int32, (R,)).astype(np.int64)
    V = s.V0 + s.P
    if R and (roots[0] < 0 or roots[-1] >= V or np.any(np.diff(roots) <= 0)):
        raise ValueError("its root ids are not rising vertex ids")
    if np.any(count < 1) or (R and np.any(count[roots < s.V0] != 1)) or int(count.sum()) != s.V0:
        raise ValueError(f"its roots' leaf counts do not cover the {s.V0} original vertices")
    s.seen[roots] = True
    s.parent[roots] = -1
    s.count[roots] = count
    s.start[roots] = np.cumsum(count) - count
    s.vertices[roots] = unordered(c.take(np.uint32, (R, 3)))
    created = roots[roots >= s.V0]
    s.normals[created] = c.take(np.float32, (len(created), 3))
    ranks = ranks_decode(c.take(np.uint32, (n_faces, 3)))
    c.done()
    if np.any((ranks < 0) | (ranks >= s.V0)):
        raise ValueError(f"a face corner's rank is outside [0, {s.V0})")
    s.face_ranks.append(ranks)
    s.killers.append(np.full(n_faces, -1, np.int32))


def read_batch(s: Stream, raw: bytes, b: int, n_faces: int, pool=None) -> None:
    """Decode batch ``b``'s chunk into ``s`` (raises ``ValueError`` on bad
    content), by the C loops where they are built; otherwise by NumPy steps.
    With ``pool`` (an executor) its killers (and, by the C loops, its face
    ranks) are found beside the caller: its entry of ``s.killers`` is then a
    future, resolved by :func:`settle` (which raises a bad rank's
    ``ValueError``) or :func:`killers_of`."""
    V0 = s.V0
    lo, hi = int(s.offsets[b]), int(s.offsets[b + 1])
    n = hi - lo
    # The C loops need the arrays' room for the face counts the header gives;
    # a chunk without it fails either way, and the NumPy steps name the
    # failure without allocating for those counts.
    if native is not None and len(raw) >= batch_bytes(n, 0, n_faces):
        _read_batch_native(s, raw, lo, hi, n_faces, pool if n_faces >= FACES_BESIDE else None)
        return
    c = _Cursor(raw)
    a, d = c.take(np.int32, (n,)), c.take(np.int32, (n,))
    c1 = c.take(np.int32, (n,)).astype(np.int64)
    for code, idx in ((2, a), (3, d)):
        bad = (idx < 0) | (idx >= V0 + lo)
        if bad.any():
            raise ValueError(_BATCH_ERRORS[code].format(lo + int(np.flatnonzero(bad)[0])))
    # Each failure names its first pcol as the C loop's does: the children
    # taken in the order v1, v2 of pcol lo, then of lo + 1, ...; a child is
    # bad where it was seen before or earlier in that order.
    both = np.concatenate([a, d])
    order = np.stack([a, d], axis=1).reshape(-1)
    repeat = np.ones(len(order), bool)
    repeat[np.unique(order, return_index=True)[1]] = False
    bad = s.seen[order].astype(bool) | repeat
    if bad.any():
        raise ValueError(_BATCH_ERRORS[4].format(lo + int(np.flatnonzero(bad)[0]) // 2))
    u = np.arange(V0 + lo, V0 + hi)
    bad = ~s.seen[u].astype(bool)
    if bad.any():
        raise ValueError(_BATCH_ERRORS[5].format(lo + int(np.flatnonzero(bad)[0])))
    total = s.count[u]
    c2 = total - c1
    bad = (c1 < 1) | (c2 < 1) | ((a < V0) & (c1 != 1)) | ((d < V0) & (c2 != 1))
    if bad.any():
        raise ValueError(_BATCH_ERRORS[6].format(lo + int(np.flatnonzero(bad)[0])))
    s.v1[lo:hi], s.v2[lo:hi] = a, d
    s.parent[a], s.parent[d] = u, u
    s.seen[both] = True
    s.seen[u] = False
    s.count[a], s.count[d] = c1, c2
    s.start[a], s.start[d] = s.start[u], s.start[u] + c1
    if s.encoding == 1:
        s.radius[lo:hi] = c.take(np.float32, (n,))
        s.alpha[lo:hi] = c.take(np.float32, (n,))
    else:
        w = s.parent[u].astype(np.int64)
        up = np.maximum(w, V0)
        s.radius[lo:hi] = float_from_residual(c.take(np.uint32, (n,)), radius_prediction(
            s.radius[up - V0], s.vertices[up], s.vertices[u], w >= 0))
        s.alpha[lo:hi] = float_from_residual(c.take(np.uint32, (n,)), alpha_prediction(
            s.alpha[up - V0], s.normals[up], s.normals[u], w >= 0))
    for name in ("delta", "mu"):
        getattr(s, name)[lo:hi] = c.take(np.float32, (n,))
    s.cost[lo:hi] = c.take(np.float64, (n,)) if s.encoding == 1 else cost_decode(c.take(np.uint64, (n,)))
    s.metric[lo:hi] = c.take(np.uint8, (n,))
    here = s.vertices[u]
    s.vertices[a] = float_from_residual(c.take(np.uint32, (n, 3)), here)
    s.vertices[d] = float_from_residual(c.take(np.uint32, (n, 3)), here)
    for idx in (a, d):
        made = idx >= V0
        if s.encoding == 1:
            s.normals[idx[made]] = c.take(np.float32, (int(made.sum()), 3))
        else:
            s.normals[idx[made]] = unit_from_residual(c.take(np.uint32, (int(made.sum()), 3)), s.normals[u[made]])
    ranks = ranks_decode(c.take(np.uint32, (n_faces, 3)))
    c.done()
    if np.any((ranks < 0) | (ranks >= V0)):
        raise ValueError(f"a face corner's rank is outside [0, {V0})")
    s.face_ranks.append(ranks)
    # The killers need only this batch's ranges, which finer chunks leave
    # alone: with a pool they are found beside the next chunks' decoding.
    job = (face_killers, ranks, s.start[u], s.count[u], lo)
    s.killers.append(pool.submit(*job) if pool is not None else job[0](*job[1:]))


# A batch chunk's failures by pmz_read_batch's outcome codes
# (pmjax/_pmz_native.c), each with the offending pcol (or the bytes left
# over): the NumPy steps of read_batch word theirs from the same table.
_BATCH_ERRORS = {
    2: "v1 of pcol {} is not a vertex made before its batch",
    3: "v2 of pcol {} is not a vertex made before its batch",
    4: "a pcol's child is already a vertex of the coarser mesh (pcol {})",
    5: "a pcol splits a vertex the coarser chunks did not make (pcol {})",
    6: "a pcol's leaf counts do not split its vertex's (pcol {})",
    7: "{} bytes are left over after its arrays",
}


# Fewest faces whose ranks and killers the C loops find on a pool's thread
# (beside the next chunks' decoding): fewer cost less than the handing over.
FACES_BESIDE = 1 << 12
# Fewest faces whose placing finish_full splits in two halves, the second on
# a pool's thread: each half then places at least FACES_BESIDE faces, the
# least that repays handing work to the pool (the placing reads as much at
# random per face as the ranks' check does).
FACES_SPLIT = 2 * FACES_BESIDE


def _read_batch_native(s: Stream, raw, lo: int, hi: int, n_faces: int, pool=None) -> None:
    """:func:`read_batch` in C: the same checks in the same order, the same
    state and arrays. The face ranks and killers are found by a second pass,
    on ``pool`` (an executor) if given: this batch's killers are then a
    future whose ``result()`` raises ``ValueError`` for a bad rank, to be
    resolved (by :func:`settle`) before a finer batch's failure is raised."""
    V0 = s.V0
    buf = np.frombuffer(raw, np.uint8)
    info = np.zeros(1, np.int64)
    if s.pointers is None:
        s.owner = np.full(V0, -1, np.int32)
        s.pointers = tuple(_ptr(a) for a in (s.ranges, s.vertices, s.normals, s.v1, s.v2, s.radius, s.alpha, s.delta,
                                             s.mu, s.cost, s.metric))
    code = native.pmz_read_batch(_ptr(buf), len(buf), V0, lo, hi, n_faces, s.encoding, *s.pointers, _ptr(info))
    if code == 1:
        raise ValueError(f"its arrays need more than its {len(buf)} bytes")
    if code:
        raise ValueError(_BATCH_ERRORS[code].format(int(info[0])))
    ranks = np.empty((n_faces, 3), np.int32)
    killer = np.empty(n_faces, np.int32)

    def faces():
        # buf, ranks and killer stay referenced by this closure until it returns.
        if native.pmz_batch_faces(_ptr(buf) + len(buf) - 12 * n_faces, n_faces, V0, lo, hi, _ptr(s.ranges),
                                  _ptr(ranks), _ptr(killer), _ptr(s.owner)):
            raise ValueError(f"a face corner's rank is outside [0, {V0})")
        return killer

    # The owner scratch serves one batch at a time: the previous batch's
    # pass (run beside this one's first) ends before this one's starts.
    if s.killers and not isinstance(s.killers[-1], np.ndarray):
        wait([s.killers[-1]])
    s.face_ranks.append(ranks)
    s.killers.append(pool.submit(faces) if pool is not None else faces())


def settle(s: Stream, i: int) -> None:
    """Wait for face group ``i``'s killers if a pool is finding them (raises
    the ``ValueError`` of a bad rank there)."""
    if not isinstance(s.killers[i], np.ndarray):
        s.killers[i] = s.killers[i].result()


def killers_of(s: Stream, names: list) -> None:
    """Resolve the killers found beside the decoding (``names``: each face
    group's chunk, for messages); a face no pcol of its batch kills raises
    ``ValueError`` naming its chunk (the base mesh's faces have none)."""
    for i in range(len(s.killers)):
        settle(s, i)
        killer = s.killers[i]
        if i and np.any(killer < 0):
            raise ValueError(f"chunk {names[i]!r}: face {int(np.flatnonzero(killer < 0)[0])} of the chunk has no "
                             "two corners under one of its batch's pcols")


def finish_full(s: Stream, raw: bytes, B: int, F: int, shading: bool, ready=None, pool=None) -> dict:
    """The full hierarchy's arrays from a stream that read every batch and
    the tail (raises ``ValueError`` on bad content). ``ready(name, array)``,
    if given, is called as each output array is final (its checksum can be
    computed meanwhile); with ``pool`` (an executor) the created vertices'
    shading normals are decoded beside the placing of the faces and the
    area normals."""
    V0, P = s.V0, s.P
    offsets = np.asarray(s.offsets, np.int64)
    c = _Cursor(raw)
    # Kept in its narrow dtype: NumPy's stable sort of small integers is a radix sort.
    group = c.take(group_dtype(B), (F,))
    residual = c.planed(np.uint32, (V0, 3))
    if shading and s.encoding == 1:
        shading = (c.planed(np.uint32, (V0 + P, 3)),)
    elif shading:
        shading = (c.planed(np.uint32, (V0, 3)), c.planed(np.uint32, (P, 3)))
    else:
        shading = None
    c.done()
    normals = s.normals
    shading_normals = None if shading is None else np.empty((V0 + P, 3), np.float32)
    # Rank -> original vertex id: each original vertex appeared exactly once.
    # int32 (as the faces): half the bytes that the placing reads at random.
    orig_of_rank = np.full(V0, -1, np.int32)
    orig_of_rank[s.start[:V0]] = np.arange(V0, dtype=np.int32)
    if np.any(orig_of_rank < 0) or not s.seen[:V0].all():
        raise ValueError("the original vertices' ranks are not a permutation")
    faces = np.empty((F, 3), np.int32)
    killer = np.empty(F, np.int32)
    # Groups were read base first, then batches B-1 .. 0.
    sizes = [len(r) for r in s.face_ranks]
    if np.any(group > B) or not np.array_equal(np.bincount(group, minlength=B + 1)[::-1], sizes):
        raise ValueError("the faces' groups do not match the chunks' face counts")
    half, second = F, None
    if native is not None:
        # One pass in face order: each face is the next of its group.
        ranks = [np.ascontiguousarray(r, np.int32) for r in s.face_ranks]
        kills = [np.ascontiguousarray(k, np.int32) for k in s.killers]
        rank_ptrs = (ctypes.c_void_p * len(ranks))(*(_ptr(r) for r in ranks))
        kill_ptrs = (ctypes.c_void_p * len(kills))(*(_ptr(k) for k in kills))

        def place(f0: int, f1: int, cursor: np.ndarray) -> None:
            # The pointer tables and arrays stay referenced by this closure.
            native.pmz_place_faces(f0, f1, B, _ptr(group), group.dtype.itemsize, rank_ptrs, kill_ptrs,
                                   _ptr(orig_of_rank), _ptr(cursor), _ptr(faces), _ptr(killer))

        # With a pool, the second half of the faces is placed there meanwhile:
        # its groups' cursors start at the first half's counts (read order).
        # Submitted before the shading and hashing jobs, so that the pool
        # starts it first and the calling thread's half does not wait for it.
        if pool is not None and F >= FACES_SPLIT:
            half = F // 2
            counts = np.bincount(group[:half], minlength=B + 1)[::-1]
            second = pool.submit(place, half, F, np.ascontiguousarray(counts, np.int64))
    created = None
    if shading is not None and len(shading) == 2:
        # The created vertices' shading normals need only their cone axes,
        # final since the batches: decoded into place now.
        created = _beside(pool, unit_from_planed, shading[1], normals[V0:], shading_normals[V0:])
    if ready is not None:
        # Final once every batch is read: the tail adds faces and normals only.
        for name in ("vertices", "v1", "v2", "radius", "alpha", "delta", "mu", "cost", "metric"):
            ready(name, getattr(s, name))
        ready("batch_offsets", offsets)
    if native is not None:
        place(0, half, np.zeros(B + 1, np.int64))
        if second is not None:
            second.result()
    else:
        by_group = np.argsort(group, kind="stable")
        bounds = np.concatenate([[0], np.cumsum(np.bincount(group, minlength=B + 1))])
        for i, g in enumerate(range(B, -1, -1)):
            sel = by_group[bounds[g]:bounds[g + 1]]
            faces[sel] = orig_of_rank[s.face_ranks[i]]
            killer[sel] = s.killers[i]
    if ready is not None:
        ready("faces", faces)
        ready("killer", killer)
    float_from_planed(residual, area_normals(s.vertices[:V0], faces, V0), normals[:V0])
    if ready is not None:
        ready("normals", normals)
    if shading is not None:
        if created is None:
            float_from_planed(shading[0], normals, shading_normals)
        else:
            float_from_planed(shading[0], normals[:V0], shading_normals[:V0])
            created.result()
        if ready is not None:
            ready("shading_normals", shading_normals)
    return dict(vertices=s.vertices, normals=normals, faces=faces, v1=s.v1, v2=s.v2, radius=s.radius,
                alpha=s.alpha, delta=s.delta, mu=s.mu, cost=s.cost, metric=s.metric,
                batch_offsets=offsets, killer=killer, shading_normals=shading_normals)


def finished(fn, *args) -> Future:
    """``fn(*args)`` run now, as a finished future (its result or exception
    delivered by ``result()``, like a pool's, so that failures are still
    reported in file order)."""
    future = Future()
    try:
        future.set_result(fn(*args))
    except BaseException as exc:
        future.set_exception(exc)
    return future


def _beside(pool, fn, *args) -> Future:
    """``fn(*args)`` submitted to ``pool``, or run now without one."""
    return pool.submit(fn, *args) if pool is not None else finished(fn, *args)


def finish_prefix(s: Stream, k: int) -> dict:
    """The progressive mesh of the base chunk and the ``k`` coarsest batches:
    its original vertices are the coarser mesh's vertices (in full-hierarchy
    id order), its pcols those of the batches read, in their order."""
    V0, P = s.V0, s.P
    B = len(s.offsets) - 1
    lo = int(s.offsets[B - k])
    frontier = np.flatnonzero(s.seen)
    W0 = len(frontier)
    new_id = np.full(V0 + P, -1, np.int64)
    new_id[frontier] = np.arange(W0)
    new_id[V0 + lo:] = W0 + np.arange(P - lo)
    ranks = np.concatenate(s.face_ranks)
    faces = new_id[rank_owner(ranks, s.start[frontier], frontier)].astype(np.int32)
    killer = np.concatenate(s.killers)
    killer = np.where(killer >= 0, killer - lo, -1).astype(np.int32)
    vertices = np.concatenate([s.vertices[frontier], s.vertices[V0 + lo:]])
    # The coarse mesh's vertices that are original vertices of the full
    # hierarchy get the area-weighted normals of the coarse mesh (refinement
    # never reads them); the others keep their cone axes.
    normals = np.concatenate([s.normals[frontier], s.normals[V0 + lo:]])
    own = area_normals(vertices[:W0], faces, W0)
    orig = frontier < V0
    normals[:W0][orig] = own[orig]
    return dict(vertices=vertices, normals=normals, faces=faces,
                v1=new_id[s.v1[lo:]].astype(np.int32), v2=new_id[s.v2[lo:]].astype(np.int32),
                radius=s.radius[lo:], alpha=s.alpha[lo:], delta=s.delta[lo:], mu=s.mu[lo:], cost=s.cost[lo:],
                metric=s.metric[lo:], batch_offsets=(np.asarray(s.offsets[B - k:], np.int64) - lo), killer=killer,
                shading_normals=None)


def chunk_sha(payload) -> bytes:
    return hashlib.sha256(payload).digest()



def stream_of(pm: PMData, k: int) -> Stream:
    """The reader's state after the base chunk and the ``k`` coarsest batches
    of ``pm`` (for a hierarchy already in memory, e.g. from a version 1 file)."""
    V0, P, B = pm.n_original_vertices, pm.n_pcols, pm.n_batches
    off = pm.batch_offsets
    v1, v2 = pm.v1.astype(np.int64), pm.v2.astype(np.int64)
    roots, start, count = leaf_ranges(V0, v1, v2, off)
    lo = int(off[B - k])
    seen = np.zeros(V0 + P, bool)
    seen[roots] = True
    seen[v1[lo:]] = True
    seen[v2[lo:]] = True
    seen[V0 + lo:] = False
    batch_of = np.repeat(np.arange(B), np.diff(off))
    group = np.where(pm.killer >= 0, batch_of[np.maximum(pm.killer, 0)] if P else 0, B)
    groups = [np.flatnonzero(group == g) for g in range(B, B - k - 1, -1)]
    return Stream(V0, P, off, pm.vertices, pm.normals, start, count, seen, pm.v1, pm.v2, pm.radius, pm.alpha,
                  pm.delta, pm.mu, pm.cost, pm.metric, [start[pm.faces[g]] for g in groups],
                  [pm.killer[g] for g in groups])
