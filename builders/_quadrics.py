"""Garland–Heckbert quadrics as packed struct-of-arrays (float64).

A quadric is the symmetric 4×4 matrix ``K = Σ w p pᵀ`` over planes
``p = (a, b, c, d)``; we keep its 10 distinct coefficients
``[aa, ab, ac, ad, bb, bc, bd, cc, cd, dd]`` so that summing two quadrics is a
vector add and a whole mesh's quadrics are one ``float64[N, 10]`` array.
"""

from __future__ import annotations

import numpy as np

from . import _native as native
from . import _rows as rows
from ._threads import MIN_ROWS, split_items
from ._topology import contains_edge, edge_keys

_I, _J = np.triu_indices(4)  # packed order above


def plane_quadrics(normals: np.ndarray, offsets: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Packed quadrics ``w · p pᵀ`` of planes ``n·x + d = 0``.

    Args:
        normals: ``(N, 3)`` unit plane normals.
        offsets: ``(N,)`` plane offsets ``d``.
        weights: ``(N,)`` weights (area for faces).

    Returns:
        ``float64[N, 10]``, column-major (each coefficient contiguous, as
        :func:`scatter_add` reads them).
    """
    # Column by column: fancy-indexing p[:, _I] * p[:, _J] would build two
    # (N, 10) temporaries. The columns are independent,
    # so two threads fill half of them each.
    p = [normals[:, 0], normals[:, 1], normals[:, 2], offsets]
    out = np.empty((len(_I), len(offsets)))

    def fill(ks):
        for k in ks:
            np.multiply(p[_I[k]], p[_J[k]], out=out[k])
            out[k] *= weights

    if len(offsets) >= MIN_ROWS:
        split_items(fill, list(range(len(_I))))
    else:
        fill(range(len(_I)))
    return out.T


def face_cross(pos: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(F, 3)`` cross products of the triangles' edges (twice the area times
    the unit normal)."""
    tri = pos[faces]
    return rows.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def face_geometry(pos: np.ndarray, faces: np.ndarray):
    """Unit normals, areas and raw cross products of triangles.

    Returns:
        ``(unit_normals (F, 3), areas (F,), cross (F, 3))``; degenerate faces get
        a zero normal.
    """
    cross = face_cross(pos, faces)
    length = rows.norm(cross)
    unit = cross / np.where(length > 0, length, 1.0)[:, None]
    return unit, 0.5 * length, cross


# Faces per step of the initial quadrics: their temporaries (about 200
# bytes per face) stay a few hundred MB at any model size.
CHUNK_FACES = 1 << 20


def vertex_quadrics(
    pos: np.ndarray, faces: np.ndarray, n_vertices: int, boundary_weight: float = 1.0, edges=None, *,
    out: np.ndarray | None = None, chunk: int | None = None,
) -> np.ndarray:
    """Area-weighted face quadrics summed per vertex, plus boundary planes.

    Boundary edges (used by one face) get a plane through the edge,
    perpendicular to the face, weighted by ``boundary_weight · |edge|²``, so
    open borders do not shrink (Garland–Heckbert §6.1).

    Args:
        pos: ``(V, 3)`` positions, model units.
        faces: ``(F, 3)`` vertex ids into ``pos``.
        n_vertices: length of the result (ids ``>= V`` get zero quadrics).
        boundary_weight: 0 disables the boundary planes.
        edges: :func:`builders._topology.unique_edges` of ``faces`` if the
            caller has them (they give the border edges without a sort).
        out: zeroed contiguous ``float64[n_vertices, 10]`` to fill (``None``:
            a new one).
        chunk: faces summed per step where the C loops are built (``None``:
            :data:`CHUNK_FACES`); the same sums in the same order as one
            step, since each vertex's rows are added in face order either way.

    Returns:
        ``float64[n_vertices, 10]`` (``out`` where given).
    """
    if out is None:
        out = np.zeros((n_vertices, 10))
    elif not (out.shape == (n_vertices, 10) and out.dtype == np.float64 and out.flags.c_contiguous):
        raise ValueError(f"vertex_quadrics: out must be a contiguous float64 ({n_vertices}, 10) array")
    for part in face_parts(faces, chunk, sums=True):
        unit, area, _ = face_geometry(pos, part)
        d = -np.einsum("ij,ij->i", unit, pos[part[:, 0]])
        kf = plane_quadrics(unit, d, area)
        unit = area = d = None
        scatter_add(kf, part.ravel(), n_vertices, repeat=3, out=out)
        kf = None
    if boundary_weight > 0:
        a, b, face = boundary_edges(faces, edges)
        if len(a):
            e = pos[b] - pos[a]
            unit = face_geometry(pos, faces[face])[0]
            m = rows.cross(e, unit)
            mlen = np.linalg.norm(m, axis=1)
            ok = mlen > 0
            m = m[ok] / mlen[ok, None]
            a, b, e = a[ok], b[ok], e[ok]
            kb = plane_quadrics(
                m, -np.einsum("ij,ij->i", m, pos[a]), boundary_weight * np.einsum("ij,ij->i", e, e)
            )
            # Summed apart, then added, on the border vertices' rows only
            # (elsewhere the sum would add +0, which changes no bit: the
            # face sums start from +0 and so are never -0).
            touched, slot = np.unique(np.concatenate([a, b]), return_inverse=True)
            out[touched] += scatter_add(np.concatenate([kb, kb]), slot.ravel(), len(touched))
    return out


def face_parts(faces: np.ndarray, chunk: int | None = None, sums: bool = False):
    """Consecutive parts of ``faces``, ``chunk`` at a time (``None``:
    :data:`CHUNK_FACES`), so that per-face temporaries stay bounded.

    ``sums``: the parts feed :func:`scatter_add` into one ``out``; the C
    loops add each vertex's rows in face order whatever the parts, NumPy's
    bincount sums a part apart, so without the C loops it is one part (the
    same bits as one step either way).
    """
    step = len(faces) if sums and not native.available() else (chunk or CHUNK_FACES)
    for lo in range(0, len(faces), max(step, 1)):
        yield faces[lo:lo + step]


def scatter_add(values: np.ndarray, index: np.ndarray, n: int, repeat: int = 1,
                out: np.ndarray | None = None) -> np.ndarray:
    """``out[index[i]] += values[i // repeat]`` for ``(N, k)`` values.

    bincount per column rather than np.add.at, which is unbuffered and
    slow for wide arrays; columns are made contiguous and repeated one at a
    time (a 2-D repeat and strided column reads touch every row's whole
    cache line per column), same sums bit for bit.

    Args:
        out: contiguous ``float64[n, k]`` to add to (``None``: zeros). The
            C loops add to it row by row, so consecutive parts of the index
            summed into one ``out`` (:func:`face_parts`) give the one step's
            bits; NumPy sums a step apart and adds it (the same bits for
            one step into zeros: its sums are never -0).
    """
    columns = np.ascontiguousarray(values.T)
    if native.available() and columns.dtype == np.float64:
        # One pass over the rows instead of one bincount per column.
        return native.scatter_add(columns, index, n, repeat, out=out)
    if repeat > 1:
        sums = np.stack([np.bincount(index, np.repeat(c, repeat), minlength=n) for c in columns], 1)
    else:
        sums = np.stack([np.bincount(index, c, minlength=n) for c in columns], 1)
    if out is None:
        return sums
    out += sums
    return out


def boundary_edges(faces: np.ndarray, edges=None):
    """Directed boundary edges: those used by exactly one face.

    Args:
        faces: ``(F, 3)`` vertex ids.
        edges: :func:`builders._topology.unique_edges` of ``faces``, or
            ``None`` to sort the keys here.

    Returns:
        ``(a, b, face)`` int arrays: the edge goes ``a -> b`` inside ``face``.
    """
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    key = edge_keys(a, b)
    # Keys seen once, from one sort; a closed mesh has none and stops here.
    if edges is not None:
        lonely = edges[3][edges[2] == 1]
    else:
        s = np.sort(key)
        once = np.ones(len(s), bool)
        same = s[1:] == s[:-1]
        once[1:] &= ~same
        once[:-1] &= ~same
        lonely = s[once]
    if len(lonely) == 0:
        empty = np.zeros(0, a.dtype)
        return empty, empty, np.zeros(0, np.int64)
    single = contains_edge(lonely, key)
    return a[single], b[single], np.repeat(np.arange(len(faces)), 3)[single]


def evaluate(q: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``xᵀ A x + 2 bᵀ x + c`` for packed quadrics ``q (N, 10)`` at ``x (N, 3)``."""
    X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
    return (
        q[:, 0] * X * X
        + 2 * q[:, 1] * X * Y
        + 2 * q[:, 2] * X * Z
        + 2 * q[:, 3] * X
        + q[:, 4] * Y * Y
        + 2 * q[:, 5] * Y * Z
        + 2 * q[:, 6] * Y
        + q[:, 7] * Z * Z
        + 2 * q[:, 8] * Z
        + q[:, 9]
    )


def optimal_placement(q: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Minimiser of each quadric, falling back to the best of a, b, midpoint.

    The 3×3 system ``A x = -b`` is solved by the adjugate. When ``A`` is
    ill-conditioned (flat or straight regions) or the solution lands far from
    the pair (more than the pair's length from its midpoint), the best of the
    two endpoints and their midpoint is used instead.

    Args:
        q: ``(N, 10)`` packed quadrics.
        a, b: ``(N, 3)`` endpoint positions.

    Returns:
        ``(position (N, 3), cost (N,))`` with cost ``>= 0``.
    """
    # Coefficient columns made contiguous first: every line below reads them,
    # and a strided column of a row-major (N, 10) loads a cache line per row.
    q = np.asfortranarray(q)
    a00, a01, a02, b0, a11, a12, b1, a22, b2 = (q[:, k] for k in (0, 1, 2, 3, 4, 5, 6, 7, 8))
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    scale = (a00 + a11 + a22) / 3.0
    solvable = np.abs(det) > 1e-9 * scale**3
    inv_det = np.where(solvable, 1.0 / np.where(solvable, det, 1.0), 0.0)
    x = -np.stack(
        [
            c00 * b0 + c01 * b1 + c02 * b2,
            c01 * b0 + c11 * b1 + c12 * b2,
            c02 * b0 + c12 * b1 + c22 * b2,
        ],
        1,
    ) * inv_det[:, None]
    mid = 0.5 * (a + b)
    length = rows.norm(b - a)
    solvable &= rows.norm(x - mid) <= length
    pos = x
    cost = evaluate(q, x)
    # Fallback where the optimum is unreliable, or (through rounding) no
    # better than the pair's own points.
    fall = ~solvable | (cost > np.minimum(evaluate(q, a), evaluate(q, b)))
    if fall.any():
        pos[fall], cost[fall] = subset_placement(q[fall], a[fall], b[fall], include_midpoint=True)
    return pos, np.maximum(cost, 0.0)


def subset_placement(q: np.ndarray, a: np.ndarray, b: np.ndarray, include_midpoint: bool = False):
    """Best of the endpoints (and optionally the midpoint) under quadric ``q``.

    Returns:
        ``(position (N, 3), cost (N,))``.
    """
    options = [a, b] + ([0.5 * (a + b)] if include_midpoint else [])
    costs = np.stack([evaluate(q, o) for o in options], 1)
    pick = np.argmin(costs, axis=1)
    pos = np.choose(pick[:, None], options)
    return pos, np.maximum(costs[np.arange(len(pick)), pick], 0.0)
