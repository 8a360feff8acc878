"""Refinement attributes of every pcol, monotone up the hierarchy (docs/design.md).

All four are computed batch by batch (children always come from earlier
batches), each batch one vectorized step:

- ``radius``: sphere at the pcol vertex containing both children's spheres,
  ``max_c |x_p − x_c| + r_c`` (originals have ``r = 0``), so it encloses every
  original vertex below and contains its children's spheres.
- ``alpha``: cone around the pcol normal containing both children's cones,
  ``min(π, max_c angle(n_p, n_c) + alpha_c)``; an original vertex's cone
  covers the normals of its faces.
- ``delta`` (along the normal) and ``mu`` (uniform), following the screen-space
  test of docs/design.md (Hoppe 1997's notation): ``delta`` bounds the distance of
  every original vertex below from the tangent plane at the pcol vertex; ``mu``
  is the part of that residual that can point off the normal, ``delta ·
  sin(min(alpha, π/2))``, and at least the distance by which an original vertex
  below is left off the coarse surface (see :func:`uncovered_distance`). Both
  are then made monotone with a max over children.
"""

from __future__ import annotations

import numpy as np

from pmjax._distance import dot_rows, point_triangle_distance

from . import _native as native
from . import _quadrics as quadrics
from ._quadrics import face_cross
from ._threads import split_rows
from ._topology import border_vertices, unique_edges


def _angle(n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0))


def original_cone_angles(vertices, normals, faces, chunk: int | None = None) -> np.ndarray:
    """Half-angle of the cone at each original vertex covering its face normals.

    Faces are taken ``chunk`` at a time (``None``:
    ``builders._quadrics.CHUNK_FACES``; a max is the same in any order), so
    the per-corner temporaries stay bounded at any model size."""
    out = np.zeros(len(vertices))
    for part in quadrics.face_parts(faces, chunk):
        fn = face_cross(vertices, part)
        fn /= np.maximum(np.linalg.norm(fn, axis=1), 1e-300)[:, None]
        corner = part.ravel()
        ang = split_rows(lambda c, f: _angle(normals[c], fn[f]), corner, np.repeat(np.arange(len(part)), 3))
        np.maximum.at(out, corner, ang)
    return out


def uncovered_distance(vertices, normals, leaves, owner, ring, lo: int, hi: int, maybe_border,
                       leaf_on_border) -> np.ndarray:
    """How far each leaf lies off the coarse surface around its owner, sideways.

    A leaf's deviation is measured along its owner's normal (``delta``). That
    misses the coarse surface pulling away from the leaf: a border vertex
    collapsing along a flat border, or a whole part collapsing to a point,
    moves nothing along the normal. So for owners on an open border of the
    coarse mesh, each leaf on the original border is projected with the
    owner's faces on the owner's tangent plane and its distance to those
    triangles is taken (0 when it projects inside one): a receding border
    leaves the original border's vertices farthest out. An owner left without
    faces is a point, so every leaf's whole distance to it counts. Owners
    inside a closed surface give 0: there the neighbours' faces cover what
    the owner's do not.

    Args:
        vertices, normals: ``float64[N, 3]`` of every vertex id (unit normals).
        leaves, owner: ``int[M]`` original vertices and the new vertex each now
            belongs to (``lo <= owner < hi``).
        ring: ``int[R, 3]`` faces after the batch that touch the new vertices.
        lo, hi: the batch's new vertex ids.
        maybe_border: ``bool[hi - lo]``, the new vertices that may lie on an
            open border (a child did before the batch); only these are checked,
            so closed surfaces cost no more than a count of their faces.
        leaf_on_border: ``bool[M]``, leaves on an open border of the original mesh.

    Returns:
        ``float64[M]`` distances, model units.
    """
    if native.available():  # one C pass, the same bits
        return native.uncovered_distance(vertices, normals, leaves, owner, ring, lo, hi, maybe_border,
                                         leaf_on_border)
    out = np.zeros(len(leaves))
    if not len(leaves):
        return out
    k = hi - lo
    corner = ring.ravel()
    mine = np.flatnonzero(corner >= lo)
    faces_of = np.bincount(corner[mine] - lo, minlength=k)
    o = owner - lo
    # An owner left without faces: the leaf's whole distance to the point.
    alone = faces_of[o] == 0
    out[alone] = np.linalg.norm(vertices[leaves[alone]] - vertices[owner[alone]], axis=1)
    check = np.asarray(maybe_border, bool) & (faces_of > 0)
    if not check[o].any():
        return out
    # The checked owners' faces, one row per (owner, face), grouped by owner.
    mine = mine[check[corner[mine] - lo]]
    order = np.argsort(corner[mine], kind="stable")
    mine = mine[order]
    cv, cf, pos_in = corner[mine] - lo, mine // 3, mine % 3
    # On a border: an edge to a neighbour that only one of the owner's faces
    # has. Every face holding an edge at the owner holds the owner, so
    # counting within its faces is exact.
    nxt = ring[cf, (pos_in + 1) % 3].astype(np.int64)
    prv = ring[cf, (pos_in + 2) % 3].astype(np.int64)
    stride = int(len(vertices)) + 1
    key = np.concatenate([cv, cv]).astype(np.int64) * stride + np.concatenate([nxt, prv])
    uniq, count = np.unique(key, return_counts=True)
    border = np.zeros(k, bool)
    border[uniq[count == 1] // stride] = True
    which = np.flatnonzero(border[o] & ~alone & np.asarray(leaf_on_border, bool))
    if not len(which):
        return out
    # Each of those leaves against each face of its owner, all flattened onto
    # the owner's tangent plane: their 3D distance there is the in-plane one.
    start = np.zeros(k + 1, np.int64)
    start[1:] = np.cumsum(np.where(check, faces_of, 0))
    n_pairs = faces_of[o[which]]
    pair_leaf = np.repeat(which, n_pairs)
    step = np.arange(len(pair_leaf)) - np.repeat(np.cumsum(n_pairs) - n_pairs, n_pairs)
    pair_face = cf[np.repeat(start[o[which]], n_pairs) + step]
    n = normals[owner[pair_leaf]]
    origin = vertices[owner[pair_leaf]]

    def flat(points):
        rel = points - origin
        return rel - dot_rows(rel, n)[:, None] * n

    dist = point_triangle_distance(flat(vertices[leaves[pair_leaf]]),
                                   *(flat(vertices[ring[pair_face, j]]) for j in range(3)))
    best = np.full(len(leaves), np.inf)
    np.minimum.at(best, pair_leaf, dist)
    out[which] = best[which]
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
        edges: :func:`builders._topology.unique_edges` of ``faces`` if the
            caller has them (``None``: counted here).
    """

    def __init__(self, vertices, normals, faces, n_original: int, edges=None):
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
        # Original vertices on an open border (an edge of one face).
        ea, eb, count, _ = edges if edges is not None else unique_edges(np.asarray(faces))
        self.on_border = border_vertices(ea, eb, count, V0)

    def add_batch(self, lo: int, c1: np.ndarray, c2: np.ndarray, ring: np.ndarray, maybe_border: np.ndarray) -> None:
        """Attributes of vertex ids ``lo .. lo+len(c1)-1``, made from ``c1[i]``
        and ``c2[i]`` (children always come from earlier batches); ``ring``
        are the faces after the batch that touch the new vertices, and
        ``maybe_border`` flags those with a child on an open border before it."""
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
        # Leaves that climb into this batch: their distance from the tangent
        # plane (one C pass, the same bits, where the C loops are built).
        if native.available():
            moving, owner, d = native.climb_leaves(self.top, self.parent, lo, hi, vertices, normals)
        else:
            up = self.parent[self.top]
            moving = np.flatnonzero(up >= lo)
            self.top[moving] = up[moving]
            owner = self.top[moving]
            # The dot product in the C pass's order, on any NumPy.
            height = np.abs(dot_rows(normals[owner], vertices[moving] - vertices[owner]))
            d = np.zeros(hi - lo)
            np.maximum.at(d, owner - lo, height)
        delta[ids] = np.maximum(d, np.maximum(delta[c1], delta[c2]))
        spread = np.sin(np.minimum(alpha[ids], np.pi / 2))
        # Leaves the coarse surface no longer covers (a receding border, a part
        # that vanished) are off it sideways, which the normal cannot see.
        off = np.zeros(hi - lo)
        u = uncovered_distance(vertices, normals, moving, owner, ring, lo, hi, maybe_border, self.on_border[moving])
        hit = np.flatnonzero(u > 0)
        np.maximum.at(off, owner[hit] - lo, u[hit])
        mu[ids] = np.maximum(np.maximum(d * spread, off), np.maximum(mu[c1], mu[c2]))

    def result(self, n_pcols: int) -> dict:
        """``float64[P]`` arrays ``radius``, ``alpha``, ``delta``, ``mu`` of the pcols."""
        ids = slice(self.V0, self.V0 + n_pcols)
        return dict(radius=self.radius[ids], alpha=self.alpha[ids], delta=self.delta[ids], mu=self.mu[ids])

