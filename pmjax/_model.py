"""The progressive mesh on the device: an immutable pytree of JAX arrays."""

from __future__ import annotations

import os

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._pmfile import PMData, read_pm


class PcolAttributes(eqx.Module):
    """What the refinement tests see of each pcol (float32).

    Attributes:
        position: ``[P, 3]`` the pcol vertex (sphere and cone centre).
        normal: ``[P, 3]`` unit cone axis.
        radius: ``[P]`` bounding-sphere radius, model units.
        alpha: ``[P]`` cone half-angle, radians.
        delta: ``[P]`` deviation along the normal, model units.
        mu: ``[P]`` uniform deviation, model units.
    """

    position: Float[Array, "P 3"]
    normal: Float[Array, "P 3"]
    radius: Float[Array, " P"]
    alpha: Float[Array, " P"]
    delta: Float[Array, " P"]
    mu: Float[Array, " P"]


class ProgressiveMesh(eqx.Module):
    """A progressive mesh ready for refinement (see ``docs/format.md``).

    Array fields live on the JAX device; the batch offsets are static, so each
    batch is a static slice under ``jit``.

    Attributes:
        vertices: ``[V0 + P, 3]`` float32 positions.
        faces: ``[F, 3]`` int32 original faces.
        child1, child2: ``[P]`` int32, pcol making each endpoint, -1 if original.
        parent: ``[V0 + P]`` int32, pcol consuming each vertex, -1 if none.
        killer: ``[F]`` int32, pcol removing each face, -1 if none.
        kills: ``[P]`` int32, faces each pcol removes.
        attributes: :class:`PcolAttributes`.
        batch_offsets: static tuple ``(0, ..., P)``.
        n_original_vertices: static V0.
    """

    vertices: Float[Array, "V 3"]
    faces: Int[Array, "F 3"]
    child1: Int[Array, " P"]
    child2: Int[Array, " P"]
    parent: Int[Array, " V"]
    killer: Int[Array, " F"]
    kills: Int[Array, " P"]
    attributes: PcolAttributes
    batch_offsets: tuple = eqx.field(static=True)
    n_original_vertices: int = eqx.field(static=True)

    @property
    def n_pcols(self) -> int:
        return self.batch_offsets[-1]

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @staticmethod
    def from_data(pm: PMData) -> "ProgressiveMesh":
        """Device copy of host arrays (:class:`pmjax.PMData`)."""
        V0, P = pm.n_original_vertices, pm.n_pcols
        parent = np.full(V0 + P, -1, np.int32)
        parent[pm.v1] = np.arange(P)
        parent[pm.v2] = np.arange(P)
        kills = np.bincount(pm.killer[pm.killer >= 0], minlength=P).astype(np.int32)
        created = pm.vertices[V0:]
        return ProgressiveMesh(
            vertices=jnp.asarray(pm.vertices),
            faces=jnp.asarray(pm.faces),
            child1=jnp.asarray(np.where(pm.v1 >= V0, pm.v1 - V0, -1).astype(np.int32)),
            child2=jnp.asarray(np.where(pm.v2 >= V0, pm.v2 - V0, -1).astype(np.int32)),
            parent=jnp.asarray(parent),
            killer=jnp.asarray(pm.killer),
            kills=jnp.asarray(kills),
            attributes=PcolAttributes(
                position=jnp.asarray(created),
                normal=jnp.asarray(pm.normals[V0:]),
                radius=jnp.asarray(pm.radius),
                alpha=jnp.asarray(pm.alpha),
                delta=jnp.asarray(pm.delta),
                mu=jnp.asarray(pm.mu),
            ),
            batch_offsets=tuple(int(o) for o in pm.batch_offsets),
            n_original_vertices=V0,
        )


def load(path: str | os.PathLike) -> ProgressiveMesh:
    """Read, validate and move a ``.pmz`` file to the JAX device.

    Raises:
        PMFormatError: see :func:`pmjax.read_pm`.
    """
    return ProgressiveMesh.from_data(read_pm(path))

