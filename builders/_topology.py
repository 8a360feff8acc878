"""Vectorized incidence structures of a triangle soup: CSR lists and edge sets."""

from __future__ import annotations

import numpy as np


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


def edge_keys(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Order-free int64 key of vertex pairs (``min * n + max``)."""
    lo, hi = np.minimum(a, b).astype(np.int64), np.maximum(a, b).astype(np.int64)
    return lo * n + hi


def unique_edges(faces: np.ndarray, n: int):
    """Undirected edges of a triangle soup.

    Returns:
        ``(a, b, face_count)`` with ``a < b``; ``face_count`` is how many faces
        use the edge (1 on a boundary, 2 inside a manifold).
    """
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    keys, counts = np.unique(edge_keys(a, b, n), return_counts=True)
    return (keys // n).astype(faces.dtype), (keys % n).astype(faces.dtype), counts


def contains_edge(ea: np.ndarray, eb: np.ndarray, a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Whether each pair ``(a[i], b[i])`` is among the edges ``(ea, eb)``.

    ``(ea, eb)`` must come from :func:`unique_edges` (sorted by key).
    """
    keys = edge_keys(ea, eb, n)
    k = edge_keys(a, b, n)
    i = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    return keys[i] == k
