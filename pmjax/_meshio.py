"""Cleaning triangle meshes.

The cleaning is explicit and reported, so a user knows what was changed:
non-finite coordinates, out-of-range indices, degenerate and duplicate faces
and unreferenced vertices are either removed (with a count in the report) or,
when nothing usable is left, refused with a :class:`MeshError` that names the
file and the element. A triangle soup (an STL file: no vertex shared by two
faces) is welded first, merging vertices whose coordinates are equal in
float32, the precision pmjax stores; a model that float32 would damage (far
from the origin for its size) is refused.

Mesh files are read and written by :mod:`pmjax._meshfiles`, which defines
:class:`MeshError`; :func:`load_clean_mesh` reads a file and cleans it.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from ._meshfiles import MeshError, read_mesh, shown_name


@dataclasses.dataclass(frozen=True)
class CleanReport:
    """What :func:`clean_mesh` changed. All counts are of removed elements."""

    nonfinite_vertices: int = 0
    out_of_range_faces: int = 0
    faces_on_nonfinite_vertices: int = 0
    degenerate_faces: int = 0
    duplicate_faces: int = 0
    unreferenced_vertices: int = 0
    welded_vertices: int = 0  # merged into another vertex, not lost

    def messages(self) -> list[str]:
        """Human-readable lines, one per non-zero count."""
        out = []
        for field in dataclasses.fields(self):
            n = getattr(self, field.name)
            if n and field.name == "welded_vertices":
                out.append(f"welded a triangle soup: merged {n} vertices into others with equal float32 "
                           "coordinates (tolerance: float32 rounding)")
            elif n:
                out.append(f"removed {n} {field.name.replace('_', ' ')}")
        return out


def weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge vertices whose coordinates are equal once rounded to float32.

    Returns:
        ``(vertices, faces, kept)``: the first of each group of equal vertices
        is kept, in input order (``kept``: their input indices), and faces
        are renumbered to them.
    """
    _, first, inverse = np.unique(vertices.astype(np.float32), axis=0, return_index=True, return_inverse=True)
    # Keep the kept vertices in input order (np.unique sorts them).
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return vertices[first[order]], rank[inverse.ravel()][faces], first[order]


# Largest float32 spacing allowed at the model's farthest coordinate, as a
# share of its bounding-box diagonal (reached ~128 diagonals from the origin).
PRECISION_LIMIT = 2.0 ** -16


# The largest float32: pmjax stores positions in float32, so every coordinate
# must lie within it.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def rows_outside_float32(v: np.ndarray) -> np.ndarray:
    """``bool[V]``: the rows of ``v`` (``[V, 3]``) with a coordinate that is
    not finite or beyond float32's range, a position pmjax cannot store."""
    return ~np.all(np.abs(v) <= FLOAT32_MAX, axis=1)


def check_float32_precision(vertices: np.ndarray, *, source: str = "<array>") -> None:
    """Refuse a model that float32 positions, which pmjax stores, would damage.

    Coordinates already exact in float32 lose nothing. Otherwise the float32
    spacing at the largest coordinate must stay below ``PRECISION_LIMIT`` of the
    bounding-box diagonal: a small model far from the origin (a survey offset)
    would otherwise collapse onto a few points.

    Raises:
        MeshError: naming ``source``, the offset, the size and the remedy.
    """
    v = np.asarray(vertices, np.float64)
    v = v[np.all(np.isfinite(v), axis=1)]
    if len(v) == 0 or np.array_equal(v.astype(np.float32).astype(np.float64), v):
        return
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    far = float(np.abs(v).max())
    spacing = float(np.spacing(np.float32(far)))
    if spacing > PRECISION_LIMIT * diag:
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        raise MeshError(
            f"{source}: coordinates reach {far:.6g} but the model is only {diag:.6g} across: pmjax stores float32 "
            f"positions, spaced {spacing:.3g} there ({spacing / diag:.1e} of the model), which would merge its "
            f"vertices. Translate the model near the origin first (its bounding-box centre is "
            f"{np.array2string(centre, precision=6)})"
        )


def is_soup(faces: np.ndarray, n_vertices: int) -> bool:
    """Whether no vertex is shared by two faces (and there are two faces or more)."""
    return len(faces) > 1 and int(np.bincount(faces.ravel(), minlength=n_vertices).max()) <= 1


def clean_mesh(
    vertices, faces, *, source: str = "<array>", weld_soup: bool | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, CleanReport]:
    """Validate and clean a triangle mesh.

    Args:
        vertices: ``(V, 3)`` coordinates, any real dtype.
        faces: ``(F, 3)`` integer vertex indices.
        source: name used in error messages (usually the file path).
        weld_soup: weld vertices with equal float32 coordinates first
            (:func:`weld`); ``None`` welds a triangle soup only (no vertex
            shared by two faces, as STL files store meshes).

    Returns:
        ``(vertices float64[V', 3], faces int32[F', 3], kept int64[V'], report)``
        where ``kept[i]`` is the input index of output vertex ``i`` (for a
        welded mesh, the first input vertex of its group).

    Raises:
        MeshError: wrong shapes or dtypes, or no valid face left.
    """
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"{source}: vertices must have shape (V, 3), got {v.shape}")
    if f.size == 0:
        raise MeshError(f"{source}: mesh has no faces")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(
            f"{source}: faces must be triangles with shape (F, 3), got {f.shape}"
        )
    if not np.issubdtype(v.dtype, np.number) or np.iscomplexobj(v):
        raise MeshError(f"{source}: vertex coordinates must be real numbers, got {v.dtype}")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{source}: face indices must be integers, got {f.dtype}")
    v = v.astype(np.float64)
    f = f.astype(np.int64)
    nv = len(v)

    # Faces pointing outside the vertex array cannot be repaired: drop them.
    in_range = np.all((f >= 0) & (f < nv), axis=1)
    out_of_range = int((~in_range).sum())
    f = f[in_range]

    # A triangle soup has one vertex per corner: weld it, or every face would
    # be its own part. Welded ids stand for their group's first input vertex.
    original_ids = np.arange(nv)
    welded = 0
    if weld_soup or (weld_soup is None and is_soup(f, nv)):
        v, f, original_ids = weld(v, f)
        welded, nv = nv - len(v), len(v)

    # Non-finite coordinates poison every quadric they touch: drop the vertex
    # and the faces that use it.
    finite = np.all(np.isfinite(v), axis=1)
    nonfinite = int((~finite).sum())
    on_bad = ~np.all(finite[f], axis=1)
    f = f[~on_bad]

    # pmjax stores float32 positions: a coordinate a face uses past float32's
    # range cannot be kept; refused (naming the vertex) before any arithmetic
    # on it.
    # (The faces left use finite vertices only.)
    used = np.zeros(nv, bool)
    used[f.ravel()] = True
    past = np.flatnonzero(used & rows_outside_float32(v))
    if len(past):
        i = int(past[0])
        raise MeshError(f"{source}: vertex {int(original_ids[i])} is at {v[i].tolist()}, beyond float32's largest "
                        f"value ({FLOAT32_MAX:.4g}), in which pmjax stores positions: scale the model down first")

    # Degenerate faces: repeated corners or (numerically) zero area.
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    # The area threshold is relative to the surface's own size: the faces'
    # corners, not stray points no face uses (scans often hold some).
    diag = np.linalg.norm(np.ptp(v[used], axis=0)) if len(f) else 0.0
    zero_area = np.linalg.norm(cross, axis=1) <= (1e-14 * diag * diag)
    degenerate = repeated | zero_area
    f = f[~degenerate]

    # Duplicate faces: the same corner set, whatever the order or winding.
    if len(f):
        key = np.sort(f, axis=1)
        _, first = np.unique(key, axis=0, return_index=True)
        first.sort()
        duplicates = len(f) - len(first)
        f = f[first]
    else:
        duplicates = 0

    if len(f) == 0:
        raise MeshError(
            f"{source}: no valid face left after cleaning "
            f"({out_of_range} out of range, {nonfinite} non-finite vertices, "
            f"{int(degenerate.sum())} degenerate)"
        )

    # Unreferenced vertices carry no surface: compact them away.
    used = np.zeros(nv, bool)
    used[f.ravel()] = True
    kept = np.flatnonzero(used)
    remap = np.full(nv, -1, np.int64)
    remap[kept] = np.arange(len(kept))
    report = CleanReport(
        nonfinite_vertices=nonfinite,
        out_of_range_faces=out_of_range,
        faces_on_nonfinite_vertices=int(on_bad.sum()),
        degenerate_faces=int(degenerate.sum()),
        duplicate_faces=int(duplicates),
        # Non-finite vertices lose all their faces, so they are never kept.
        unreferenced_vertices=int(nv - len(kept) - nonfinite),
        welded_vertices=welded,
    )
    # Judged on what is kept: cleaning may leave a smaller model.
    check_float32_precision(v[kept], source=source)
    return v[kept], remap[f].astype(np.int32), original_ids[kept], report


def load_clean_mesh(path):
    """:func:`read_mesh` followed by :func:`clean_mesh` (see both)."""
    v, f = read_mesh(path)
    return clean_mesh(v, f, source=shown_name(path))


def default_model_path() -> str:
    """Path of the model shipped in the package (Keenan Crane's Spot, public domain)."""
    return os.path.join(os.path.dirname(__file__), "data", "spot.ply")
