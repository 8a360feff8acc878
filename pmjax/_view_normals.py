"""Shading normals fitted to the original surface in the mesh one view draws."""

from __future__ import annotations

import threading
import weakref

import numpy as np

from . import _normals
from ._normals import _corner_sums, _face_cross, _fit_batch, _hierarchy_arrays, _native_hierarchy, _Samples


# The per-view fit's Jacobi sweeps and the share of each step taken
# (weighted Jacobi). Unlike a batch's, the drawn mesh's created vertices
# are each other's neighbours, so a plain sweep moves every vertex for
# neighbours that move too and overshoots, by turns (on the dragon's orbit
# odd counts of plain sweeps draw better than even ones, more of them
# worse); taking two thirds of each step damps that.
VIEW_SWEEPS = 3
VIEW_RELAX = 0.67


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
    ``sweeps`` weighted Jacobi sweeps from the stored shading normals, each
    moving a normal the share ``relax`` of the way to its step's solution,
    then normalized. With an eye position a sample's weight is the area seen from
    there instead: its area times its normal's cosine toward the eye (zero
    when facing away) over its squared distance. Original vertices keep
    their stored normals, so the original mesh is drawn as with the stored
    ones; refinements are not changed, only their normals.

    By C loops (``pmjax/_normals_native.c``, on up to two threads) where
    that extension is built: the drawn vertices are a front of the
    hierarchy, so a created vertex's samples are the run of its leaves in
    the hierarchy's leaf order: only the drawn created vertices' leaves are
    located on faces (ordering the samples by original id is one pass over
    a byte per original vertex). Else, or for vertex ids that are not a front (a drawn
    vertex above another, or one listed twice), by NumPy, climbing from
    every original vertex to its drawn ancestor: the same bits either way
    (each sum taken in the order of :func:`pmjax.fitted_normals`).

    Args:
        pm: a :class:`pmjax.PMData` or :class:`pmjax.ProgressiveMesh`.
        normals: ``[V0 + P, 3]`` the stored shading normals (the fit's start
            and the original vertices' normals, also the samples' targets),
            e.g. ``pmjax.fitted_normals(pm)``.
        sweeps: Jacobi sweeps, a whole number >= 1 (default
            :data:`VIEW_SWEEPS`).
        relax: the share of each step taken, in (0, 1] (default
            :data:`VIEW_RELAX`; 1: plain Jacobi, with the batch fit's
            sweeps the batch fit's rule).
    """

    def __init__(self, pm, normals, *, sweeps: int = VIEW_SWEEPS, relax: float = VIEW_RELAX):
        if isinstance(sweeps, bool) or not isinstance(sweeps, (int, np.integer)) or sweeps < 1:
            raise ValueError(f"ViewNormals: sweeps must be a whole number >= 1, got {sweeps!r}")
        if isinstance(relax, bool) or not isinstance(relax, (int, float, np.floating, np.integer)) or not 0 < relax <= 1:
            raise ValueError(f"ViewNormals: relax must be a number in (0, 1], got {relax!r}")
        self._sweeps, self._relax = int(sweeps), float(relax)
        V0, vertices, faces, parent, _ = _hierarchy_arrays(pm)
        normals = np.asarray(normals)
        if normals.shape != (len(vertices), 3):
            raise ValueError(f"ViewNormals: normals must be [{len(vertices)}, 3], got {list(normals.shape)}")
        self._V0, self._parent = V0, parent
        self._positions = np.ascontiguousarray(vertices.T)  # [3, V] by axis
        self._normals = np.ascontiguousarray(normals, np.float32)
        cross = _face_cross(self._positions, faces)
        area = _corner_sums(faces, np.linalg.norm(cross, axis=0)[None] / 6.0, len(vertices))[0]
        self._samples = _Samples(self._positions[:, :V0], np.ascontiguousarray(self._normals[:V0].T, np.float64),
                                 area[:V0])
        self._hierarchy = pm
        self._leaves = None  # the C loops' leaf order, made on their first call
        self._workspace = None  # and their arrays, kept from call to call
        self._lock = threading.Lock()  # one call at a time uses them

    def _leaf_order(self):
        """``(arrays for pmn_view_normals)`` or ``None`` where the C loops
        are not built or do not take the hierarchy (its ids, int32)."""
        if self._leaves is None:
            hierarchy = _native_hierarchy(self._hierarchy)
            if hierarchy is None:
                self._leaves = ()
            else:
                V0, vertices, _, _, kid_lo, kid_hi = hierarchy
                V = len(vertices)
                leaf, first, count = np.empty(max(V0, 1), np.int32), np.empty(V, np.int32), np.empty(V, np.int32)
                if _normals.native.pmn_leaf_order(V0, V, kid_lo.ctypes.data, kid_hi.ctypes.data, leaf.ctypes.data,
                                                  first.ctypes.data, count.ctypes.data):
                    raise MemoryError("ViewNormals: out of memory in the C loops")
                leaf = leaf[:V0]
                # The workspace first: the leaves are kept only with one.
                lib = _normals.native
                workspace = lib.pmn_view_workspace()
                if not workspace:
                    raise MemoryError("ViewNormals: out of memory in the C loops")
                self._workspace = workspace
                weakref.finalize(self, lib.pmn_view_workspace_free, workspace)
                # The samples' arrays in leaf order: positions by axis,
                # targets by vertex, areas.
                self._leaves = (leaf, first, count, np.ascontiguousarray(self._samples.positions[:, leaf]),
                                np.ascontiguousarray(self._samples.normals[:, leaf].T),
                                np.ascontiguousarray(self._samples.weights[leaf]),
                                np.ascontiguousarray(self._positions.T))
        return self._leaves or None

    def _native(self, ids, faces, eye):
        """``float64[N, 3]`` by the C loops, or ``None`` where they are not
        built, do not take the hierarchy or the ids are not a front."""
        if _normals.native is None:
            return None
        ids, faces = np.ascontiguousarray(ids, np.int64), np.ascontiguousarray(faces, np.int64)
        eye = None if eye is None else np.ascontiguousarray(np.asarray(eye, np.float64).reshape(3))
        out = np.empty((len(ids), 3))
        with self._lock:
            if self._leaf_order() is None:
                return None
            leaf, first, count, position, target, area, positions = self._leaves
            rc = _normals.native.pmn_view_normals(
                self._V0, positions.ctypes.data, self._normals.ctypes.data, leaf.ctypes.data, first.ctypes.data,
                count.ctypes.data, position.ctypes.data, target.ctypes.data, area.ctypes.data, len(ids),
                ids.ctypes.data, len(faces), faces.ctypes.data, None if eye is None else eye.ctypes.data, self._sweeps,
                self._relax, _normals.FIT_THREADS, _normals.FIT_MIN_SPLIT, self._workspace, out.ctypes.data)
        if rc == 1:
            raise MemoryError("ViewNormals: out of memory in the C loops")
        return out if rc == 0 else None

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
        if eye is not None:
            eye = np.asarray(eye, np.float64)
            if eye.shape != (3,) or not np.isfinite(eye).all():
                raise ValueError(f"ViewNormals: eye must be 3 finite coordinates, got {eye.tolist()}")
        fitted = self._native(ids, faces, eye)
        if fitted is not None:
            return fitted.astype(np.float32)
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
        normals[:, lo:] = _fit_batch(coordinates, corners, ancestor, samples, normals, lo, len(ids), self._sweeps,
                                     self._relax)
        return np.ascontiguousarray(normals.T[slot_of], np.float32)
