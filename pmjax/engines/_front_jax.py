"""The front engine as JAX kernels: a top-down traversal that stops where a subtree is decided.

Where the C core is not built, this engine refines a camera or a camera
batch eagerly (its buffer capacities adapt between calls, which needs the
host). The dense engine tests every pcol. Here the forest of pcols is walked
from its roots, one generation (depth below a root) at a time. At each visited pcol two
things are evaluated:

- its own decision, ``collapse(p)``, by the very predicate the dense engine
  uses (:func:`pmjax._predicate.view_collapse_mask`), so the bits are the same;
- the subtree bound (:func:`pmjax._subtree.subtree_collapses`): if every pcol
  below certainly collapses, the whole subtree is executed and not entered.

The children of the other visited pcols form the next generation. Then, from
the deepest generation up, ``executed(p) = whole(p) ∨ (collapse(p) ∧
executed(c1) ∧ executed(c2))``, an original vertex counting as executed. Every
pcol not visited lies under a decided subtree, so it is executed: the visited
pcols and their flags are the whole answer, and the work is proportional to
them (about twice the pcols not executed), not to the hierarchy. On a CPU,
each generation also has a fixed cost of a dozen small kernels, which
dominates on small hierarchies (docs/front.md).

Generations are fixed-capacity buffers (XLA needs static shapes). The
children of a generation are compacted into the next buffer by a prefix sum;
each call reports how many each generation needed. The first call on a mesh
uses buffers as large as the whole forest's generations (exact, never
overflows) and sizes the buffers from what it needed; a later call that needed
more than a buffer holds is redone with the full buffers, and the buffers grow
(:class:`FrontPlan`). The answer is therefore always exact; only its cost
depends on the capacities.

The same traversal serves many cameras at once: a node then carries a
``uint32`` word, one bit per camera of a group of 32, and a node is visited
when any of the 32 visits it (:func:`traverse` with ``lanes_dtype=uint32``).
"""

from __future__ import annotations

import functools
import threading
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._bitsets import WORD, column_popcounts, unpack_cameras, weight_bits_for
from .._predicate import view_collapse_mask
from .._subtree import subtree_collapses
from .._units import camera_in_model_units
from .._view import View
from ._dense import gather
from ._tables import derived, table_columns


class FrontPlan:
    """The traversal's buffer capacities for one mesh content (grown when a
    view needs more; kept with its derived tables,
    :class:`pmjax.engines._tables.Derived`). A capacity only changes the
    cost: a call that overflowed a buffer is redone with full ones.

    Attributes:
        generation_sizes: pcols at each depth below a root, over the whole forest
            (the buffers that can never overflow).
    """

    # After a call, buffers hold GROWTH times what the views needed, rounded up
    # to a multiple of ROUND: few distinct shapes, so few compilations.
    GROWTH = 1.5
    ROUND = 64

    def __init__(self, generation_sizes):
        self.generation_sizes = tuple(int(g) for g in generation_sizes)
        self._capacities: dict = {}
        self._lock = threading.Lock()

    def capacities(self, kind) -> tuple:
        """Current capacities for a traversal kind (one camera or words of 32,
        per set of tests and projection): the whole forest's generations until
        a first call has measured what views need."""
        with self._lock:
            return self._capacities.get(kind, self.generation_sizes)

    def fit(self, kind, needed) -> tuple:
        """Grow the capacities of ``kind`` to hold ``needed`` (per generation,
        the most any view of a call needed) with room to spare."""
        with self._lock:
            old = self._capacities.get(kind, (0,) * len(self.generation_sizes))
            new = tuple(min(g, max(c, self._round(self.GROWTH * n), 1))
                        for g, c, n in zip(self.generation_sizes, old, needed))
            self._capacities[kind] = new
            return new

    def run(self, kind, call):
        """``call(capacities)`` with this kind's capacities; a call that
        overflowed one is redone with full buffers (exact). Either way the
        capacities then fit what was needed. ``call`` returns a tuple whose
        last element is ``needed`` (``[G]``, or ``[W, G]`` per word)."""
        capacities = self.capacities(kind)
        out = call(capacities)
        needed = np.asarray(out[-1]).reshape(-1, len(capacities)).max(0)
        if capacities != self.full and np.any(needed > np.asarray(capacities)):
            out = call(self.full)
            needed = np.asarray(out[-1]).reshape(-1, len(capacities)).max(0)
        if capacities == self.full or np.any(needed > np.asarray(capacities)):
            self.fit(kind, needed)
        return out

    @classmethod
    def _round(cls, n) -> int:
        return int(-(-int(np.ceil(n)) // cls.ROUND) * cls.ROUND)

    @property
    def full(self) -> tuple:
        return self.generation_sizes


_plans: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_plans_lock = threading.Lock()


def plan_of(d) -> FrontPlan:
    """The capacities kept for one mesh content (``Derived``)."""
    with _plans_lock:
        plan = _plans.get(d)
        if plan is None:
            plan = _plans[d] = FrontPlan(d.generation_sizes)
        return plan


BLOCK = 64


def prefix_count(flags):
    """Inclusive prefix sum of a bool vector, as ``int32``.

    Two small matrix products with triangular matrices of ones (exact in
    float32 below 2^24, at full precision: a GPU's default TF32 products
    would round counts above 1024): blocks of 64, then the blocks' totals. On the CPU,
    ``jnp.cumsum`` is a reduce-window, much slower, and an associative scan
    cost a dozen tiny kernels per call.
    """
    n = flags.shape[0]
    blocks = jnp.pad(flags.astype(jnp.float32), (0, -n % BLOCK)).reshape(-1, BLOCK)
    exact = jax.lax.Precision.HIGHEST
    within = jnp.matmul(blocks, jnp.triu(jnp.ones((BLOCK, BLOCK), jnp.float32)), precision=exact)
    totals = within[:, -1]
    before = jnp.matmul(totals, jnp.triu(jnp.ones((totals.shape[0],) * 2, jnp.float32), 1), precision=exact)
    return (within + before[:, None]).reshape(-1)[:n].astype(jnp.int32)


def traverse(jt, decide, capacities, lanes_dtype):
    """The top-down traversal and the bottom-up resolution (see module doc).

    Args:
        jt: :class:`pmjax.engines._tables.JaxTables`.
        decide: ``decide(attrs, bounds) -> (collapse, whole)`` for gathered
            pcols, each a ``lanes_dtype`` array ``[C]``: bool for one camera,
            ``uint32`` words for 32 cameras (bit ``c`` for camera ``c``).
        capacities: static buffer size per generation.
        lanes_dtype: ``bool`` or ``jnp.uint32``.

    Returns:
        ``(ids, executed, needed)``: ``ids int32[sum(capacities)]`` the visited
        pcols (``P`` in unused slots), ``executed`` their lanes (all set in
        unused slots and for cameras that did not visit a pcol: both are
        executed), ``needed int32[G]`` the pcols each generation had to hold.
    """
    P = jt.table.shape[0]
    none = jnp.zeros((), lanes_dtype)
    every = ~none
    # One camera: a pushed child is visited by it, so visits are the valid slots.
    single = lanes_dtype == bool

    def descend(g, ids, visits, count):
        """Evaluate generation ``g`` and push the children of the pcols it
        could not decide, compacted (prefix sum) into the next buffer."""
        cap = capacities[g]
        valid = jnp.arange(cap) < count
        visits = valid if single else jnp.where(valid, visits, none)
        collapse, whole = decide(*table_columns(gather(jt.table, ids).T))
        open_ = visits & ~whole
        kids = gather(jt.children, ids)
        c1, c2 = kids[:, 0], kids[:, 1]
        push = jnp.concatenate([(open_ != none) & (c1 >= 0), (open_ != none) & (c2 >= 0)])
        slot = prefix_count(push) - 1
        nxt = capacities[g + 1] if g + 1 < len(capacities) else 0
        target = jnp.where(push, slot, nxt)  # out of range: dropped
        next_ids = jnp.zeros(nxt, jnp.int32).at[target].set(jnp.concatenate([c1, c2]), mode="drop")
        next_visits = None if single else \
            jnp.zeros(nxt, lanes_dtype).at[target].set(jnp.concatenate([open_, open_]), mode="drop")
        # The last prefix count is the total (a sum here was a reduce-window).
        return (visits, collapse, whole, push, slot), (next_ids, next_visits, slot[-1] + 1)

    ids = jt.roots
    visits = None if single else jnp.full(ids.shape, every)
    count = jnp.int32(ids.shape[0])
    levels, needed = [], [count]
    # Top-down. A generation with nothing to visit (the deep ones, for most
    # views) is skipped by a conditional, which is also a boundary no fusion
    # crosses: XLA's CPU compiler would otherwise fuse the tests into each of
    # their three consumers and run them three to five times.
    for g in range(len(capacities)):
        run = functools.partial(descend, g)
        skip = lambda ids, visits, count, run=run: jax.tree.map(
            lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(run, ids, visits, count))
        state, (ids_next, visits_next, wanted) = jax.lax.cond(count > 0, run, skip, ids, visits, count)
        levels.append((ids, count) + state)
        if g + 1 == len(capacities):
            break
        needed.append(wanted)
        ids, visits, count = ids_next, visits_next, jnp.minimum(wanted, capacities[g + 1])
    # Bottom-up: a pcol runs if its subtree is decided, or it collapses and
    # both children ran (a child not pushed is original, or not open: ran).
    below = None
    out_ids, out_exec = [], []
    for ids, count, visits, collapse, whole, push, slot in reversed(levels):
        cap = ids.shape[0]
        if below is None:
            child_ran = jnp.full(2 * cap, every)
        else:
            # A child beyond the next buffer was dropped: the clip keeps the read
            # in range, and the call, which reports the overflow, is redone.
            child_ran = jnp.where(push, gather(below, jnp.clip(slot, 0, below.shape[0] - 1)), every)
        ran = ~visits | whole | (collapse & child_ran[:cap] & child_ran[cap:])
        below = ran
        out_ids.append(jnp.where(jnp.arange(cap) < count, ids, P))
        out_exec.append(ran)
    return jnp.concatenate(out_ids[::-1]), jnp.concatenate(out_exec[::-1]), jnp.stack(needed)


def one_camera_decide(view, tests):
    """``decide`` for :func:`traverse` with one camera's :class:`View`."""

    def decide(attrs, bounds):
        collapse = view_collapse_mask(attrs, view, tests, rows=False)
        return collapse, subtree_collapses(attrs.center, attrs.axis, bounds, view, tests)

    return decide


def front_counts(pm, visited, not_ran):
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
def refine_chunk(pm, jt, camera, tau, tests, capacities):
    tau = eqx.error_if(jnp.asarray(tau, jnp.float32), ~(tau >= 0), "tau must be >= 0 (and not NaN)")
    view = View.of(camera_in_model_units(camera, jt.exponent), tau)
    visited, ran, needed = traverse(jt, one_camera_decide(view, tests), capacities, bool)
    counts = front_counts(pm, visited, (visited < pm.n_pcols) & ~ran)
    return (visited, ran) + counts + (needed,)


def word_counts(pm, visited, ran):
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


def pack_word(mask):
    """One word of 32 cameras per column: bit ``c`` is ``mask[c]``. An
    unrolled OR of shifted rows, one elementwise loop (the reduction over
    the camera axis of :func:`pmjax._bitsets.pack_cameras` is slower on
    the front's gathered columns)."""
    word = mask[0].astype(jnp.uint32)
    for c in range(1, WORD):
        word = word | (mask[c].astype(jnp.uint32) << c)
    return word


def counts(pm, cameras, tau, tests, want_masks: bool, want_front=False):
    """Counts (and on request dense masks, or each word's front) of a chunk of
    cameras, 32 per word, through :func:`counts_chunk`; the buffers are grown
    and the chunk redone when a word needed more."""
    d = derived(pm)
    jt = d.jax
    out = plan_of(d).run(("word", tests, cameras.orthographic),
                     lambda capacities: counts_chunk(pm, jt, cameras, tau, tests, capacities, want_masks, want_front))
    return out[:-1]


def refine(pm, camera, tau, tests):
    """One camera: ``(visited, ran, n_faces, n_vertices, n_executed)``, the
    buffers grown and the call redone when a generation needed more."""
    d = derived(pm)
    jt = d.jax
    out = plan_of(d).run(("one", tests, camera.orthographic),
                     lambda capacities: refine_chunk(pm, jt, camera, tau, tests, capacities))
    return out[:-1]


@functools.partial(jax.jit, static_argnames=("tests", "capacities", "want_masks", "want_front"))
def counts_chunk(pm, jt, cameras, tau, tests, capacities, want_masks, want_front=False):
    """Per camera ``(faces, vertices, executed)``, then ``executed`` masks
    ``bool[K, P]`` if ``want_masks``, then, if ``want_front``, per word of 32
    cameras the visited pcols ``int32[W, C]`` and their executed words
    ``uint32[W, C]``, and last the buffers each word needed. ``tau``: a
    scalar or one per camera."""
    views = View.batch(camera_in_model_units(cameras, jt.exponent), tau)
    words = views.values.reshape(views.values.shape[0], -1, WORD)  # [22, W, 32]

    def one_word(values):
        group = View(values, cameras.orthographic)

        def decide(attrs, bounds):
            collapse = group.map(lambda v: view_collapse_mask(attrs, v, tests, rows=False))
            whole = group.map(lambda v: subtree_collapses(attrs.center, attrs.axis, bounds, v, tests))
            return pack_word(collapse), pack_word(whole)

        visited, ran, needed = traverse(jt, decide, capacities, jnp.uint32)
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


