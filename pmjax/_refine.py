"""View-dependent refinement: the Visualizer's inverse traversal, batch by batch.

``executed(p) = collapse(p) and exists(v1) and exists(v2)`` (DESIGN §3). Pcols
of one batch only depend on earlier batches, so the sequential loop becomes
one vectorized predicate over all pcols plus one gather per batch, each batch
a static slice under ``jit``.
"""

from __future__ import annotations

import functools
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._bitsets import WORD, column_popcounts, pack_cameras, unpack_cameras, weight_bits_for
from ._camera import Camera, camera_count, index_camera
from ._model import ProgressiveMesh
from ._predicate import ALL_TESTS, Tests, UserPredicate, collapse_mask, critical_tau, view_collapse_mask
from ._view import View


def gather(values, indices):
    """``values[indices]`` for indices known to be in range: no wrapping of
    negative indices nor clamping (2x faster gathers on the CPU)."""
    return values.at[indices].get(mode="promise_in_bounds")


def up_the_batches(pm: ProgressiveMesh, own, leaf, join):
    """Fold a per-pcol value up the hierarchy, batch by batch (static slices).

    ``out[p] = join(own[p], value(v1), value(v2))`` where ``value`` is ``leaf``
    for an original vertex and ``out`` of the pcol that made a created one;
    children always come from earlier batches, so one gather per batch.
    ``own`` is ``[P, ...]``: trailing axes (cameras, words) ride along.
    ``leaf`` must be an identity of ``join`` (``join(x, leaf, leaf) = x``): the
    first batch, whose children are all original vertices, keeps ``own``, and
    only the later batches are computed (in place).
    """
    # An explicit copy: where ``own`` is an argument of the jitted caller,
    # without it XLA copied the whole array at every batch (dragon 0.44 -> 9.7 ms).
    out = jnp.copy(own)
    trailing = (1,) * (own.ndim - 1)
    for lo, hi in zip(pm.batch_offsets[1:-1], pm.batch_offsets[2:]):
        if lo == hi:
            continue
        c1 = pm.child1[lo:hi].reshape((-1,) + trailing)
        c2 = pm.child2[lo:hi].reshape((-1,) + trailing)
        e1 = jnp.where(c1 < 0, leaf, gather(out, jnp.maximum(pm.child1[lo:hi], 0)))
        e2 = jnp.where(c2 < 0, leaf, gather(out, jnp.maximum(pm.child2[lo:hi], 0)))
        out = out.at[lo:hi].set(join(own[lo:hi], e1, e2))
    return out


def propagate(pm: ProgressiveMesh, collapse):
    """Executed set from the per-pcol collapse decisions.

    A pcol runs if it may collapse and both its vertices exist: originals
    always exist, a created vertex exists iff the pcol making it ran.

    Args:
        collapse: ``bool[P]`` (one camera) or ``uint32[P, W]`` camera bitsets
            (:func:`pmjax._bitsets.pack_cameras`); the result has the same form.
    """
    everything = ~jnp.zeros((), collapse.dtype)  # True, or all 32 bits set
    return up_the_batches(pm, collapse, everything, lambda own, a, b: own & a & b)


def down_the_batches(pm: ProgressiveMesh, coarsest, climb):
    """Resolve a per-vertex value coarse to fine, batch by batch (static slices).

    A vertex's value depends on the pcol consuming it (its parent), always in
    a later batch, so batches are resolved from the last to the first, then
    the original vertices.

    Args:
        coarsest: ``coarsest(ids)``: values of the created vertices ``ids``
            (all ``P`` of them, ``V0 + p`` for pcol ``p``) as if nothing
            coarser mattered; final for the last batch, whose vertices no
            pcol consumes, and overwritten for the others.
        climb: ``climb(parent, ids, created, pcols)``: values of vertices
            ``ids`` given ``created``, the ``[P, ...]`` values of the created
            vertices (final for the parents' batches); ``parent`` is each
            vertex's consuming pcol (negative: consumed by none); ``pcols``
            is the static ``slice`` of pcols that made ``ids``, or ``None``
            for the original vertices (the last call).

    Returns:
        ``(originals [V0, ...], created [P, ...])``: the values of all vertices.
    """
    V0, P = pm.n_original_vertices, pm.n_pcols
    # Each batch is written in place into one [P] array: its reads (the
    # parents, in later batches) are separate gathers, so XLA updates the
    # slice without a copy. The previous way, a growing concatenation of the
    # finished batches, copied every coarser batch again at each batch
    # (dragon representatives 1.31 -> 1.22 ms, bunny 0.10 -> 0.08 ms).
    created = coarsest(jnp.arange(V0, V0 + P, dtype=jnp.int32))
    offsets = pm.batch_offsets
    for lo, hi in reversed(list(zip(offsets[:-2], offsets[1:-1]))):
        if lo == hi:
            continue
        ids = jnp.arange(V0 + lo, V0 + hi, dtype=jnp.int32)
        created = created.at[lo:hi].set(climb(pm.parent[V0 + lo:V0 + hi], ids, created, slice(lo, hi)))
    originals = climb(pm.parent[:V0], jnp.arange(V0, dtype=jnp.int32), created, None)
    return originals, created


def representatives(pm: ProgressiveMesh, executed: Bool[Array, " P"]) -> Int[Array, " V"]:
    """``vref``: each vertex's current representative (two-phase referencing).

    Resolved coarse to fine: a vertex takes its parent's representative
    (already final, parents are in later batches) if the parent ran, else
    itself. What is carried for the created vertices is their representative
    if their pcol ran and -1 if not, so that each vertex reads one random
    element (its parent's) instead of two (whether the parent ran, and its
    representative): dragon 1.26 -> 1.03 ms.
    """
    V0, P = pm.n_original_vertices, pm.n_pcols

    def climb(parent, ids, created, pcols):
        t = gather(created, jnp.maximum(parent, 0))
        rep = jnp.where((parent >= 0) & (t >= 0), t, ids)
        # The original vertices always exist; a created one only if its pcol ran.
        return rep if pcols is None else jnp.where(executed[pcols], rep, -1)

    originals, created = down_the_batches(pm, lambda ids: jnp.where(executed, ids, -1), climb)
    created = jnp.where(created >= 0, created, jnp.arange(V0, V0 + P, dtype=jnp.int32))
    return jnp.concatenate([originals, created])


class Refinement(eqx.Module):
    """The result of refining a progressive mesh for one view.

    Attributes:
        executed: ``bool[P]`` pcols executed.
        active: ``bool[F]`` faces drawn.
        rep: ``int32[V0 + P]`` representative of every vertex (``vref``).
        n_faces, n_vertices, n_executed: counts (``n_vertices`` = V0 − executed,
            the vertex front).
    """

    executed: Bool[Array, " P"]
    active: Bool[Array, " F"]
    rep: Int[Array, " V"]
    n_faces: Int[Array, ""]
    n_vertices: Int[Array, ""]
    n_executed: Int[Array, ""]

    def mesh(self, pm: ProgressiveMesh):
        """Compacted refined mesh as plain arrays.

        Returns:
            ``(vertices float32[n, 3], faces int32[m, 3], vertex_ids int64[n])``.
        """
        active = np.asarray(self.active)
        faces = np.asarray(self.rep)[np.asarray(pm.faces)[active]]
        ids, inverse = np.unique(faces, return_inverse=True)
        return np.asarray(pm.vertices)[ids], inverse.reshape(-1, 3).astype(np.int32), ids

    def to_trimesh(self, pm: ProgressiveMesh):
        """The refined mesh as a ``trimesh.Trimesh`` (not processed)."""
        import trimesh

        v, f, _ = self.mesh(pm)
        return trimesh.Trimesh(v, f, process=False)


def _finish(pm: ProgressiveMesh, executed) -> Refinement:
    k = pm.killer
    active = (k < 0) | ~gather(executed, jnp.maximum(k, 0))
    n_exec = jnp.sum(executed, dtype=jnp.int32)
    # Faces from the pcols, as executed_and_killed counts them for a batch:
    # m per executed pcol, corrected on the few uncommon pcols (a sum over P,
    # not over the F faces).
    m = pm.common_kills
    killed = m * n_exec + jnp.sum(jnp.where(gather(executed, pm.uncommon), pm.uncommon_extra_kills, 0))
    return Refinement(
        executed=executed,
        active=active,
        rep=representatives(pm, executed),
        n_faces=jnp.int32(pm.n_faces) - killed,
        n_vertices=jnp.int32(pm.n_original_vertices) - n_exec,
        n_executed=n_exec,
    )


def refine(
    pm: ProgressiveMesh,
    camera: Camera,
    tau=1.0,
    tests: Tests = ALL_TESTS,
    predicate: Optional[UserPredicate] = None,
    context=None,
    combine: str = "or",
) -> Refinement:
    """Refine ``pm`` for one camera.

    Args:
        pm: :class:`ProgressiveMesh` (``pmjax.load``).
        camera: one :class:`Camera`.
        tau: screen-space tolerance in pixels of the image height, a scalar
            ``>= 0``. A Python or NumPy value is checked here (``ValueError``);
            a JAX array is checked inside the compiled call.
        tests: :class:`Tests` to switch tests off (ablations).
        predicate, context, combine: optional user test, see
            :func:`pmjax.collapse_mask`.

    Returns:
        :class:`Refinement` (device arrays; ``.mesh(pm)`` gives NumPy arrays).
    """
    # A host scalar travels as a NumPy float32: a new value does not recompile,
    # and no device computation runs to convert it.
    if isinstance(tau, (int, float, np.generic, np.ndarray)):
        tau = np.asarray(tau, np.float32)
        if tau.shape != ():
            raise ValueError(f"tau must be a scalar, got shape {tau.shape}")
        if not tau >= 0:
            raise ValueError(f"tau must be >= 0 (and not NaN), got {tau}")
    # As under eqx.filter_jit, the context's arrays are traced and its other
    # leaves (Python numbers, strings) are static.
    if context is None or eqx.is_array(context):  # the common cases, without the partition's cost
        arrays, others = context, _NOTHING_STATIC
    else:
        arrays, others = eqx.partition(context, eqx.is_array)
        others = _Static(others)
    return _refine(pm, camera, tau, arrays, others, tests, predicate, combine)


class _Static:
    """A pytree of hashable leaves, usable as a static ``jax.jit`` argument."""

    def __init__(self, tree):
        self.leaves, self.treedef = jax.tree.flatten(tree)
        self._hash = hash((self.treedef, tuple(self.leaves)))

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return isinstance(other, _Static) and (self.treedef, self.leaves) == (other.treedef, other.leaves)

    @property
    def tree(self):
        return jax.tree.unflatten(self.treedef, self.leaves)


_NOTHING_STATIC = _Static(None)


# jax.jit, not eqx.filter_jit: the call is a few hundred microseconds on small
# meshes, and filter_jit's Python-side partition of the pytrees cost 60-90 us of
# it (bunny 0.37 -> 0.28 ms per refine).
@functools.partial(jax.jit, static_argnames=("context_static", "tests", "predicate", "combine"))
def _refine(pm, camera, tau, context_arrays, context_static, tests, predicate, combine):
    context = eqx.combine(context_arrays, context_static.tree)
    tau = eqx.error_if(jnp.asarray(tau, jnp.float32), ~(tau >= 0), "tau must be >= 0 (and not NaN)")
    collapse = collapse_mask(pm.attributes, camera, tau, tests, predicate, context, combine)
    # Materialize the decisions once: fused into the per-batch slices of the
    # propagation, the predicate ran 20 % slower overall (dragon 5.1 -> 4.1 ms
    # per refine with the barrier, same bits).
    collapse = jax.lax.optimization_barrier(collapse)
    return _finish(pm, propagate(pm, collapse))


@eqx.filter_jit
def _counts_chunk(pm, cameras, tau, tests, predicate, context, combine, want_masks):
    # Collapse decisions per camera, then 32 cameras per word through the hierarchy.
    views = View.batch(cameras, tau)
    collapse = views.map(lambda v: view_collapse_mask(pm.attributes, v, tests, predicate, context, combine, rows=False))
    words = propagate(pm, pack_cameras(collapse))
    n_exec, killed = executed_and_killed(pm, words)
    out = (pm.n_faces - killed, pm.n_original_vertices - n_exec, n_exec)
    return out + ((unpack_cameras(words),) if want_masks else ())


def executed_and_killed(pm: ProgressiveMesh, words):
    """Per camera, executed pcols and the faces they kill, from executed
    camera bitsets ``uint32[P, W]`` (:func:`propagate`).

    Most pcols kill the same number of faces ``m`` (2 for an edge collapse
    inside a manifold), so ``killed = m·executed + sum((kills − m)·bit)``,
    where the correction only reads the few other pcols (dragon: 0.7 %), one
    bit plane of their weights at a time.
    """
    n_exec = column_popcounts(words)
    m = pm.common_kills
    killed = m * n_exec
    rows = words[pm.uncommon]
    delta = pm.uncommon_extra_kills
    for sign, most in ((1, pm.max_kills - m), (-1, m - pm.min_kills)):
        weight = jnp.maximum(sign * delta, 0)
        for b in range(weight_bits_for(most) if most > 0 else 0):
            plane = jnp.where((((weight >> b) & 1) == 1)[:, None], rows, jnp.uint32(0))
            killed = killed + sign * (column_popcounts(plane) << b)
    return n_exec, killed


def refine_batch(
    pm: ProgressiveMesh,
    cameras: Camera,
    tau=1.0,
    *,
    tests: Tests = ALL_TESTS,
    predicate: Optional[UserPredicate] = None,
    context=None,
    combine: str = "or",
    chunk: int = 256,
    return_masks: bool = False,
    progress: bool = False,
) -> dict:
    """Refine for K cameras at once (vmap), ``chunk`` cameras per kernel call so
    memory stays bounded for any K.

    Args:
        pm: :class:`ProgressiveMesh`.
        cameras: a camera batch (leading axis K).
        tau: tolerance in pixels (shared by all cameras).
        chunk: cameras per vmapped call, rounded up to a multiple of 32 (one
            bitset word); the last chunk is padded.
        return_masks: also return ``executed`` masks ``bool[K, P]``.

    Returns:
        dict of NumPy arrays: ``faces``, ``vertices``, ``executed_count``
        (``int32[K]``) and, on request, ``executed`` (``bool[K, P]``).
    """
    K = camera_count(cameras)
    if K == 0:
        raise ValueError("refine_batch needs a camera batch (leading axis); use refine for one camera")
    if not (np.isfinite(tau) and tau >= 0):
        raise ValueError(f"tau must be >= 0 and finite, got {tau}")
    chunk = -(-max(1, min(int(chunk), K)) // WORD) * WORD
    outs = []
    starts = range(0, K, chunk)
    if progress:
        from tqdm import tqdm

        starts = tqdm(starts, unit="chunk", desc="refine")
    tau32 = jnp.float32(tau)
    for s in starts:
        idx = np.minimum(np.arange(s, s + chunk), K - 1)  # pad by repeating the last
        part = index_camera(cameras, jnp.asarray(idx))
        res = _counts_chunk(pm, part, tau32, tests, predicate, context, combine, return_masks)
        n = min(chunk, K - s)
        outs.append([np.asarray(r)[:n] for r in res])
    cols = [np.concatenate(c) for c in zip(*outs)]
    out = dict(faces=cols[0], vertices=cols[1], executed_count=cols[2])
    if return_masks:
        out["executed"] = cols[3]
    return out


# -- critical tolerances ----------------------------------------------------------


@eqx.filter_jit
def critical_tolerances(pm: ProgressiveMesh, camera: Camera, tests: Tests = ALL_TESTS) -> Float[Array, " P"]:
    """``eps[P]`` such that, for this view, ``executed(p) ⇔ tau > eps(p)``.

    ``eps(p) = max(t_p, eps(children))`` with ``t_p`` from
    :func:`pmjax.critical_tau` (DESIGN §3): the whole family of refinements of
    one view in one array.
    """
    # Materialized once, as in refine (dragon 3.5 -> 2.9 ms).
    t = jax.lax.optimization_barrier(critical_tau(pm.attributes, camera, tests))
    return up_the_batches(pm, t, -jnp.inf, lambda own, a, b: jnp.maximum(own, jnp.maximum(a, b)))


def faces_for_budget(pm: ProgressiveMesh, camera: Camera, budget: int, tests: Tests = ALL_TESTS):
    """The smallest ``tau`` whose face count is the largest not above ``budget``.

    One sort of the critical tolerances: the face count for ``tau`` is ``F``
    minus the faces killed by pcols with ``eps < tau``.

    Returns:
        ``(tau, faces)``: ``tau`` (pixels, float32) and the face count there.
        If no tolerance meets the budget, the coarsest (``tau = inf``) count.
    """
    eps = np.asarray(critical_tolerances(pm, camera, tests), np.float32)
    kills = np.asarray(pm.kills)
    order = np.argsort(eps, kind="stable")
    e = eps[order]
    faces_after = pm.n_faces - np.cumsum(kills[order])
    # All pcols with equal eps switch together: look at the end of each tie.
    ends = np.searchsorted(e, e, side="right") - 1
    faces_at = faces_after[ends]
    if pm.n_faces <= budget:
        return np.float32(0.0), int(pm.n_faces)
    ok = np.flatnonzero((faces_at <= budget) & np.isfinite(e))
    if len(ok) == 0:
        return np.float32(np.inf), int(faces_after[-1] if len(e) else pm.n_faces)
    k = ok[0]
    tau = np.nextafter(np.float32(max(e[k], 0.0)), np.float32(np.inf)) if e[k] >= 0 else np.float32(0.0)
    return np.float32(tau), int(faces_at[k])
