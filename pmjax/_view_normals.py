"""Shading normals fitted to the original surface in the mesh one view draws."""

from __future__ import annotations

import numpy as np

from ._normals import _corner_sums, _face_cross, _fit_batch, _hierarchy_arrays, _Samples


class ViewNormals:
    """Shading normals of a refinement's mesh, its created vertices fitted
    together to the original surface in that mesh.

    :func:`pmjax.fitted_normals` fits each created vertex once, in the mesh
    just after its batch, with the other corners fixed; a view's refinement
    draws vertices of many batches side by side, so a created vertex's fan
    there is not the one it was fitted on. Here every created vertex of the
    drawn mesh is an unknown of one weighted least-squares fit over that
    mesh (the rule of :func:`pmjax.fitted_normals`: samples are the original
    vertices standing under a created vertex of the mesh, on the face of its
    fan their projection falls into most deeply, each weighted by its area,
    a third of its faces', with target its vertex normal), solved by
    :data:`pmjax._normals.FIT_SWEEPS` Jacobi sweeps from the stored shading
    normals. With an eye position a sample's weight is the area seen from
    there instead: its area times its normal's cosine toward the eye (zero
    when facing away) over its squared distance. Original vertices keep
    their stored normals, so the original mesh is drawn as with the stored
    ones; refinements are not changed, only their normals.

    Args:
        pm: a :class:`pmjax.PMData` or :class:`pmjax.ProgressiveMesh`.
        normals: ``[V0 + P, 3]`` the stored shading normals (the fit's start
            and the original vertices' normals, also the samples' targets),
            e.g. ``pmjax.fitted_normals(pm)``.
    """

    def __init__(self, pm, normals):
        V0, vertices, faces, parent, _ = _hierarchy_arrays(pm)
        normals = np.asarray(normals)
        if normals.shape != (len(vertices), 3):
            raise ValueError(f"ViewNormals: normals must be [{len(vertices)}, 3], got {list(normals.shape)}")
        self._V0, self._parent = V0, parent
        self._positions = np.ascontiguousarray(vertices.T)  # [3, V] by axis
        self._normals = np.asarray(normals, np.float32)
        cross = _face_cross(self._positions, faces)
        area = _corner_sums(faces, np.linalg.norm(cross, axis=0)[None] / 6.0, len(vertices))[0]
        self._samples = _Samples(self._positions[:, :V0], np.ascontiguousarray(self._normals[:V0].T, np.float64),
                                 area[:V0])

    def __call__(self, vertex_ids, faces, eye=None) -> np.ndarray:
        """The shading normals of one drawn mesh.

        Args:
            vertex_ids: ``[N]`` the hierarchy ids of the mesh's vertices (the
                third output of :meth:`pmjax.Refinement.mesh`).
            faces: ``[F, 3]`` the mesh's faces, indices into ``vertex_ids``.
            eye: optional ``[3]`` the camera's position (world units): the
                samples are then weighted by the area seen from there.

        Returns:
            ``float32[N, 3]`` unit normals, row ``i`` for ``vertex_ids[i]``.
        """
        V0, V = self._V0, self._positions.shape[1]
        ids = np.asarray(vertex_ids, np.int64).reshape(-1)
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        if len(ids) and not (0 <= ids.min() and ids.max() < V):
            raise ValueError(f"ViewNormals: vertex ids must be in [0, {V}), got {ids.min()}..{ids.max()}")
        if len(faces) and not (0 <= faces.min() and faces.max() < len(ids)):
            raise ValueError(f"ViewNormals: faces must index the {len(ids)} vertices")
        # Slots: the mesh's original vertices first, then its created ones
        # (the unknowns, slots lo:N), each group in the given order.
        order = np.argsort(ids >= V0, kind="stable")
        slot_of = np.empty(len(ids), np.int64)
        slot_of[order] = np.arange(len(ids))
        lo = int(np.count_nonzero(ids < V0))
        normals = np.ascontiguousarray(self._normals[ids[order]].T, np.float64)  # [3, N]
        if lo == len(ids) or not len(faces):
            return np.ascontiguousarray(normals.T[slot_of], np.float32)
        # Each original vertex's ancestor in the mesh: up its parents to the
        # first drawn vertex (-1 where none is drawn).
        slot = np.full(V, -1, np.int64)
        slot[ids[order]] = np.arange(len(ids))
        at = np.arange(V0)
        climbing = np.flatnonzero(slot[at] < 0)
        while len(climbing):
            up = self._parent[at[climbing]]
            at[climbing] = np.where(up >= 0, V0 + up, -1)
            climbing = climbing[(up >= 0) & (slot[np.maximum(at[climbing], 0)] < 0)]
        ancestor = np.where(at >= 0, slot[np.maximum(at, 0)], -1)
        samples = self._samples
        if eye is not None:
            # The area seen from the eye: projected toward it, over the
            # squared distance (facing away: not seen).
            to_eye = np.asarray(eye, np.float64).reshape(3, 1) - samples.positions
            distance = np.linalg.norm(to_eye, axis=0)
            distance = np.where(distance > 0, distance, 1.0)
            facing = np.maximum((samples.normals * to_eye).sum(axis=0) / distance, 0.0)
            samples = samples._replace(weights=samples.weights * facing / distance**2)
        coordinates = np.ascontiguousarray(self._positions[:, ids[order]])
        corners = np.ascontiguousarray(slot_of[faces].T)
        normals[:, lo:] = _fit_batch(coordinates, corners, ancestor, samples, normals, lo, len(ids))
        return np.ascontiguousarray(normals.T[slot_of], np.float32)
