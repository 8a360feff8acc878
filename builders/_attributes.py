"""Refinement attributes of every pcol, monotone up the hierarchy (DESIGN §2).

All four are computed batch by batch (children always come from earlier
batches), each batch one vectorized step:

- ``radius``: sphere at the pcol vertex containing both children's spheres,
  ``max_c |x_p − x_c| + r_c`` (originals have ``r = 0``), so it encloses every
  original vertex below and contains its children's spheres.
- ``alpha``: cone around the pcol normal containing both children's cones,
  ``min(π, max_c angle(n_p, n_c) + alpha_c)``; an original vertex's cone
  covers the normals of its faces.
- ``delta`` (along the normal) and ``mu`` (uniform), following the screen-space
  test of DESIGN §3 (Hoppe 1997's notation): ``delta`` bounds the distance of
  every original vertex below from the tangent plane at the pcol vertex; ``mu``
  is the part of that residual that can point off the normal, ``delta ·
  sin(min(alpha, π/2))``. Both are then made monotone with a max over children.
"""

from __future__ import annotations

import numpy as np

from ._quadrics import face_cross
from ._threads import split_rows


def _angle(n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0))


def original_cone_angles(vertices, normals, faces) -> np.ndarray:
    """Half-angle of the cone at each original vertex covering its face normals."""
    fn = face_cross(vertices, faces)
    fn /= np.maximum(np.linalg.norm(fn, axis=1), 1e-300)[:, None]
    corner = faces.ravel()
    ang = split_rows(lambda c, f: _angle(normals[c], fn[f]), corner, np.repeat(np.arange(len(faces)), 3))
    out = np.zeros(len(vertices))
    np.maximum.at(out, corner, ang)
    return out


class HierarchyAttributes:
    """Refinement attributes filled in batch by batch, as the builder makes
    the batches (so the work can run beside it).

    Args:
        vertices, normals: ``float64[N, 3]`` buffers of all vertex ids the
            build may make (model units; unit normals). A batch's rows must be
            written before :meth:`add_batch` is called for it; rows are only read.
        faces: ``int[F, 3]`` original faces.
        n_original: ``V0``, the number of original vertices.
    """

    def __init__(self, vertices, normals, faces, n_original: int):
        n, V0 = len(vertices), n_original
        self.vertices, self.normals, self.V0 = vertices, normals, V0
        self.radius = np.zeros(n)  # per vertex; originals stay 0
        self.alpha = np.zeros(n)
        self.alpha[:V0] = original_cone_angles(vertices[:V0], normals[:V0], faces)
        self.delta = np.zeros(n)
        self.mu = np.zeros(n)
        self.parent = np.full(n, -1, np.int64)
        # Topmost vertex reached so far from each original vertex (its leaf chain).
        self.top = np.arange(V0)

    def add_batch(self, lo: int, c1: np.ndarray, c2: np.ndarray) -> None:
        """Attributes of vertex ids ``lo .. lo+len(c1)-1``, made from ``c1[i]``
        and ``c2[i]`` (children always come from earlier batches)."""
        hi = lo + len(c1)
        if lo == hi:
            return
        vertices, normals = self.vertices, self.normals
        radius, alpha, delta, mu = self.radius, self.alpha, self.delta, self.mu
        ids = np.arange(lo, hi)
        self.parent[c1] = ids
        self.parent[c2] = ids
        x, n = vertices[ids], normals[ids]
        # Spheres and cones that contain the children's.
        radius[ids] = np.maximum(
            np.linalg.norm(x - vertices[c1], axis=1) + radius[c1],
            np.linalg.norm(x - vertices[c2], axis=1) + radius[c2],
        )
        alpha[ids] = np.minimum(
            np.pi,
            np.maximum(_angle(n, normals[c1]) + alpha[c1], _angle(n, normals[c2]) + alpha[c2]),
        )
        # Leaves that climb into this batch: their distance from the tangent plane.
        up = self.parent[self.top]
        moving = np.flatnonzero(up >= lo)
        self.top[moving] = up[moving]
        owner = self.top[moving]
        height = np.abs(np.einsum("ij,ij->i", normals[owner], vertices[moving] - vertices[owner]))
        d = np.zeros(hi - lo)
        np.maximum.at(d, owner - lo, height)
        delta[ids] = np.maximum(d, np.maximum(delta[c1], delta[c2]))
        spread = np.sin(np.minimum(alpha[ids], np.pi / 2))
        mu[ids] = np.maximum(d * spread, np.maximum(mu[c1], mu[c2]))

    def result(self, n_pcols: int) -> dict:
        """``float64[P]`` arrays ``radius``, ``alpha``, ``delta``, ``mu`` of the pcols."""
        ids = slice(self.V0, self.V0 + n_pcols)
        return dict(radius=self.radius[ids], alpha=self.alpha[ids], delta=self.delta[ids], mu=self.mu[ids])

