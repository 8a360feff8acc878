"""The progressive mesh on the device: an immutable pytree of JAX arrays."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._pmfile import PMData


class PcolAttributes(eqx.Module):
    """What the refinement tests see of each pcol (float32 on the speed path).

    Struct of arrays: coordinates are rows (``[3, P]``), so every test is a
    fused elementwise loop over contiguous memory; the cone's sine and cosine
    are stored so no test needs trigonometry per view.

    Attributes:
        center: ``[3, P]`` the pcol vertex (sphere and cone centre), rows x, y, z.
        axis: ``[3, P]`` unit cone axis.
        radius: ``[P]`` bounding-sphere radius, model units.
        alpha: ``[P]`` cone half-angle, radians (kept for reference: the
            tests read its sine and cosine only, so an update of the
            orientation test's cones goes to ``sin_alpha`` and ``cos_alpha``).
        sin_alpha, cos_alpha: ``[P]`` its sine and cosine.
        delta: ``[P]`` deviation along the normal, model units.
        mu: ``[P]`` uniform deviation, model units.
    """

    center: Float[Array, "3 P"]
    axis: Float[Array, "3 P"]
    radius: Float[Array, " P"]
    alpha: Float[Array, " P"]
    sin_alpha: Float[Array, " P"]
    cos_alpha: Float[Array, " P"]
    delta: Float[Array, " P"]
    mu: Float[Array, " P"]

    @property
    def position(self) -> Float[Array, "P 3"]:
        """``[P, 3]`` sphere centres (a transposed view of ``center``)."""
        return self.center.T

    @property
    def normal(self) -> Float[Array, "P 3"]:
        """``[P, 3]`` cone axes."""
        return self.axis.T

    @staticmethod
    def from_arrays(position, normal, radius, alpha, delta, mu, dtype=np.float32) -> "PcolAttributes":
        """Attributes from per-pcol arrays (``position``/``normal`` ``[P, 3]``)."""
        alpha = np.asarray(alpha, np.float64)
        arr = lambda x: jnp.asarray(np.ascontiguousarray(x, dtype=dtype))
        return PcolAttributes(
            center=arr(np.asarray(position).T),
            axis=arr(np.asarray(normal).T),
            radius=arr(radius),
            alpha=arr(alpha),
            sin_alpha=arr(np.sin(alpha)),
            cos_alpha=arr(np.cos(alpha)),
            delta=arr(delta),
            mu=arr(mu),
        )


class ProgressiveMesh(eqx.Module):
    """A progressive mesh ready for refinement (see ``docs/format.md``).

    Array fields live on the JAX device; the batch offsets are static (the
    folds' windows are planned from them when tracing). It holds the mesh's
    own arrays only: what an engine derives from them (subtree bounds, the front
    engine's layout) is computed from the arrays and cached under their
    contents (:mod:`pmjax.engines`), so an updated mesh (``eqx.tree_at``,
    arithmetic on its arrays) is refined from its new values.

    Attributes:
        vertices: ``[V0 + P, 3]`` float32 positions.
        faces: ``[F, 3]`` int32 original faces.
        child1, child2: ``[P]`` int32, pcol making each endpoint, -1 if original.
        parent: ``[V0 + P]`` int32, pcol consuming each vertex, -1 if none.
        killer: ``[F]`` int32, pcol removing each face, -1 if none.
        kills: ``[P]`` int32, faces each pcol removes (the faces whose
            ``killer`` it is); update it with :meth:`with_kills`, which
            updates its summary below too (a public call refuses a mesh whose
            ``kills``, summary and ``killer`` disagree).
        attributes: :class:`PcolAttributes`.
        batch_offsets: static tuple ``(0, ..., P)``.
        n_original_vertices: static V0.
        max_kills, min_kills, common_kills: static, the most, the fewest and
            the most common number of faces one pcol removes (the batched face
            count is ``common_kills`` per executed pcol plus corrections whose
            bit planes these size).
        uncommon: ``[N]`` int32, the pcols whose kills differ from
            ``common_kills`` (the only ones the correction looks at).
        shading_normals: ``[V0 + P, 3]`` float32 shading normals stored in
            the file (:func:`pmjax.fitted_normals`), or None when the file has
            none; drawing only, the refinement never reads them.
    """

    vertices: Float[Array, "V 3"]
    faces: Int[Array, "F 3"]
    child1: Int[Array, " P"]
    child2: Int[Array, " P"]
    parent: Int[Array, " V"]
    killer: Int[Array, " F"]
    kills: Int[Array, " P"]
    attributes: PcolAttributes
    uncommon: Int[Array, " N"]
    batch_offsets: tuple = eqx.field(static=True)
    n_original_vertices: int = eqx.field(static=True)
    max_kills: int = eqx.field(static=True, default=0)
    min_kills: int = eqx.field(static=True, default=0)
    common_kills: int = eqx.field(static=True, default=0)
    shading_normals: Float[Array, "V 3"] | None = None

    @property
    def n_pcols(self) -> int:
        return self.batch_offsets[-1]

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def total_kills(self) -> Int[Array, ""]:
        """Faces all pcols together remove (``F`` minus the base mesh's faces)."""
        return jnp.sum(self.kills, dtype=jnp.int32)

    @property
    def uncommon_extra_kills(self) -> Int[Array, " N"]:
        """``[N]`` faces each ``uncommon`` pcol kills beyond ``common_kills``
        (may be negative): the correction of every face count."""
        return self.kills[self.uncommon] - self.common_kills

    def with_kills(self, kills) -> "ProgressiveMesh":
        """The same mesh with ``kills`` (``[P]`` faces each pcol removes, host
        values) and the static summary that describes them
        (:func:`kill_summary`): ``eqx.tree_at`` would leave the summary of the
        old counts, which the engines' face counts read."""
        return dataclasses.replace(self, **kill_summary(np.asarray(kills, np.int32)))

    def astype(self, dtype) -> "ProgressiveMesh":
        """The same mesh with positions and pcol attributes in ``dtype``
        (``jnp.float64`` for gradient checks; needs ``jax.enable_x64``)."""
        attrs = jax.tree.map(lambda x: x.astype(dtype), self.attributes)
        return eqx.tree_at(lambda m: (m.vertices, m.attributes), self, (self.vertices.astype(dtype), attrs))

    @staticmethod
    def from_data(pm: PMData) -> "ProgressiveMesh":
        """Device copy of host arrays (:class:`pmjax.PMData`)."""
        V0, P = pm.n_original_vertices, pm.n_pcols
        parent = np.full(V0 + P, -1, np.int32)
        parent[pm.v1] = np.arange(P)
        parent[pm.v2] = np.arange(P)
        child1 = np.where(pm.v1 >= V0, pm.v1 - V0, -1).astype(np.int32)
        child2 = np.where(pm.v2 >= V0, pm.v2 - V0, -1).astype(np.int32)
        return ProgressiveMesh(
            vertices=jnp.asarray(pm.vertices),
            faces=jnp.asarray(pm.faces),
            child1=jnp.asarray(child1),
            child2=jnp.asarray(child2),
            parent=jnp.asarray(parent),
            killer=jnp.asarray(pm.killer),
            attributes=PcolAttributes.from_arrays(pm.vertices[V0:], pm.normals[V0:], pm.radius, pm.alpha, pm.delta,
                                                  pm.mu),
            batch_offsets=tuple(int(o) for o in pm.batch_offsets),
            n_original_vertices=V0,
            **kill_summary(pm.kills.astype(np.int32)),
            shading_normals=None if pm.shading_normals is None else jnp.asarray(pm.shading_normals),
        )


def kill_summary(kills: np.ndarray, common: int | None = None) -> dict:
    """The :class:`ProgressiveMesh` fields that describe ``kills``
    (``common``: the base count, by default the most frequent)."""
    kills = np.asarray(kills)
    if common is None:
        common = int(np.argmax(np.bincount(kills))) if len(kills) else 0
    return dict(
        kills=jnp.asarray(kills, jnp.int32),
        uncommon=jnp.asarray(np.flatnonzero(kills != common).astype(np.int32)),
        max_kills=int(kills.max(initial=0)),
        min_kills=int(kills.min()) if len(kills) else 0,
        common_kills=int(common),
    )
