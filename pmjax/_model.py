"""The progressive mesh on the device: an immutable pytree of JAX arrays."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._pmfile import PMData, read_arrays
from ._structure import NestingCheck, check_normals, check_structure, remember_structure, structure_known
from ._subtree import SubtreeBounds, front_bounds, subtree_bounds


class PcolAttributes(eqx.Module):
    """What the refinement tests see of each pcol (float32 on the speed path).

    Struct of arrays: coordinates are rows (``[3, P]``), so every test is a
    fused elementwise loop over contiguous memory; the cone's sine and cosine
    are stored so no test needs trigonometry per view.

    Attributes:
        center: ``[3, P]`` the pcol vertex (sphere and cone centre), rows x, y, z.
        axis: ``[3, P]`` unit cone axis.
        radius: ``[P]`` bounding-sphere radius, model units.
        alpha: ``[P]`` cone half-angle, radians.
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
        max_kills, min_kills, common_kills: static, the most, the fewest and
            the most common number of faces one pcol removes (the batched face
            count is ``common_kills`` per executed pcol plus corrections whose
            bit planes these size).
        uncommon: ``[N]`` int32, the pcols whose kills differ from
            ``common_kills`` (the only ones the correction looks at).
        subtree: :class:`pmjax._subtree.SubtreeBounds`, per pcol, bounds over
            its subtree (the output-sensitive traversal's pruning test).
        roots: ``[R]`` int32, the pcols no pcol consumes (the forest's roots).
        table: ``[P, 16]`` float32, per pcol its attributes and subtree bounds
            in one 64-byte row (columns ``pmjax._front.TABLE_ATTRIBUTES``, then
            ``TABLE_BOUNDS``): the traversal gathers scattered pcols, one row
            each instead of 16 separate arrays.
        children: ``[P, 2]`` int32, ``child1`` and ``child2`` side by side.
        plan: static :class:`pmjax._front.FrontPlan` (traversal capacities,
            host arrays of the front mesh).
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
    subtree: SubtreeBounds
    roots: Int[Array, " R"]
    table: Float[Array, "P 16"]
    children: Int[Array, "P 2"]
    plan: object = eqx.field(static=True)
    batch_offsets: tuple = eqx.field(static=True)
    n_original_vertices: int = eqx.field(static=True)
    max_kills: int = eqx.field(static=True, default=0)
    min_kills: int = eqx.field(static=True, default=0)
    common_kills: int = eqx.field(static=True, default=0)

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

    def astype(self, dtype) -> "ProgressiveMesh":
        """The same mesh with positions and pcol attributes in ``dtype``
        (``jnp.float64`` for gradient checks; needs ``jax.enable_x64``)."""
        attrs = jax.tree.map(lambda x: x.astype(dtype), self.attributes)
        return eqx.tree_at(lambda m: (m.vertices, m.attributes), self, (self.vertices.astype(dtype), attrs))

    @staticmethod
    def from_data(pm: PMData, *, nesting=None) -> "ProgressiveMesh":
        """Device copy of host arrays (:class:`pmjax.PMData`).

        Args:
            pm: the host arrays.
            nesting: optional :class:`pmjax._structure.NestingCheck`, run on
                the subtree-bound pass (``pmjax.load`` uses it).
        """
        V0, P = pm.n_original_vertices, pm.n_pcols
        parent = np.full(V0 + P, -1, np.int32)
        parent[pm.v1] = np.arange(P)
        parent[pm.v2] = np.arange(P)
        from ._front import TABLE_ATTRIBUTES, TABLE_BOUNDS, FrontPlan, forest_generations

        kills = pm.kills.astype(np.int32)
        created = pm.vertices[V0:]
        child1 = np.where(pm.v1 >= V0, pm.v1 - V0, -1).astype(np.int32)
        child2 = np.where(pm.v2 >= V0, pm.v2 - V0, -1).astype(np.int32)
        attributes = PcolAttributes.from_arrays(created, pm.normals[V0:], pm.radius, pm.alpha, pm.delta, pm.mu)
        # Bounds from the float32 values the tests read.
        host = {k: np.asarray(getattr(attributes, k)) for k in ("center", "axis", "sin_alpha", "cos_alpha")}
        bounds = subtree_bounds(host["center"].T, host["axis"].T, pm.radius, host["sin_alpha"], host["cos_alpha"],
                                pm.delta, pm.mu, child1, child2, pm.batch_offsets, nesting=nesting)
        roots, depth = forest_generations(parent[V0:], pm.batch_offsets)
        rows = front_bounds(bounds, host["axis"])
        table = np.concatenate([np.atleast_2d(np.asarray(getattr(attributes, k))) for k in TABLE_ATTRIBUTES]
                               + [rows[k].reshape(1, P) for k in TABLE_BOUNDS]).T
        return ProgressiveMesh(
            vertices=jnp.asarray(pm.vertices),
            faces=jnp.asarray(pm.faces),
            child1=jnp.asarray(child1),
            child2=jnp.asarray(child2),
            parent=jnp.asarray(parent),
            killer=jnp.asarray(pm.killer),
            attributes=attributes,
            subtree=SubtreeBounds(**{k: jnp.asarray(v) for k, v in bounds.items()}),
            roots=jnp.asarray(roots),
            table=jnp.asarray(np.ascontiguousarray(table, np.float32)),
            children=jnp.asarray(np.stack([child1, child2], axis=1)),
            plan=FrontPlan(np.bincount(depth, minlength=1) if P else np.zeros(0, np.int64)),
            batch_offsets=tuple(int(o) for o in pm.batch_offsets),
            n_original_vertices=V0,
            **kill_summary(kills),
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


def load(path: str | os.PathLike) -> ProgressiveMesh:
    """Read, validate and move a ``.pmz`` file to the JAX device.

    Raises:
        PMFormatError: see :func:`pmjax.read_pm`.
    """
    data, fingerprint = read_arrays(path)
    if structure_known(fingerprint):
        return ProgressiveMesh.from_data(data)
    source = os.fspath(path)
    # The structure check runs beside the device copy (both mostly NumPy,
    # which releases the GIL), and the attributes' nesting inside the copy's
    # subtree-bound pass, which gathers the same parent-child pairs.
    # validate_pm has already bounded every index, so the copy is safe on a
    # forged file, and it is never returned.
    check_normals(data, source)
    with ThreadPoolExecutor(max_workers=1) as pool:
        check = pool.submit(check_structure, data, source=source, threads=1, nesting=False)
        pm = ProgressiveMesh.from_data(data, nesting=NestingCheck(data, source))
        check.result()
    remember_structure(fingerprint)
    return pm

