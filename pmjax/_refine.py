"""View-dependent refinement: the Visualizer's inverse traversal, batch by batch.

``executed(p) = collapse(p) and exists(v1) and exists(v2)`` (docs/design.md). Pcols
of one batch only depend on earlier batches, so the sequential loop becomes
one vectorized predicate over all pcols plus one gather per batch, each batch
a static slice under ``jit``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt32

from . import _native
from ._bitsets import WORD, column_popcounts, pack_cameras, unpack_cameras, weight_bits_for
from ._camera import Camera, camera_count, index_camera
from ._front import gather, one_camera_decide, traverse
from ._model import ProgressiveMesh
from ._predicate import ALL_TESTS, Tests, UserPredicate, collapse_mask, critical_tau, view_collapse_mask
from ._subtree import subtree_collapses
from ._view import View


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


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["pm", "visited", "visited_executed", "dense", "n_faces", "n_vertices", "n_executed",
                                "front_positions"],
                   meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Refinement:
    """The result of refining a progressive mesh for one view.

    An immutable pytree (a frozen dataclass registered with JAX): it is made
    and read on the host once per view, where an ``equinox.Module``'s
    construction checks and bound methods cost more than a small refine.

    The output-sensitive engine (``method="front"``) keeps only the pcols its
    traversal visited and whether each ran; every other pcol lies under a
    decided subtree and ran. The full arrays (``executed``, ``active``,
    ``rep``) are computed from that when asked; the dense engine
    (``method="dense"``) computes them eagerly.

    Attributes:
        pm: the :class:`ProgressiveMesh` refined (shared, not copied).
        visited: ``int32[C]`` pcols the traversal visited, ``P`` in unused slots
            (``None`` from the dense engine).
        visited_executed: ``bool[C]`` whether each ran (``True`` in unused slots).
        dense: :class:`DenseRefinement` from the dense engine, else ``None``.
        n_faces, n_vertices, n_executed: counts (``n_vertices`` = V0 − executed,
            the vertex front).
        front_positions: ``int32[C]`` the visited pcols' places in the C
            loops' breadth-first layout, which their front mesh reads (``None``
            from the other engines).
    """

    pm: ProgressiveMesh
    visited: Optional[Int[Array, " C"]]
    visited_executed: Optional[Bool[Array, " C"]]
    dense: Optional[DenseRefinement]
    n_faces: Int[Array, ""]
    n_vertices: Int[Array, ""]
    n_executed: Int[Array, ""]
    front_positions: Optional[Int[Array, " C"]] = None

    @property
    def executed(self) -> Bool[Array, " P"]:
        """``bool[P]`` pcols executed."""
        if self.dense is not None:
            return self.dense.executed
        if isinstance(self.visited, np.ndarray):  # host lists (C traversal, paths): no compile per length
            out = np.ones(self.pm.n_pcols, bool)
            out[self.visited[self.visited < self.pm.n_pcols]] = np.asarray(self.visited_executed)[
                self.visited < self.pm.n_pcols]
            return jnp.asarray(out)
        return _spread_executed(self.visited, self.visited_executed, self.pm.n_pcols)

    @property
    def active(self) -> Bool[Array, " F"]:
        """``bool[F]`` faces drawn (their killer did not run)."""
        if self.dense is not None:
            return self.dense.active
        return _active_faces(self.pm, self.executed)

    @property
    def rep(self) -> Int[Array, " V"]:
        """``int32[V0 + P]`` representative of every vertex (``vref``)."""
        if self.dense is not None:
            return self.dense.rep
        return _representatives(self.pm, self.executed)

    @property
    def n_visited(self) -> int:
        """Pcols whose decision the engine looked at (``P`` for the dense engine)."""
        if self.visited is None:
            return self.pm.n_pcols
        if isinstance(self.visited, np.ndarray):
            return int(np.count_nonzero(self.visited < self.pm.n_pcols))
        return int(jnp.sum(self.visited < self.pm.n_pcols))

    def mesh(self, pm: Optional[ProgressiveMesh] = None):
        """Compacted refined mesh as plain arrays.

        Args:
            pm: the mesh refined (optional; it is the one :attr:`pm` holds).

        Returns:
            ``(vertices float32[n, 3], faces int32[m, 3], vertex_ids int32[n])``:
            faces in increasing original face order, ``vertex_ids`` the sorted
            PM vertex ids used. From the front its cost follows the faces
            drawn, plus one prefix sum over the V0 original vertices.
        """
        if pm is not None and pm is not self.pm and (pm.n_pcols, pm.n_faces, pm.n_original_vertices) != (
                self.pm.n_pcols, self.pm.n_faces, self.pm.n_original_vertices):
            raise ValueError("Refinement.mesh: pm is not the mesh this refinement was made for "
                             f"({pm.n_pcols} pcols, {pm.n_faces} faces; refined: {self.pm.n_pcols}, {self.pm.n_faces})")
        if self.dense is None:
            visited, ran = np.asarray(self.visited), np.asarray(self.visited_executed)
            if self.front_positions is not None and _native.available():
                return _native.front_mesh(self.pm, visited, ran, self.front_positions, int(self.n_faces),
                                          int(self.n_vertices))
            from ._front_mesh import front_mesh

            return front_mesh(self.pm, visited, ran)
        active = np.asarray(self.dense.active)
        faces = np.asarray(self.dense.rep)[np.asarray(self.pm.faces)[active]]
        ids, inverse = np.unique(faces, return_inverse=True)
        return np.asarray(self.pm.vertices)[ids], inverse.reshape(-1, 3).astype(np.int32), ids

    def to_trimesh(self, pm: Optional[ProgressiveMesh] = None):
        """The refined mesh as a ``trimesh.Trimesh`` (not processed)."""
        import trimesh

        v, f, _ = self.mesh(pm)
        return trimesh.Trimesh(v, f, process=False)


@functools.partial(jax.jit, static_argnums=2)
def _spread_executed(visited, visited_executed, n_pcols):
    # Unused slots hold P: dropped.
    return jnp.ones(n_pcols, bool).at[visited].set(visited_executed, mode="drop")


@jax.jit
def _active_faces(pm, executed):
    k = pm.killer
    if pm.n_pcols == 0:  # nothing can kill a face
        return jnp.ones(k.shape, bool)
    return (k < 0) | ~gather(executed, jnp.maximum(k, 0))


_representatives = jax.jit(lambda pm, executed: representatives(pm, executed))


def _finish(pm: ProgressiveMesh, executed):
    active = _active_faces(pm, executed)
    n_exec = jnp.sum(executed, dtype=jnp.int32)
    # Faces from the pcols, as executed_and_killed counts them for a batch:
    # m per executed pcol, corrected on the few uncommon pcols (a sum over P,
    # not over the F faces).
    m = pm.common_kills
    killed = m * n_exec + jnp.sum(jnp.where(gather(executed, pm.uncommon), pm.uncommon_extra_kills, 0))
    dense = DenseRefinement(executed=executed, active=active, rep=representatives(pm, executed))
    return dense, jnp.int32(pm.n_faces) - killed, jnp.int32(pm.n_original_vertices) - n_exec, n_exec


METHODS = ("auto", "front", "dense")

# "auto" picks the front engine (docs/front.md, same-run measurements on 2
# cores): with the C loops, for one camera on every hierarchy (cow, 2,896
# pcols: 3.7x faster than dense; dragon, 436,325: 18-20x) and for camera
# batches from FRONT_BATCH_FROM_PCOLS on (bunny, 34,819: 1.3-1.6x; Grand
# Canyon, 39,998: 1.5-1.6x; St Helens, 148,883: 3.5x; dragon: 5.3-5.6x; cow
# 0.5-0.7x). Without
# them, the front engine as JAX kernels wins for one camera only from
# FRONT_FROM_PCOLS on (bunny 0.63x, St Helens 1.44x, dragon 2.06x) and never
# for batches.
FRONT_FROM_PCOLS = 100_000
FRONT_BATCH_FROM_PCOLS = 30_000


def _method(pm: ProgressiveMesh, method: str, predicate, batch: bool = False) -> str:
    """The engine a call uses. ``"auto"``: the front engine where it is the
    faster (above); the dense engine for a user predicate (it has no subtree
    bound, so only the dense engine can apply it)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "front" and predicate is not None:
        raise ValueError("method='front' cannot apply a user predicate (it has no subtree bound); "
                         "use method='dense' or 'auto'")
    if pm.n_pcols == 0:
        return "dense"
    if method == "auto":
        if predicate is not None:
            return "dense"
        if _native.available():
            return "front" if not batch or pm.n_pcols >= FRONT_BATCH_FROM_PCOLS else "dense"
        return "front" if not batch and pm.n_pcols >= FRONT_FROM_PCOLS else "dense"
    return method


def check_tau(tau) -> float:
    """A host tolerance as a ``float``: >= 0, ``inf`` allowed (every collapsible
    pcol), NaN refused (``ValueError``)."""
    try:
        value = float(tau)
    except (TypeError, ValueError):
        raise ValueError(f"tau must be a number >= 0, got {tau!r}") from None
    if not value >= 0:
        raise ValueError(f"tau must be >= 0 (inf: every collapsible pcol; not NaN), got {tau}")
    return value


def _host_tau(tau):
    """A host scalar tau as float32 (a new value does not recompile), checked;
    a JAX array is passed on and checked inside the compiled call."""
    if isinstance(tau, jax.Array) and not isinstance(tau, jax.core.Tracer):
        tau = np.asarray(tau)  # concrete: checked here, not inside the compiled call
    if isinstance(tau, (int, float, np.generic, np.ndarray)):
        tau = np.asarray(tau, np.float32)
        if tau.shape != ():
            raise ValueError(f"tau must be a scalar, got shape {tau.shape}")
        check_tau(tau)
    return tau


def refine(
    pm: ProgressiveMesh,
    camera: Camera,
    tau=1.0,
    tests: Tests = ALL_TESTS,
    predicate: Optional[UserPredicate] = None,
    context=None,
    combine: str = "or",
    method: str = "auto",
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
        method: ``"front"``: output-sensitive traversal from the roots, pruned
            by subtree bounds (cost ∝ the pcols near the front; C loops where
            they are built, else JAX kernels); ``"dense"``: every pcol tested
            and propagated (the reference); ``"auto"`` (default): ``"front"``
            where it is faster (every hierarchy with the C loops; from
            ``FRONT_FROM_PCOLS`` pcols without), ``"dense"`` with a user
            predicate (which has no subtree bound). All give the same bits.

    Returns:
        :class:`Refinement` (device arrays; ``.mesh()`` gives NumPy arrays).
    """
    tau = _host_tau(tau)
    if _method(pm, method, predicate) == "front":
        return _refine_front(pm, camera, tau, tests)
    # As under eqx.filter_jit, the context's arrays are traced and its other
    # leaves (Python numbers, strings) are static.
    if context is None or eqx.is_array(context):  # the common cases, without the partition's cost
        arrays, others = context, _NOTHING_STATIC
    else:
        arrays, others = eqx.partition(context, eqx.is_array)
        others = _Static(others)
    dense, n_faces, n_vertices, n_executed = _refine(pm, camera, tau, arrays, others, tests, predicate, combine)
    return Refinement(pm=pm, visited=None, visited_executed=None, dense=dense, n_faces=n_faces,
                      n_vertices=n_vertices, n_executed=n_executed)


def _refine_front(pm: ProgressiveMesh, camera: Camera, tau, tests: Tests) -> Refinement:
    if _native.available():
        visited, ran, positions, n_faces, n_vertices, n_executed = _native.refine_one(pm, camera, tau, tests)
        return Refinement(pm=pm, visited=visited, visited_executed=ran, dense=None, n_faces=n_faces,
                          n_vertices=n_vertices, n_executed=n_executed, front_positions=positions)
    # The one host synchronisation: did every generation fit its buffer?
    out = pm.plan.run(("one", tests, camera.orthographic),
                      lambda capacities: _front_refine(pm, camera, tau, tests, capacities))
    visited, ran, n_faces, n_vertices, n_executed, _ = out
    return Refinement(pm=pm, visited=visited, visited_executed=ran, dense=None, n_faces=n_faces,
                      n_vertices=n_vertices, n_executed=n_executed)


def front_counts(pm: ProgressiveMesh, visited, not_ran):
    """``(n_faces, n_vertices, n_executed)`` from the pcols that did not run
    (``not_ran``, lanes over ``visited``; ``visited`` holds ``P`` in unused
    slots): every face is drawn but those killed by the pcols that ran."""
    P = pm.n_pcols
    if P == 0:  # every face drawn, no pcol
        return jnp.int32(pm.n_faces), jnp.int32(pm.n_original_vertices), jnp.int32(0)
    kills = jnp.where(visited < P, gather(pm.kills, jnp.minimum(visited, P - 1)), 0)
    n_not_run = jnp.sum(not_ran, axis=-1, dtype=jnp.int32)
    kept = jnp.sum(jnp.where(not_ran, kills, 0), axis=-1, dtype=jnp.int32)
    n_exec = P - n_not_run
    return pm.n_faces - pm.total_kills + kept, pm.n_original_vertices - n_exec, n_exec


@functools.partial(jax.jit, static_argnames=("tests", "capacities"))
def _front_refine(pm, camera, tau, tests, capacities):
    tau = eqx.error_if(jnp.asarray(tau, jnp.float32), ~(tau >= 0), "tau must be >= 0 (and not NaN)")
    view = View.of(camera, tau)
    visited, ran, needed = traverse(pm, one_camera_decide(view, tests), capacities, bool)
    counts = front_counts(pm, visited, (visited < pm.n_pcols) & ~ran)
    return (visited, ran) + counts + (needed,)


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


def word_counts(pm: ProgressiveMesh, visited, ran):
    """:func:`front_counts` for a word of 32 cameras, from the executed words
    ``ran`` of the visited pcols: per camera, the pcols that did not run and
    the faces they keep are column popcounts (one per bit plane of the kill
    counts), not sums over 32 unpacked rows."""
    P = pm.n_pcols
    if P == 0:
        return tuple(jnp.full(WORD, v, jnp.int32) for v in (pm.n_faces, pm.n_original_vertices, 0))
    valid = visited < P
    kills = jnp.where(valid, gather(pm.kills, jnp.minimum(visited, P - 1)), 0)
    not_ran = jnp.where(valid, ~ran, jnp.uint32(0))[:, None]  # [C, 1]
    n_not_run = column_popcounts(not_ran)
    kept = jnp.zeros(WORD, jnp.int32)
    for b in range(weight_bits_for(pm.max_kills)):
        kept = kept + (column_popcounts(jnp.where((((kills >> b) & 1) == 1)[:, None], not_ran, jnp.uint32(0))) << b)
    n_exec = P - n_not_run
    return pm.n_faces - pm.total_kills + kept, pm.n_original_vertices - n_exec, n_exec


def pack_word(mask: Bool[Array, "32 N"]) -> UInt32[Array, " N"]:
    """One word of 32 cameras per column: bit ``c`` is ``mask[c]``. An
    unrolled OR of shifted rows, one elementwise loop (the reduction over
    the camera axis of :func:`pmjax._bitsets.pack_cameras` ran 3x slower on
    the front's gathered columns)."""
    word = mask[0].astype(jnp.uint32)
    for c in range(1, WORD):
        word = word | (mask[c].astype(jnp.uint32) << c)
    return word


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
    method: str = "auto",
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
        method: ``"dense"``, ``"front"`` (each camera traversed by the C
            loops, the cameras split over the cores; as JAX kernels where the
            loops are not built, per group of 32 cameras the union of their
            fronts) or ``"auto"``: the front engine with the C loops from
            ``FRONT_BATCH_FROM_PCOLS`` pcols on, else dense (docs/front.md).
            Same results.

    Returns:
        dict of NumPy arrays: ``faces``, ``vertices``, ``executed_count``
        (``int32[K]``) and, on request, ``executed`` (``bool[K, P]``).
    """
    K = camera_count(cameras)
    if K == 0:
        raise ValueError("refine_batch needs a camera batch (leading axis); use refine for one camera")
    tau = check_tau(tau)
    chunk = -(-max(1, min(int(chunk), K)) // WORD) * WORD
    outs = []
    starts = range(0, K, chunk)
    if progress:
        from tqdm import tqdm

        starts = tqdm(starts, unit="chunk", desc="refine")
    front = _method(pm, method, predicate, batch=True) == "front"
    native = front and _native.available()
    # The C loops read tau on the host (a device scalar costs a dispatch).
    tau32 = np.float32(tau) if native else jnp.float32(tau)
    # The front engine takes nearby cameras together: as JAX kernels in words,
    # as C loops one after another (their fronts share cache lines; 4-6 %
    # faster on the dragon). Results go back to the caller's order.
    order = nearby_order(np.asarray(cameras.eye)) if front else np.arange(K)
    # Chunks are cut on the host (one transfer of the batch, then NumPy
    # indexing: slicing device arrays costs a dispatch per field and chunk,
    # measured at half the time of a bunny batch), and their results are read
    # only after every chunk is dispatched, so cutting overlaps computing.
    host = jax.tree.map(np.asarray, cameras)
    for s in starts:
        idx = order[np.minimum(np.arange(s, s + chunk), K - 1)]  # pad by repeating the last
        part = jax.tree.map(lambda a: a[idx], host)
        if native:
            res = _native.refine_many(pm, part, tau32, tests, return_masks)
        elif front:
            res = _front_counts(pm, part, tau32, tests, return_masks)
        else:
            res = _counts_chunk(pm, part, tau32, tests, predicate, context, combine, return_masks)
        n = min(chunk, K - s)
        # Masks are large: read each chunk's at once; counts at the end.
        outs.append(([np.asarray(r)[:n] for r in res] if return_masks else res, n))
    outs = [[np.asarray(r)[:n] for r in res] for res, n in outs]
    cols = [np.empty_like(c) for c in (np.concatenate(c) for c in zip(*outs))]
    for col, parts in zip(cols, zip(*outs)):
        col[order] = np.concatenate(parts)
    out = dict(faces=cols[0], vertices=cols[1], executed_count=cols[2])
    if return_masks:
        out["executed"] = cols[3]
    return out


def nearby_order(eyes: np.ndarray) -> np.ndarray:
    """An order of the cameras in which consecutive eyes are close: the
    Morton (Z-order) code of each eye in the eyes' bounding box, 10 bits per
    axis. Cameras that see the model from nearby share most of their front, so
    a word of 32 of them visits little more than one camera alone."""
    lo, hi = eyes.min(0), eyes.max(0)
    cells = ((eyes - lo) / np.where(hi > lo, hi - lo, 1.0) * 1023).astype(np.int64)
    # Bit b of axis a goes to bit 3b + a (the bits are disjoint: a sum is an or).
    bits = np.arange(10)
    code = (((cells[:, :, None] >> bits) & 1) << (3 * bits + np.arange(3)[:, None])).sum(axis=(1, 2))
    return np.argsort(code, kind="stable")


def _front_counts(pm: ProgressiveMesh, cameras: Camera, tau, tests: Tests, want_masks: bool, want_front=False):
    """Counts (and on request dense masks, or each word's front) of a chunk of
    cameras, 32 per word, through :func:`_front_counts_chunk`; the buffers
    are grown and the chunk redone when a word needed more."""
    out = pm.plan.run(("word", tests, cameras.orthographic),
                      lambda capacities: _front_counts_chunk(pm, cameras, tau, tests, capacities, want_masks,
                                                             want_front))
    return out[:-1]


@functools.partial(jax.jit, static_argnames=("tests", "capacities", "want_masks", "want_front"))
def _front_counts_chunk(pm, cameras, tau, tests, capacities, want_masks, want_front=False):
    """Per camera ``(faces, vertices, executed)``, then ``executed`` masks
    ``bool[K, P]`` if ``want_masks``, then, if ``want_front``, per word of 32
    cameras the visited pcols ``int32[W, C]`` and their executed words
    ``uint32[W, C]``, and last the buffers each word needed. ``tau``: a
    scalar or one per camera."""
    views = View.batch(cameras, tau)
    words = views.values.reshape(views.values.shape[0], -1, WORD)  # [22, W, 32]

    def one_word(values):
        group = View(values, cameras.orthographic)

        def decide(attrs, bounds):
            collapse = group.map(lambda v: view_collapse_mask(attrs, v, tests, rows=False))
            whole = group.map(lambda v: subtree_collapses(attrs.center, attrs.axis, bounds, v, tests))
            return pack_word(collapse), pack_word(whole)

        visited, ran, needed = traverse(pm, decide, capacities, jnp.uint32)
        counts = word_counts(pm, visited, ran)
        masks = ()
        if want_masks:
            dense = jnp.full(pm.n_pcols, ~jnp.uint32(0)).at[visited].set(ran, mode="drop")
            masks = (unpack_cameras(dense[:, None]),)
        front = (visited, ran) if want_front else ()
        return counts + masks + front + (needed,)

    # lax.map, not vmap: under vmap each generation's conditional becomes a
    # select that runs every generation at full capacity.
    out = jax.lax.map(one_word, jnp.moveaxis(words, 1, 0))
    n_front = 2 if want_front else 0
    # Words back to cameras: [W, 32, ...] -> [K, ...]; the fronts and ``needed`` stay per word.
    per_camera = out[:len(out) - 1 - n_front]
    return tuple(x.reshape((-1,) + x.shape[2:]) for x in per_camera) + tuple(out[len(per_camera):])


# -- critical tolerances ----------------------------------------------------------


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


def check_budget(budget) -> int:
    """A face budget as an ``int``: a whole number >= 0 (``ValueError`` otherwise)."""
    ok = isinstance(budget, (int, np.integer)) and not isinstance(budget, bool)
    if not ok and isinstance(budget, (float, np.floating)) and np.isfinite(budget) and float(budget).is_integer():
        ok, budget = True, int(budget)
    if not ok or budget < 0:
        raise ValueError(f"a face budget must be a whole number >= 0, got {budget!r}")
    return int(budget)


def faces_for_budget(pm: ProgressiveMesh, camera: Camera, budget: int, tests: Tests = ALL_TESTS,
                     method: str = "auto"):
    """The smallest ``tau`` whose face count is the largest not above ``budget``.

    Dense: one sort of the critical tolerances: a pcol runs at ``tau`` iff
    ``eps < tau``, so the face count at ``tau`` is ``F`` minus the faces killed
    by the pcols with ``eps < tau``. Even ``tau = 0`` runs the pcols with
    ``eps < 0`` (culled: outside the frustum or facing away). Front: a
    search over the float32 bit patterns of ``tau`` (a bracket, then regula
    falsi on ``log tau``) on exact counts of the output-sensitive engine
    (about 24 refinements, each costing what the view's front costs); the same
    answer (docs/design.md).

    Args:
        pm: :class:`ProgressiveMesh`.
        camera: one camera.
        budget: faces, a whole number >= 0.
        tests: :class:`Tests`.
        method: ``"front"`` (the C loops), ``"dense"`` or ``"auto"`` (front
            with the C loops from ``FRONT_FROM_PCOLS`` pcols on, else dense).

    Returns:
        ``(tau, faces)``: ``tau`` (pixels, float32) and the face count there,
        which :func:`pmjax.refine` reproduces. ``tau = 0`` when even the finest
        view fits; when no tolerance meets the budget, ``tau = inf`` and the
        coarsest count, which is then above ``budget``.

    Raises:
        ValueError: a budget that is negative, fractional, NaN or not a number.
    """
    budget = check_budget(budget)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "front" and not _native.available():
        raise ValueError("faces_for_budget(method='front') needs the C loops (pmjax.native_available()); "
                         "use method='dense' or 'auto'")
    # The search pays about 24 refines: faster than the sort from about
    # FRONT_FROM_PCOLS pcols on (measured in docs/front.md).
    front = method == "front" or (method == "auto" and pm.n_pcols >= FRONT_FROM_PCOLS)
    if front and _native.available() and pm.n_pcols > 0:
        return _native.faces_for_budget(pm, camera, budget, tests)
    eps = np.asarray(critical_tolerances(pm, camera, tests), np.float32)
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
