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


def refinement_attributes(vertices, normals, faces, v1, v2, batch_offsets):
    """Sphere radius, cone half-angle and deviations for every pcol.

    Args:
        vertices: ``float64[V0 + P, 3]`` all positions (model units).
        normals: ``float64[V0 + P, 3]`` unit normals.
        faces: ``int[F, 3]`` original faces.
        v1, v2: ``int[P]`` pcol endpoints.
        batch_offsets: ``int[B + 1]``.

    Returns:
        dict of ``float64[P]`` arrays ``radius`` (model units), ``alpha``
        (radians), ``delta``, ``mu`` (model units).
    """
    P = len(v1)
    V0 = len(vertices) - P
    radius = np.zeros(V0 + P)  # per vertex; originals stay 0
    alpha = np.zeros(V0 + P)
    alpha[:V0] = original_cone_angles(vertices[:V0], normals[:V0], faces)
    delta = np.zeros(V0 + P)
    mu = np.zeros(V0 + P)
    parent = np.full(V0 + P, -1, np.int64)
    parent[v1] = V0 + np.arange(P)
    parent[v2] = V0 + np.arange(P)
    # Topmost vertex reached so far from each original vertex (its leaf chain).
    top = np.arange(V0)
    for b in range(len(batch_offsets) - 1):
        lo, hi = V0 + batch_offsets[b], V0 + batch_offsets[b + 1]
        if lo == hi:
            continue
        ids = np.arange(lo, hi)
        x, n = vertices[ids], normals[ids]
        c1, c2 = v1[ids - V0], v2[ids - V0]
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
        up = parent[top]
        moving = np.flatnonzero((up >= lo) & (up < hi))
        top[moving] = up[moving]
        owner = top[moving]
        height = np.abs(np.einsum("ij,ij->i", normals[owner], vertices[moving] - vertices[owner]))
        d = np.zeros(hi - lo)
        np.maximum.at(d, owner - lo, height)
        delta[ids] = np.maximum(d, np.maximum(delta[c1], delta[c2]))
        spread = np.sin(np.minimum(alpha[ids], np.pi / 2))
        mu[ids] = np.maximum(d * spread, np.maximum(mu[c1], mu[c2]))
    return {k: a[V0:] for k, a in dict(radius=radius, alpha=alpha, delta=delta, mu=mu).items()}
