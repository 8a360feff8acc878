"""Shading normals of a hierarchy, batch by batch beside the build.

:func:`pmjax._normals.fitted_normals` of the finished hierarchy walks every
living face once per batch to find the faces around each batch's new
vertices. The builder has those faces at hand after each batch (the faces
of the current mesh with a new corner, in mesh order), so the same sums are
made here from them alone: the same additions in the same order, so the same
bits (tests/test_build_memory.py compares every row with
``fitted_normals``).
"""

from __future__ import annotations

import numpy as np

from pmjax._normals import SHARPEN, _unit

from . import _quadrics as quadrics


def area_normal_sums(vertices: np.ndarray, faces: np.ndarray, chunk: int | None = None, out=None) -> np.ndarray:
    """``pmjax._normals._area_normal_sums``: per vertex the sum of its faces'
    cross products (twice the area times the unit normal), the same bits,
    with the faces' cross products made ``chunk`` faces at a time (``None``:
    ``builders._quadrics.CHUNK_FACES``). Corner 0 of every face is added
    first, then corner 1, then corner 2, as there; the cross products are
    made once per corner, so the temporaries stay a chunk's.

    Args:
        vertices: ``float64[V, 3]``; faces: ``int[F, 3]`` ids below ``V``.
        out: zeroed ``float64[V, 3]`` to fill (``None``: a new one).

    Returns:
        ``float64[V, 3]`` (``out`` where given).
    """
    total = np.zeros_like(vertices) if out is None else out
    chunk = max(chunk or quadrics.CHUNK_FACES, 1)
    for k in range(3):
        for lo in range(0, len(faces), chunk):
            part = np.asarray(faces[lo:lo + chunk], np.int64)
            p0 = vertices[part[:, 0]]
            cross = np.cross(vertices[part[:, 1]] - p0, vertices[part[:, 2]] - p0)
            np.add.at(total, part[:, k], cross)
    return total


class ShadingNormals:
    """:func:`pmjax._normals.fitted_normals`, filled in batch by batch.

    Args:
        vertices: ``float64[V0, 3]`` original positions, model units; they
            are rounded to float32 first, as the hierarchy stores them.
        faces: ``int[F, 3]`` original faces.
        n_ids: bound on the vertex ids the build may make.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, n_ids: int):
        V0 = len(vertices)
        stored = vertices.astype(np.float32).astype(np.float64)
        # Per vertex id: the area-weighted normal sum of the original faces
        # below it, its unit vector, and the fitted normal.
        self.total = np.zeros((n_ids, 3))
        area_normal_sums(stored, faces, out=self.total[:V0])
        stored = None
        self.base = np.zeros((n_ids, 3))
        self.base[:V0] = _unit(self.total[:V0])
        self.out = np.zeros((n_ids, 3), np.float32)
        self.out[:V0] = self.base[:V0]

    def add_batch(self, lo: int, c1: np.ndarray, c2: np.ndarray, ring: np.ndarray) -> None:
        """Normals of vertex ids ``lo .. lo+len(c1)-1``, made from ``c1[i]``
        and ``c2[i]``; ``ring`` are the faces after the batch with a corner
        among the new vertices, in the order of the current mesh."""
        hi = lo + len(c1)
        if lo == hi:
            return
        total, base = self.total, self.base
        # A parent's sum: zero plus its children's, the smaller id first
        # (fitted_normals adds them in that order onto a zero row).
        first, second = np.minimum(c1, c2), np.maximum(c1, c2)
        t = np.zeros((hi - lo, 3))
        t += total[first]
        t += total[second]
        total[lo:hi] = t
        base[lo:hi] = _unit(t)
        # The neighbours' sums of every new corner: corner 0 of every face,
        # then corner 1, then corner 2, faces in mesh order (fitted_normals'
        # order). Each column is its own sum, so they are added one at a
        # time (small temporaries beside the build).
        k = hi - lo
        ring_sum, count = np.zeros((3, k)), np.zeros(k, np.int64)
        for c in range(3):
            new = np.flatnonzero(ring[:, c] >= lo)
            slot = ring[new, c] - lo
            one, other = ring[new, (c + 1) % 3], ring[new, (c + 2) % 3]
            for j in range(3):
                np.add.at(ring_sum[j], slot, base[one, j] + base[other, j])
            count += np.bincount(slot, minlength=k)
        ring_sum = ring_sum.T
        seen = 2.0 * count  # a sum of 2.0 per corner, exact
        fitted = base[lo:hi].copy()
        has = seen > 0
        fitted[has] = (1.0 - SHARPEN) * fitted[has] + SHARPEN * ring_sum[has] / seen[has, None]
        self.out[lo:hi] = _unit(fitted)

    def result(self, n_vertices: int) -> np.ndarray:
        """``float32[n_vertices, 3]``: the shading normals of ids below ``n_vertices``."""
        return self.out[:n_vertices].copy()
