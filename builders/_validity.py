"""Which collapses keep the surface sane: no flips, no degenerate faces, and
(for edges, unless topology change is allowed) the link condition."""

from __future__ import annotations

import numpy as np

from ._rows import any3, cross, dot
from ._topology import contains_edge, key_ends


def collapse_is_valid(
    pos: np.ndarray,
    faces: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    x: np.ndarray,
    pair: np.ndarray,
    face: np.ndarray,
    *,
    min_area2: float,
    link_test: np.ndarray,
    boundary_vertex: np.ndarray,
) -> np.ndarray:
    """Validity of moving ``a[i]`` and ``b[i]`` to ``x[i]``.

    Args:
        pos: ``(N, 3)`` positions; faces: ``(F, 3)`` current faces.
        a, b, x: candidate pairs and their placements ``(C, 3)``.
        pair, face: the domain incidence, each domain face once per pair.
        min_area2: squared doubled area under which a face is degenerate.
        link_test: ``(C,)`` whether to apply the link condition (edges whose
            topology must be kept).
        boundary_vertex: ``(N,)`` whether a vertex lies on a border.

    Returns:
        ``bool[C]``.
    """
    tri = faces[face]
    has_a = tri == a[pair, None]
    has_b = tri == b[pair, None]
    # Faces holding both endpoints vanish with the collapse: nothing to check.
    on_edge = any3(has_a) & any3(has_b)
    # Every other domain face has exactly one moving corner. Rotate it to the
    # front (a cyclic shift keeps the orientation) and compare the face's
    # doubled-area normal before and after the corner moves to x.
    check = ~on_edge
    t, moving, at = tri[check], (has_a | has_b)[check], pair[check]
    m0, m1 = moving[:, 0], moving[:, 1]
    t0, t1, t2 = t[:, 0], t[:, 1], t[:, 2]
    q0 = pos[np.where(m0, t0, np.where(m1, t1, t2))]
    q1 = pos[np.where(m0, t1, np.where(m1, t2, t0))]
    q2 = pos[np.where(m0, t2, np.where(m1, t0, t1))]
    moved = x[at]
    old_cross = cross(q1 - q0, q2 - q0)
    new_cross = cross(q1 - moved, q2 - moved)
    # A flip: the normal turns by more than 90 degrees.
    flips = dot(new_cross, old_cross) <= 0.0
    degenerate = dot(new_cross, new_cross) <= min_area2
    ok = np.bincount(at, flips | degenerate, minlength=len(a)) == 0
    if link_test.any():
        # Link condition: the common neighbours of a and b are exactly the
        # apexes of the faces on edge ab; an interior edge between two border
        # vertices would pinch the surface.
        apexes = np.bincount(pair, on_edge, minlength=len(a))
        common = _common_neighbours(tri, has_a, has_b, pair, len(a))
        pinch = (apexes >= 2) & boundary_vertex[a] & boundary_vertex[b]
        ok &= ~link_test | ((common == apexes) & ~pinch)
    return ok


def _common_neighbours(tri, has_a, has_b, pair, n_pairs) -> np.ndarray:
    """Per pair, the vertices sharing a face with both endpoints."""
    other = ~(has_a | has_b)
    span = np.int64(tri.max()) + 1 if len(tri) else 1
    key = pair[:, None].astype(np.int64) * span + tri
    side_a = _distinct(key[other & any3(has_a)[:, None]])
    side_b = _distinct(key[other & any3(has_b)[:, None]])
    # A key in both distinct lists appears exactly twice in their union.
    both = np.sort(np.concatenate([side_a, side_b]))
    twice = both[1:][both[1:] == both[:-1]]
    return np.bincount(twice // span, minlength=n_pairs)


def _distinct(keys: np.ndarray) -> np.ndarray:
    keys = np.sort(keys)
    return keys[np.r_[True, keys[1:] != keys[:-1]]] if len(keys) else keys


class KnownInvalid:
    """Pairs found invalid whose domain has not changed since.

    A collapse's validity depends only on its domain faces, their vertices'
    positions, the placement and the endpoints' border flags. Pair keys name
    vertex ids, and an id's position and quadric never change; under one
    metric the placement depends on those and on the faces around the
    endpoints alone, so a verdict holds until a collapse touches a face
    around an endpoint. Another metric places the pair elsewhere: the builder
    starts a fresh set where its metric schedule moves on. Without the set,
    late batches re-check the same stuck candidates batch after batch.
    Keys are :func:`edge_keys`.
    """

    def __init__(self):
        self.keys = np.zeros(0, np.int64)  # sorted

    def of(self, keys: np.ndarray) -> np.ndarray:
        """``bool`` mask: which of ``keys`` are known invalid."""
        return contains_edge(self.keys, keys)

    def add(self, keys: np.ndarray) -> None:
        if len(keys):
            self.keys = np.union1d(self.keys, keys)

    def forget_around(self, faces: np.ndarray, collapsed: np.ndarray, n_vertices: int) -> None:
        """Drop the verdicts of pairs with an endpoint on a face (of ``faces``,
        before the batch) that holds a ``collapsed`` vertex."""
        if len(self.keys) == 0:
            return
        hit = np.zeros(n_vertices, bool)
        hit[collapsed] = True
        moved = np.zeros(n_vertices, bool)
        moved[faces[any3(hit[faces])].ravel()] = True
        lo, hi = key_ends(self.keys)
        self.keys = self.keys[~(moved[lo] | moved[hi])]
