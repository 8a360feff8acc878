"""Output-sensitive refinement: a top-down traversal that stops where a subtree is decided.

The dense engine tests every pcol. Here the forest of pcols is walked from its
roots, one generation (depth below a root) at a time. At each visited pcol two
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

import jax
import jax.numpy as jnp
import numpy as np

from ._model import PcolAttributes
from ._predicate import view_collapse_mask
from ._subtree import FrontBounds, subtree_collapses


def gather(values, indices):
    """``values[indices]`` for indices known to be in range: no wrapping of
    negative indices nor clamping (2x faster gathers on the CPU)."""
    return values.at[indices].get(mode="promise_in_bounds")


class FrontPlan:
    """Host-side, mutable companions of one :class:`ProgressiveMesh`: the
    traversal's buffer capacities (grown when a view needs more) and the host
    arrays the front mesh reads. Hashed by the forest's shape, so it can ride
    as a static field.

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
        self.host: dict = {}

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

    # Equal plans (same forest shape) share compiled kernels: the capacities a
    # kernel is compiled for are its own static argument.
    def __hash__(self):
        return hash(self.generation_sizes)

    def __eq__(self, other):
        return isinstance(other, FrontPlan) and self.generation_sizes == other.generation_sizes


def forest_generations(parent: np.ndarray, batch_offsets) -> tuple[np.ndarray, np.ndarray]:
    """Roots of the pcol forest and each pcol's depth below its root.

    Args:
        parent: ``[P]`` the pcol consuming each pcol's vertex, ``-1`` for none
            (``ProgressiveMesh.parent`` of the created vertices).

    Returns:
        ``(roots int32[R], depth int32[P])``; roots in increasing order.
    """
    depth = np.zeros(len(parent), np.int32)
    # Parents are in later batches: resolve from the last batch down.
    for lo, hi in reversed(list(zip(batch_offsets[:-1], batch_offsets[1:]))):
        up = parent[lo:hi]
        depth[lo:hi] = np.where(up >= 0, depth[np.maximum(up, 0)] + 1, 0)
    return np.flatnonzero(parent < 0).astype(np.int32), depth


# Columns of ProgressiveMesh.table: these attributes (center and axis three
# columns each), then these subtree bounds.
TABLE_ATTRIBUTES = ("center", "axis", "radius", "sin_alpha", "cos_alpha", "delta", "mu")
TABLE_BOUNDS = ("reach", "spread", "facing", "error", "axis_scale")


def _gathered(pm, ids):
    """The attributes and subtree bounds of pcols ``ids``, from one row each."""
    return table_columns(gather(pm.table, ids).T)


def table_columns(rows):
    """``(PcolAttributes, FrontBounds)`` of table rows as columns ``[16, C]``."""
    # Columns 0-2 centre, 3-5 axis, then one column per remaining attribute
    # (not alpha: the tests read its sine and cosine), then the bounds.
    scalars = {k: rows[4 + i] for i, k in enumerate(TABLE_ATTRIBUTES) if i >= 2}
    attrs = PcolAttributes(center=rows[0:3], axis=rows[3:6], alpha=None, **scalars)
    bounds = FrontBounds(**{k: rows[11 + i] for i, k in enumerate(TABLE_BOUNDS)})
    return attrs, bounds


BLOCK = 64


def prefix_count(flags):
    """Inclusive prefix sum of a bool vector, as ``int32``.

    Two small matrix products with triangular matrices of ones (exact in
    float32 below 2^24, at full precision: a GPU's default TF32 products
    would round counts above 1024): blocks of 64, then the blocks' totals. On the CPU,
    ``jnp.cumsum`` (a reduce-window) ran 3x slower, and an associative scan
    cost a dozen tiny kernels per call.
    """
    n = flags.shape[0]
    blocks = jnp.pad(flags.astype(jnp.float32), (0, -n % BLOCK)).reshape(-1, BLOCK)
    exact = jax.lax.Precision.HIGHEST
    within = jnp.matmul(blocks, jnp.triu(jnp.ones((BLOCK, BLOCK), jnp.float32)), precision=exact)
    totals = within[:, -1]
    before = jnp.matmul(totals, jnp.triu(jnp.ones((totals.shape[0],) * 2, jnp.float32), 1), precision=exact)
    return (within + before[:, None]).reshape(-1)[:n].astype(jnp.int32)


def traverse(pm, decide, capacities, lanes_dtype):
    """The top-down traversal and the bottom-up resolution (see module doc).

    Args:
        pm: :class:`ProgressiveMesh`.
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
    P = pm.n_pcols
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
        collapse, whole = decide(*_gathered(pm, ids))
        open_ = visits & ~whole
        kids = gather(pm.children, ids)
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

    ids = pm.roots
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

    def decide(attrs: PcolAttributes, bounds: FrontBounds):
        collapse = view_collapse_mask(attrs, view, tests, rows=False)
        return collapse, subtree_collapses(attrs.center, attrs.axis, bounds, view, tests)

    return decide
