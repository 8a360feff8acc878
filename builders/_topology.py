"""Vectorized incidence structures of a triangle soup: CSR lists and edge sets."""

from __future__ import annotations

import numpy as np

from . import _native as native


def expand_ranges(starts: np.ndarray, counts: np.ndarray):
    """Flatten the ranges ``[starts[i], starts[i] + counts[i])``.

    Returns:
        ``(owner, index)``: for every element of every range, the range number
        ``i`` and the element's position.
    """
    counts = counts.astype(np.int64)
    owner = np.repeat(np.arange(len(counts)), counts)
    first = np.cumsum(counts) - counts
    index = np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(first - starts, counts)
    return owner, index


class VertexFaces:
    """For each vertex, the faces that use it (CSR)."""

    def __init__(self, faces: np.ndarray, n_vertices: int):
        flat = faces.ravel()
        self.order = np.argsort(flat, kind="stable") // 3  # face ids grouped by vertex
        self.degree = np.bincount(flat, minlength=n_vertices)
        self.starts = np.cumsum(self.degree) - self.degree

    def of_pairs(self, a: np.ndarray, b: np.ndarray, faces: np.ndarray | None = None):
        """Faces touching ``a[i]`` or ``b[i]`` (the edge-collapse domain).

        Args:
            a, b: ``(C,)`` pairs.
            faces: if given, the ``(F, 3)`` faces this was built from; faces
                touching both endpoints are then listed once, not twice.

        Returns:
            ``(pair, face)``: pair number and face id, grouped by pair.
        """
        verts = np.stack([a, b], 1).ravel()
        owner, idx = expand_ranges(self.starts[verts], self.degree[verts])
        pair, face = owner // 2, self.order[idx]
        if faces is not None:
            second = (owner % 2 == 1) & np.any(faces[face] == a[pair, None], axis=1)
            pair, face = pair[~second], face[~second]
        return pair, face


def edge_keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Order-free int64 key of vertex pairs: ``min << 32 | max`` (ids below
    2**31). Keys sort like the pairs ``(min, max)``, and, unlike ``min * n +
    max``, split back into ids with a shift and a mask instead of a division."""
    lo, hi = np.minimum(a, b).astype(np.int64), np.maximum(a, b).astype(np.int64)
    return (lo << 32) | hi


def key_ends(keys: np.ndarray):
    """``(min, max)`` vertex ids of :func:`edge_keys` keys."""
    return keys >> 32, keys & 0xFFFFFFFF


def unique_edges(faces: np.ndarray):
    """Undirected edges of a triangle soup.

    Returns:
        ``(a, b, face_count, keys)`` in key order, with ``a < b`` (of the
        faces' integer type); ``face_count`` is how many faces use the edge
        (1 on a boundary, 2 inside a manifold); ``keys`` their :func:`edge_keys`.
    """
    if native.available() and faces.dtype == np.int32:
        return native.unique_edges(faces)
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    keys, counts = np.unique(edge_keys(a, b), return_counts=True)
    lo, hi = key_ends(keys)
    return lo.astype(faces.dtype), hi.astype(faces.dtype), counts, keys


def border_vertices(a: np.ndarray, b: np.ndarray, face_count: np.ndarray, n_vertices: int) -> np.ndarray:
    """``bool[n_vertices]``: the vertices on an open border, that is on an
    edge of one face (``a, b, face_count`` as :func:`unique_edges` gives them)."""
    border = face_count == 1
    out = np.zeros(n_vertices, bool)
    out[a[border]] = True
    out[b[border]] = True
    return out


def contains_edge(edge_keys_sorted: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Whether each key of ``keys`` is among ``edge_keys_sorted`` (ascending,
    as :func:`unique_edges` gives them)."""
    if len(edge_keys_sorted) == 0:
        return np.zeros(len(keys), bool)
    i = np.minimum(np.searchsorted(edge_keys_sorted, keys), len(edge_keys_sorted) - 1)
    return edge_keys_sorted[i] == keys
