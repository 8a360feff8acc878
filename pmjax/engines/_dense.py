"""The dense engine: every pcol tested, the decisions propagated batch by batch.

``executed(p) = collapse(p) and exists(v1) and exists(v2)`` (docs/design.md).
Pcols of one batch only depend on earlier batches, so the sequential loop
becomes one vectorized predicate over all pcols plus one gather per batch,
each batch a static slice under ``jit``. The reference every other engine is
tested against, and the engine of GPUs, of user predicates and of meshes
being traced.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._bitsets import column_popcounts, pack_cameras, unpack_cameras, weight_bits_for
from .._predicate import ALL_TESTS, Tests, collapse_mask, critical_tau, view_collapse_mask
from .._view import View

if TYPE_CHECKING:
    from .._camera import Camera
    from .._model import ProgressiveMesh


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
    if P == 0:  # every vertex is its own representative
        return jnp.arange(V0, dtype=jnp.int32)

    def climb(parent, ids, created, pcols):
        t = gather(created, jnp.maximum(parent, 0))
        rep = jnp.where((parent >= 0) & (t >= 0), t, ids)
        # The original vertices always exist; a created one only if its pcol ran.
        return rep if pcols is None else jnp.where(executed[pcols], rep, -1)

    originals, created = down_the_batches(pm, lambda ids: jnp.where(executed, ids, -1), climb)
    created = jnp.where(created >= 0, created, jnp.arange(V0, V0 + P, dtype=jnp.int32))
    return jnp.concatenate([originals, created])


class DenseRefinement(eqx.Module):
    """The full-hierarchy arrays the dense engine computes for one view.

    Attributes:
        executed: ``bool[P]``; active: ``bool[F]``; rep: ``int32[V0 + P]``.
    """

    executed: Bool[Array, " P"]
    active: Bool[Array, " F"]
    rep: Int[Array, " V"]


@jax.jit
def _active_faces(pm, executed):
    k = pm.killer
    if pm.n_pcols == 0:  # nothing can kill a face
        return jnp.ones(k.shape, bool)
    return (k < 0) | ~gather(executed, jnp.maximum(k, 0))


_representatives = jax.jit(lambda pm, executed: representatives(pm, executed))


def finish(pm, executed):
    active = _active_faces(pm, executed)
    n_exec = jnp.sum(executed, dtype=jnp.int32)
    # Faces from the pcols, as executed_and_killed counts them for a batch:
    # m per executed pcol, corrected on the few uncommon pcols (a sum over P,
    # not over the F faces).
    m = pm.common_kills
    killed = m * n_exec + jnp.sum(jnp.where(gather(executed, pm.uncommon), pm.uncommon_extra_kills, 0))
    dense = DenseRefinement(executed=executed, active=active, rep=representatives(pm, executed))
    return dense, jnp.int32(pm.n_faces) - killed, jnp.int32(pm.n_original_vertices) - n_exec, n_exec


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
def refine(pm, camera, tau, context_arrays, context_static, tests, predicate, combine):
    context = eqx.combine(context_arrays, context_static.tree)
    tau = eqx.error_if(jnp.asarray(tau, jnp.float32), ~(tau >= 0), "tau must be >= 0 (and not NaN)")
    collapse = collapse_mask(pm.attributes, camera, tau, tests, predicate, context, combine)
    # Materialize the decisions once: fused into the per-batch slices of the
    # propagation, the predicate ran 20 % slower overall (dragon 5.1 -> 4.1 ms
    # per refine with the barrier, same bits).
    collapse = jax.lax.optimization_barrier(collapse)
    return finish(pm, propagate(pm, collapse))


@eqx.filter_jit
def counts_chunk(pm, cameras, tau, tests, predicate, context, combine, want_masks):
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


@eqx.filter_jit
def critical_tolerances(pm: ProgressiveMesh, camera: Camera, tests: Tests = ALL_TESTS) -> Float[Array, " P"]:
    """``eps[P]`` such that, for this view, ``executed(p) ⇔ tau > eps(p)``.

    ``eps(p) = max(t_p, eps(children))`` with ``t_p`` from
    :func:`pmjax.critical_tau` (docs/design.md): the whole family of refinements of
    one view in one array.
    """
    # Materialized once, as in refine (dragon 3.5 -> 2.9 ms).
    t = jax.lax.optimization_barrier(critical_tau(pm.attributes, camera, tests))
    return up_the_batches(pm, t, -jnp.inf, lambda own, a, b: jnp.maximum(own, jnp.maximum(a, b)))


def budget_sort(pm, eps, budget: int):
    """:func:`pmjax.faces_for_budget` from the critical tolerances ``eps`` of
    one view, on the host: one sort (a pcol runs at ``tau`` iff ``eps < tau``)."""
    eps = np.asarray(eps, np.float32)
    kills = np.asarray(pm.kills)
    order = np.argsort(eps, kind="stable")
    e = eps[order]
    faces_after = pm.n_faces - np.cumsum(kills[order])
    # All pcols with equal eps switch together: look at the end of each tie.
    ends = np.searchsorted(e, e, side="right") - 1
    faces_at = faces_after[ends]

    def faces_below(t):  # face count once every pcol with eps < t has run
        n = int(np.searchsorted(e, t, side="left"))
        return int(faces_after[n - 1]) if n else int(pm.n_faces)

    finest = faces_below(np.float32(0.0))
    if finest <= budget:
        return np.float32(0.0), finest
    ok = np.flatnonzero((faces_at <= budget) & np.isfinite(e))
    if len(ok) == 0:
        return np.float32(np.inf), faces_below(np.float32(np.inf))
    k = ok[0]  # eps >= 0 here: the negative ones all run at tau = 0
    return np.nextafter(e[k], np.float32(np.inf)), int(faces_at[k])


def budget_sort_traced(pm, eps, budget):
    """:func:`budget_sort` as JAX operations (under ``jit`` and ``vmap``):
    the same answer."""
    order = jnp.argsort(eps, stable=True)
    e = eps[order]
    faces_after = jnp.int32(pm.n_faces) - jnp.cumsum(pm.kills[order], dtype=jnp.int32)
    ends = jnp.searchsorted(e, e, side="right") - 1
    faces_at = faces_after[ends]

    def faces_below(t):
        n = jnp.searchsorted(e, jnp.float32(t), side="left")
        return jnp.where(n > 0, faces_after[jnp.maximum(n - 1, 0)], jnp.int32(pm.n_faces))

    finest = faces_below(0.0)
    ok = (faces_at <= budget) & jnp.isfinite(e)
    k = jnp.argmax(ok)
    fits, any_ok = finest <= budget, jnp.any(ok)
    tau = jnp.where(fits, jnp.float32(0), jnp.where(any_ok, jnp.nextafter(e[k], jnp.float32(jnp.inf)),
                                                   jnp.float32(jnp.inf)))
    faces = jnp.where(fits, finest, jnp.where(any_ok, faces_at[k], faces_below(jnp.inf)))
    return tau, faces


def mesh(pm, dense: DenseRefinement):
    """The compacted mesh of a dense refinement in fixed-capacity arrays (under
    ``jit``): ``(vertices float32 [V0, 3], faces int32 [F, 3], ids int32 [V0],
    n_faces, n_ids)``, faces in increasing original order, ids increasing;
    rows past the counts hold -1 (faces, ids) and 0 (vertices)."""
    F, V, V0 = pm.n_faces, pm.vertices.shape[0], pm.n_original_vertices
    active = dense.active
    corners = dense.rep[pm.faces]
    slot = jnp.cumsum(active, dtype=jnp.int32) - 1
    used = jnp.zeros(V, bool).at[jnp.where(active[:, None], corners, V)].set(True, mode="drop")
    rank = jnp.cumsum(used, dtype=jnp.int32) - 1
    # Distinct representatives drawn: at most one per original vertex.
    ids = jnp.nonzero(used, size=V0, fill_value=-1)[0].astype(jnp.int32)
    faces = jnp.full((F, 3), -1, jnp.int32).at[jnp.where(active, slot, F)].set(rank[corners], mode="drop")
    vertices = jnp.where(ids[:, None] >= 0, pm.vertices[jnp.maximum(ids, 0)], 0)
    return vertices, faces, ids, slot[-1] + 1 if F else jnp.int32(0), rank[-1] + 1
