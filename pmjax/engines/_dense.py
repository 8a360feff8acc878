"""The dense engine: every pcol tested, the decisions propagated batch by batch.

``executed(p) = collapse(p) and exists(v1) and exists(v2)`` (docs/design.md).
Pcols of one batch only depend on earlier batches, so the sequential loop
becomes one vectorized predicate over all pcols plus one gather per batch,
the batches visited by a few loops over windows under ``jit``. The reference
every other engine is tested against, and the engine of GPUs, of user
predicates and of meshes being traced.
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
from .._units import attributes_in_model_units, camera_in_model_units
from .._view import View

if TYPE_CHECKING:
    from .._camera import Camera
    from .._model import ProgressiveMesh


def gather(values, indices):
    """``values[indices]`` for indices known to be in range: no wrapping of
    negative indices nor clamping (cheaper gathers on the CPU)."""
    return values.at[indices].get(mode="promise_in_bounds")


# Loops per fold: the batches are visited by at most this many loops, one per
# window width, so a fold compiles a fixed handful of bodies whatever the
# number of batches. One window per batch: a loop step costs little, but
# each step's operations may be handed between threads.
MAX_WIDTHS = 6


@functools.lru_cache(maxsize=256)
def window_plan(sizes: tuple) -> tuple:
    """Window widths for a fold visiting batches of these sizes, one window each.

    A batch's window is at least as wide as the largest batch from it to the
    end of ``sizes``, so widths never grow along ``sizes`` and runs of equal
    width are consecutive. The at most :data:`MAX_WIDTHS` widths minimise
    the total window size (a small dynamic programme over the sizes).
    Empty batches get no window.

    Returns:
        ``((width, index), ...)`` in the order of ``sizes``: ``index`` an
        ``int`` array of positions in ``sizes`` whose windows have ``width``.
    """
    sizes = np.asarray(sizes, np.int64)
    index = np.nonzero(sizes)[0]
    if index.size == 0:
        return ()
    need = np.maximum.accumulate(sizes[index][::-1])[::-1]
    levels = np.unique(need)  # ascending
    # below[j]: windows whose need is at most levels[j - 1]. cost[k, j]: the
    # least total width of those with k + 1 widths, the largest levels[j].
    below = np.searchsorted(np.sort(need), levels, side="right")
    below = np.concatenate([[0], below])
    n, k_max = len(levels), min(MAX_WIDTHS, len(levels))
    cost = np.full((k_max, n), np.inf)
    choice = np.zeros((k_max, n), np.int64)
    cost[0] = levels * below[1:]
    for k in range(1, k_max):
        for j in range(k, n):
            # The next smaller width is levels[i]; it serves needs up to itself.
            c = cost[k - 1, :j] + levels[j] * (below[j + 1] - below[1:j + 1])
            choice[k, j] = int(np.argmin(c))
            cost[k, j] = c[choice[k, j]]
    k, j = int(np.argmin(cost[:, n - 1])), n - 1
    widths = [int(levels[j])]
    while k > 0:
        j, k = int(choice[k, j]), k - 1
        widths.append(int(levels[j]))
    widths = np.asarray(sorted(widths))
    width_of = widths[np.searchsorted(widths, need)]
    return tuple((int(w), index[width_of == w]) for w in sorted(set(width_of.tolist()), reverse=True))


def _fold(pm: ProgressiveMesh, carry, sizes_from: int, reverse: bool, update):
    """Rewrite each batch of ``carry`` (``[n, ...]``, rows = pcols) in turn.

    Batches ``sizes_from …`` of the mesh are visited in order (``reverse``:
    from the last), one window each (:func:`window_plan`), by a few
    ``lax.scan`` loops. ``update(carry, current, start, width)`` gives the
    new values of the window ``carry[start:start + width]`` (``current``);
    only the window's own batch is written, so a window may start before its
    batch (moved back to fit in the array) or run past it. The carry holds
    each batch's input until its window rewrites it: loops read their inputs
    from it, so reverse mode keeps one window per step, and nothing outside
    the loops is read per window (a value computed outside and read by the
    windows would be computed again inside their reads).
    """
    offsets = np.asarray(pm.batch_offsets, np.int64)
    n = carry.shape[0]
    trailing = (1,) * (carry.ndim - 1)
    runs = window_plan(tuple(np.diff(offsets)[sizes_from:].tolist()))
    for width, index in reversed(runs) if reverse else runs:
        batch = (index[::-1] if reverse else index) + sizes_from
        lo, hi = offsets[batch], offsets[batch + 1]
        windows = tuple(jnp.asarray(a.astype(np.int32)) for a in (np.minimum(lo, n - width), lo, hi))

        def step(carry, window, width=width):
            start, lo, hi = window
            row = start + jnp.arange(width, dtype=jnp.int32)
            mine = ((row >= lo) & (row < hi)).reshape((-1,) + trailing)
            current = jax.lax.dynamic_slice_in_dim(carry, start, width)
            new = jnp.where(mine, update(carry, current, start, width), current)
            return jax.lax.dynamic_update_slice_in_dim(carry, new, start, 0), None

        carry, _ = jax.lax.scan(step, carry, windows)
    return carry


def up_the_batches(pm: ProgressiveMesh, own, leaf, join):
    """Fold a per-pcol value up the hierarchy, fine to coarse.

    ``out[p] = join(own[p], value(v1), value(v2))`` where ``value`` is ``leaf``
    for an original vertex and ``out`` of the pcol that made a created one.
    Children always come from earlier batches, so a batch is one vectorized
    step, and the batches are visited by a few loops (:func:`_fold`): the
    program does not grow with the number of batches. ``own`` is
    ``[P, ...]``: trailing axes (cameras, words) ride along. ``leaf`` must be
    an identity of ``join`` (``join(x, leaf, leaf) = x``): the first batch,
    whose children are all original vertices, keeps ``own``.
    """
    trailing = (1,) * (own.ndim - 1)

    def update(out, own_window, start, width):
        c1 = jax.lax.dynamic_slice_in_dim(pm.child1, start, width)
        c2 = jax.lax.dynamic_slice_in_dim(pm.child2, start, width)
        e1 = jnp.where(c1.reshape((-1,) + trailing) < 0, leaf, gather(out, jnp.maximum(c1, 0)))
        e2 = jnp.where(c2.reshape((-1,) + trailing) < 0, leaf, gather(out, jnp.maximum(c2, 0)))
        return join(own_window, e1, e2)

    return _fold(pm, own, 1, False, update)


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


def down_the_batches(pm: ProgressiveMesh, own, combine):
    """Resolve a per-vertex value coarse to fine.

    ``out[v] = combine(own[v], out[parent(v)], has_parent)`` for every vertex
    ``v`` (``V0 + P`` of them; the parent is the created vertex of the pcol
    consuming ``v``, always of a later batch; ``has_parent`` is false for a
    vertex no pcol consumes, and the parent's value is then arbitrary).
    The created vertices are resolved batch by batch from the last, by a few
    loops (:func:`_fold`), then the original vertices in one step.
    ``combine`` sees ``[n, ...]`` slices and ``[n, 1...]`` flags, and must be
    elementwise in the vertex.

    Args:
        own: ``[V0 + P, ...]`` per-vertex inputs.
        combine: ``combine(own, parent_out, has_parent) -> out``.

    Returns:
        ``[V0 + P, ...]``: the values of all vertices.
    """
    V0 = pm.n_original_vertices
    flags = lambda parent: (parent >= 0).reshape(parent.shape + (1,) * (own.ndim - 1))
    parent = pm.parent[V0:]

    def update(created, own_window, start, width):
        up = jax.lax.dynamic_slice_in_dim(parent, start, width)
        return combine(own_window, gather(created, jnp.maximum(up, 0)), flags(up))

    created = _fold(pm, own[V0:], 0, True, update)
    up = pm.parent[:V0]
    originals = combine(own[:V0], gather(created, jnp.maximum(up, 0)), flags(up))
    return jnp.concatenate([originals, created])


def representatives(pm: ProgressiveMesh, executed: Bool[Array, " P"]) -> Int[Array, " V"]:
    """``vref``: each vertex's current representative (two-phase referencing).

    Resolved coarse to fine: a vertex takes its parent's representative
    (already final, parents are in later batches) if the parent ran, else
    itself. What is carried for a vertex is its representative if it exists
    (an original one, or a created one whose pcol ran) and -1 if not, so that
    each vertex reads one element (its parent's) instead of two.
    """
    V0, P = pm.n_original_vertices, pm.n_pcols
    if P == 0:  # every vertex is its own representative
        return jnp.arange(V0, dtype=jnp.int32)
    ids = jnp.arange(V0 + P, dtype=jnp.int32)
    exists = jnp.concatenate([jnp.ones(V0, bool), executed])

    def combine(own, t, has_parent):
        return jnp.where(own < 0, -1, jnp.where(has_parent & (t >= 0), t, own))

    rep = down_the_batches(pm, jnp.where(exists, ids, -1), combine)
    # A created vertex that does not exist is its own representative.
    return jnp.where(rep >= 0, rep, ids)


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
# meshes, and filter_jit's Python-side partition of the pytrees would be a
# large share of it.
@functools.partial(jax.jit, static_argnames=("context_static", "tests", "predicate", "combine"))
def refine(pm, camera, tau, context_arrays, context_static, tests, predicate, combine):
    context = eqx.combine(context_arrays, context_static.tree)
    tau = eqx.error_if(jnp.asarray(tau, jnp.float32), ~(tau >= 0), "tau must be >= 0 (and not NaN)")
    collapse = collapse_mask(pm.attributes, camera, tau, tests, predicate, context, combine)
    return finish(pm, propagate(pm, collapse))


@eqx.filter_jit
def counts_chunk(pm, cameras, tau, tests, predicate, context, combine, want_masks):
    # Collapse decisions per camera, then 32 cameras per word through the hierarchy.
    attrs, exponent = attributes_in_model_units(pm.attributes)
    views = View.batch(camera_in_model_units(cameras, exponent), tau)
    collapse = views.map(lambda v: view_collapse_mask(attrs, v, tests, predicate, context, combine, rows=False,
                                                      world=pm.attributes))
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
    t = critical_tau(pm.attributes, camera, tests)
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
