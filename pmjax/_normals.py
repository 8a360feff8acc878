"""Normals of the hierarchy: every vertex's normal from the original surface it stands for."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:  # the builder imports this module without JAX
    from ._model import ProgressiveMesh


def hierarchy_normals(pm: ProgressiveMesh) -> np.ndarray:
    """Unit normal of every vertex, original and created: the area-weighted
    normal of the original faces around the original vertices it replaces.

    Shading a coarse vertex with the normal of the fine surface it stands for
    keeps a refined mesh's shading close to the original's (appearance
    preservation), and the normals, like positions, blend along ancestor
    chains for geomorphs (:func:`pmjax.geomorph_mesh`).

    Returns:
        ``float32[V0 + P, 3]`` (zero for a vertex with no faces around it).
    """
    V0, vertices, faces, parent, offsets = _hierarchy_arrays(pm)
    total = _area_normal_sums(vertices, faces)
    # Up the batches: a created vertex sums its two children (children are
    # finished before their parent's batch).
    for kids in _consumed_by_batch(parent, offsets):
        np.add.at(total, V0 + parent[kids], total[kids])
    return _unit(total).astype(np.float32)


# Jacobi sweeps of a batch's least-squares fit: created vertices of one batch
# rarely share a face (their collapses are independent), so the first sweep
# nearly solves it and the second settles the few shared faces.
FIT_SWEEPS = 2


def _hierarchy_arrays(pm):
    """``(V0, vertices f64, faces i64, parent, batch_offsets)`` of a
    :class:`pmjax.PMData` or a :class:`pmjax.ProgressiveMesh` (``parent[x]``:
    the pcol consuming vertex ``x``, -1 if none)."""
    V0 = int(pm.n_original_vertices)
    vertices = np.asarray(pm.vertices, np.float64)
    faces = np.asarray(pm.faces, np.int64)
    offsets = np.asarray(pm.batch_offsets, np.int64)
    if hasattr(pm, "v1"):
        parent = np.full(len(vertices), -1, np.int64)
        parent[np.asarray(pm.v1)] = np.arange(len(pm.v1))
        parent[np.asarray(pm.v2)] = np.arange(len(pm.v2))
    else:
        parent = np.asarray(pm.parent, np.int64)
    return V0, vertices, faces, parent, offsets


def _area_normal_sums(vertices, faces) -> np.ndarray:
    """``[V, 3]`` per vertex the sum of its faces' cross products (2·area·normal)."""
    total = np.zeros_like(vertices)
    if len(faces):
        cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
        for k in range(3):
            np.add.at(total, faces[:, k], cross)
    return total


def _consumed_by_batch(parent, offsets) -> list:
    """Per batch, the vertices its pcols consume (``parent`` in the batch)."""
    order = np.argsort(parent, kind="stable")
    consumed = order[parent[order] >= 0]
    starts = np.searchsorted(parent[consumed], offsets)
    return [consumed[starts[b]:starts[b + 1]] for b in range(len(offsets) - 1)]


def _unit(n: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def fitted_normals(pm) -> np.ndarray:
    """Shading normal of every vertex, fitted to the original surface by least squares.

    Rule: an original vertex keeps its area-weighted vertex normal (what the
    original mesh is drawn with). The vertices created by a batch get, in
    the mesh just after that batch, the normals whose interpolation across
    the faces best matches the original surface's normals: samples are the
    original vertices ``p`` whose ancestor in that mesh is a created vertex
    ``u``, each weighted by its area (a third of its faces'), with target its
    vertex normal; ``p`` lies on the face of ``u``'s fan that its projection
    falls into most deeply (largest smallest barycentric coordinate; the
    coordinates then clamped to the face), and the fit minimizes
    ``Σ w_p |Σ_k b_k(p) n_k - n_p|²`` over the created vertices' normals
    ``n_u``, the other corners' normals fixed at their fitted values
    (:data:`FIT_SWEEPS` Jacobi sweeps from the subtree means of
    :func:`hierarchy_normals`; a vertex without samples keeps its subtree
    mean), then normalized. Interpolation across faces averages neighbouring
    vertex normals; the fit undoes that averaging where the original
    surface turns. Computed batch by batch up the hierarchy (children before
    parents), vectorized per batch. The cone axes are not involved.

    Args:
        pm: a :class:`pmjax.PMData` or :class:`pmjax.ProgressiveMesh`.

    Returns:
        ``float32[V0 + P, 3]``, unit (zero for a vertex with no face area
        below it).
    """
    V0, vertices, faces, parent, offsets = _hierarchy_arrays(pm)
    total = _area_normal_sums(vertices, faces)
    samples = _Samples(vertices[:V0], _unit(total[:V0]), _vertex_areas(vertices, faces)[:V0])
    consumed = _consumed_by_batch(parent, offsets)
    # rep[x]: the vertex that stands for x after the current batch (x itself
    # until consumed); corners: the live faces' corners after the batch;
    # ancestor[p]: the vertex standing for original vertex p.
    rep = np.arange(len(vertices))
    corners = faces
    ancestor = np.arange(V0)
    out = _unit(total)
    for b in range(len(offsets) - 1):
        kids = consumed[b]
        np.add.at(total, V0 + parent[kids], total[kids])
        lo, hi = V0 + offsets[b], V0 + offsets[b + 1]
        out[lo:hi] = _unit(total[lo:hi])
        rep[kids] = V0 + parent[kids]
        corners = rep[corners]
        alive = (corners[:, 0] != corners[:, 1]) & (corners[:, 1] != corners[:, 2]) & (corners[:, 0] != corners[:, 2])
        corners = corners[alive]
        ancestor = rep[ancestor]
        out[lo:hi] = _fit_batch(vertices, corners, ancestor, samples, out, lo, hi)
    return out.astype(np.float32)


class _Samples(NamedTuple):
    """The original surface's samples: its vertices."""

    positions: np.ndarray  # [V0, 3]
    normals: np.ndarray  # [V0, 3], unit area-weighted vertex normals
    weights: np.ndarray  # [V0], a third of the area of each vertex's faces


def _vertex_areas(vertices, faces) -> np.ndarray:
    """``[V]`` a third of the area of each vertex's faces."""
    area = np.zeros(len(vertices))
    if len(faces):
        cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
        for k in range(3):
            np.add.at(area, faces[:, k], np.linalg.norm(cross, axis=1) / 6.0)
    return area


# Samples located at a time by _own_faces: its temporaries take about 2 kB per
# sample (some 250 bytes for each face of a fan of about seven), so a block
# stays near 30 MB whatever the mesh.
SAMPLE_BLOCK = 1 << 14


def _own_faces(vertices, corners, fan, first, size, positions):
    """``(corners int[S, 3], barycentric float[S, 3])`` of the face each sample
    lies on: of the ``size[s]`` faces ``fan[first[s]:first[s] + size[s]]`` of
    its fan, the one its projection falls into most deeply (largest smallest
    barycentric coordinate), the coordinates clamped to the face."""
    # Each sample paired with each face of its fan.
    group = np.concatenate([[0], np.cumsum(size)[:-1]])
    pair = np.repeat(np.arange(len(size)), size)
    face = fan[np.repeat(first - group, size) + np.arange(len(pair))]
    # Barycentric coordinates of the projection on each face's plane.
    tri = corners[face]
    a = vertices[tri[:, 0]]
    e0, e1, e2 = vertices[tri[:, 1]] - a, vertices[tri[:, 2]] - a, positions[pair] - a
    d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
    d20, d21 = (e2 * e0).sum(1), (e2 * e1).sum(1)
    det = d00 * d11 - d01 * d01
    det = np.where(det > 0, det, 1.0)  # a degenerate face: coordinates of no use, rarely chosen
    b1, b2 = (d11 * d20 - d01 * d21) / det, (d00 * d21 - d01 * d20) / det
    bary = np.stack([1.0 - b1 - b2, b1, b2], axis=1)
    # The deepest face of each sample (the first of equals).
    depth = bary.min(axis=1)
    deepest = np.flatnonzero(depth >= np.maximum.reduceat(depth, group)[pair])
    own = deepest[np.unique(pair[deepest], return_index=True)[1]]
    bary = np.clip(bary[own], 0.0, None)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), np.finfo(float).tiny)
    return tri[own], bary


def _fit_batch(vertices, corners, ancestor, samples: _Samples, normals, lo: int, hi: int) -> np.ndarray:
    """``[hi - lo, 3]`` fitted unit normals of the vertices ``lo:hi`` created
    by one batch, in the mesh of live faces ``corners`` just after it
    (``normals``: every other vertex's, fixed; the batch's subtree means)."""
    # Step 1: each created vertex's fan, as (vertex slot, face) pairs grouped by slot.
    touched = np.flatnonzero((corners >= lo).any(axis=1))
    slot_of, face_of = [], []
    for k in range(3):
        on = touched[corners[touched, k] >= lo]
        slot_of.append(corners[on, k] - lo)
        face_of.append(on)
    slot_of, face_of = np.concatenate(slot_of), np.concatenate(face_of)
    order = np.argsort(slot_of, kind="stable")
    fan = face_of[order]
    fan_size = np.bincount(slot_of, minlength=hi - lo)
    fan_start = np.concatenate([[0], np.cumsum(fan_size)])
    start = normals[lo:hi]
    # Step 2: the samples standing under a created vertex with a fan, and the
    # face of that fan each lies on, a block of samples at a time (memory
    # bounded by the block, not the mesh).
    sample = np.flatnonzero(ancestor >= lo)
    sample = sample[fan_size[ancestor[sample] - lo] > 0]
    if not len(sample):
        return start
    parts = [_own_faces(vertices, corners, fan, fan_start[ancestor[block] - lo], fan_size[ancestor[block] - lo],
                        samples.positions[block])
             for block in np.array_split(sample, -(-len(sample) // SAMPLE_BLOCK))]
    tri, bary = np.concatenate([t for t, _ in parts]), np.concatenate([b for _, b in parts])
    # Step 4: Jacobi sweeps of the weighted least squares over the created
    # vertices' normals, the other corners fixed.
    weight, target = samples.weights[sample], samples.normals[sample]
    created = tri >= lo
    slot = np.where(created, tri - lo, 0)
    diagonal = np.zeros(hi - lo)
    for k in range(3):
        on = created[:, k]
        np.add.at(diagonal, slot[on, k], weight[on] * bary[on, k] ** 2)
    fitted = start.copy()
    for _ in range(FIT_SWEEPS):
        values = np.where(created[..., None], fitted[slot], normals[tri])  # [S, 3 corners, 3]
        residual = target - (bary[..., None] * values).sum(axis=1)
        rhs = np.zeros((hi - lo, 3))
        for k in range(3):
            on = created[:, k]
            own = residual[on] + bary[on, k, None] * values[on, k]  # the residual without this corner
            np.add.at(rhs, slot[on, k], (weight[on] * bary[on, k])[:, None] * own)
        solved = diagonal > 0
        fitted = np.where(solved[:, None], rhs / np.where(solved, diagonal, 1.0)[:, None], start)
    return _unit(fitted)
