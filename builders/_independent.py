"""Parallel greedy choice of non-conflicting collapses (docs/design.md).

Two candidates conflict when their domains (faces touching either endpoint)
share a face. A candidate is taken when it is the cheapest among all remaining
candidates touching its domain; taken candidates block their domains, and the
rounds repeat until nothing is left (or a round cap is reached). With fixed priorities this gives the same
set as a sequential greedy over candidates in cost order, but every round is
a handful of array reductions.

No (candidate, face) incidence is materialised: "cheapest candidate touching
face f" is the min over f's corners of "cheapest candidate at that vertex",
and "cheapest over my domain" is the min over my endpoints of the min over
the faces around them. Faces no remaining candidate touches are dropped from
later rounds, so rounds get cheaper as they go.

Validity is checked lazily, only for the round's winners: an invalid winner is
dropped without blocking anything, which again matches the sequential greedy
that skips invalid candidates. Winners of one round are independent, so every
face lies in at most one winner's domain and that domain is found with one
vertex-to-owner gather (:func:`domain_of_independent`).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ._rows import any3, max3, min3

# Candidate ids and scratch values are int32 (fewer bytes per gather and
# scatter in every round); _NONE is above every id.
_NONE = np.iinfo(np.int32).max


def domain_of_independent(
    a: np.ndarray, b: np.ndarray, faces: np.ndarray, face_ids: np.ndarray, owner: np.ndarray
):
    """Domain faces of pairwise independent pairs.

    Args:
        a, b: ``(K,)`` endpoints of independent pairs.
        faces: ``(F, 3)`` faces to search; ``face_ids`` their ids.
        owner: ``int32[n_vertices]`` scratch buffer filled with -1; it is
            left filled with -1 again.

    Returns:
        ``(pair, face)``: for every face touching a pair, the pair number and
        the face id (each face at most once).
    """
    owner[a] = np.arange(len(a), dtype=np.int32)
    owner[b] = np.arange(len(b), dtype=np.int32)
    of_face = max3(owner[faces])
    owner[a] = -1
    owner[b] = -1
    hit = of_face >= 0
    return of_face[hit], face_ids[hit]


def select_independent(
    a: np.ndarray,
    b: np.ndarray,
    faces: np.ndarray,
    n_vertices: int,
    is_valid: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    max_rounds: int = 64,
) -> np.ndarray:
    """Maximal set of valid, pairwise independent candidates, cheapest first.

    Args:
        a, b: ``(C,)`` candidate endpoints, sorted by cost (index = priority);
            every endpoint has a face.
        faces: ``(F, 3)`` current faces.
        n_vertices: bound on vertex ids.
        is_valid: ``is_valid(ids, pair, face)`` gives a ``bool`` mask over
            candidate ids, with their domain incidence; called once per id.
        max_rounds: stop after this many rounds (once something is taken).
            Late rounds take a handful of candidates each; past the cap they
            are left for the next batch instead of paying a round each.

    Returns:
        Chosen candidate ids, ascending (cheapest first).
    """
    remaining = np.arange(len(a), dtype=np.int32)
    face_ids = np.arange(len(faces))
    # Scratch buffers over vertex ids, reset after each use (only the touched
    # entries), so a round costs O(remaining work), not O(vertices).
    at_vertex = np.full(n_vertices, _NONE, np.int32)
    around = np.full(n_vertices, _NONE, np.int32)
    owner = np.full(n_vertices, -1, np.int32)
    mark = np.zeros(n_vertices, bool)
    vertex_blocked = np.zeros(n_vertices, bool)
    chosen = []
    n_chosen = 0
    rounds = 0
    # The cap only counts once something is taken: a batch whose cheapest
    # candidates are all invalid keeps going until it finds a valid one.
    while len(remaining) and (rounds < max_rounds or n_chosen == 0):
        rounds += 1
        ra, rb = a[remaining], b[remaining]
        # Only faces at a remaining endpoint matter from now on.
        mark[ra] = True
        mark[rb] = True
        keep = any3(mark[faces])
        mark[ra] = False
        mark[rb] = False
        faces, face_ids = faces[keep], face_ids[keep]
        corner = faces.ravel()
        # Cheapest remaining candidate at each vertex, then at each face.
        np.minimum.at(at_vertex, ra, remaining)
        np.minimum.at(at_vertex, rb, remaining)
        at_face = min3(at_vertex[faces])
        # Cheapest over the faces around each vertex = over each domain half.
        np.minimum.at(around, corner, np.repeat(at_face, 3))
        winners = remaining[np.minimum(around[ra], around[rb]) == remaining]
        at_vertex[ra] = _NONE
        at_vertex[rb] = _NONE
        around[corner] = _NONE
        pair, face = domain_of_independent(a[winners], b[winners], faces, face_ids, owner)
        taken = winners[is_valid(winners, pair, face)]
        chosen.append(taken)
        n_chosen += len(taken)
        # Faces touched by a taken candidate are used; so is every vertex of them.
        mark[a[taken]] = True
        mark[b[taken]] = True
        used = any3(mark[faces])
        mark[a[taken]] = False
        mark[b[taken]] = False
        vertex_blocked[faces[used].ravel()] = True
        alive = ~(vertex_blocked[ra] | vertex_blocked[rb])
        alive[np.searchsorted(remaining, winners)] = False
        remaining = remaining[alive]
    return np.sort(np.concatenate(chosen)) if chosen else np.zeros(0, np.int32)
