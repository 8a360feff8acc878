"""What the front engines derive from a progressive mesh, as functions of its arrays.

The front engines read tables that the mesh's own arrays do not hold: the
bounds over each pcol's subtree (:mod:`pmjax._subtree`), the forest laid out
breadth first for the C core, one row per pcol, and the front mesh's records.
They are computed on the host from the mesh's arrays and cached under a
digest of those arrays (:mod:`pmjax.engines._content`): a mesh whose
positions, normals or attributes were updated (``eqx.tree_at``, arithmetic)
has another digest and gets its own tables, never stale ones.

Only a mesh whose arrays are known can have tables: a mesh being traced
(passed as an argument of a ``jit``-compiled function) is refined by the dense
engine (:func:`pmjax.engines.select`).
"""

from __future__ import annotations

import collections
import threading
import weakref

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float, Int

from .._model import PcolAttributes
from .._units import host_lengths_in_model_units, unit_exponent
from .._subtree import FrontBounds, below_bounds, front_bounds, subtree_bounds
from . import _content
from ._front_mesh import CoreMesh, core_records, depth_first

# Columns of a table row: these attributes (centre and axis three columns
# each), then these bounds. The C core's rows hold the bounds over the pcols
# strictly below each pcol and, in the last column, the children's link
# (KIDS, pmjax/engines/core/internal.h); the JAX engine's the bounds over the
# whole subtree and 1 / |axis|.
TABLE_ATTRIBUTES = ("center", "axis", "radius", "sin_alpha", "cos_alpha", "delta", "mu")
TABLE_BOUNDS = ("reach", "spread", "facing", "error", "axis_scale")
ROW = 16

# Meshes whose tables are kept (most recently used first out).
CACHE_SIZE = 4


class CoreTables(eqx.Module):
    """The hierarchy as the C core reads it (``PmxHierarchy`` in
    ``pmjax/engines/core/pmx.h``): the pcol forest breadth first, position
    ``q`` holding pcol ``order[q]``, the roots first.

    Attributes:
        rows: ``float32 [P, 16]`` per position its attributes, the bounds over
            the pcols strictly below it, and its children's link (int32 bits).
        kills: ``int32 [P]`` faces each position's pcol kills.
        order: ``int32 [P]`` the pcol at each position.
        n_roots: static, the roots (positions ``0 .. n_roots - 1``).
        exponent: static, the model unit ``2^exponent`` of the lengths
            (:mod:`pmjax._units`); cameras are brought to it before they meet
            the rows.
    """

    rows: Float[Array, "P 16"]
    kills: Int[Array, " P"]
    order: Int[Array, " P"]
    n_roots: int = eqx.field(static=True)
    exponent: int = eqx.field(static=True, default=0)

    @property
    def n_pcols(self) -> int:
        return int(self.rows.shape[0])


class JaxTables(eqx.Module):
    """The hierarchy as the front engine's JAX kernels read it
    (:mod:`pmjax.engines._front_jax`).

    Attributes:
        table: ``float32 [P, 16]`` per pcol its attributes and the bounds over
            its subtree (columns ``TABLE_ATTRIBUTES``, then ``TABLE_BOUNDS``).
        children: ``int32 [P, 2]`` the pcols that made each endpoint (-1: original).
        roots: ``int32 [R]`` the pcols no pcol consumes.
        kills: ``int32 [P]``.
        exponent: static, the model unit (as :class:`CoreTables`).
    """

    table: Float[Array, "P 16"]
    children: Int[Array, "P 2"]
    roots: Int[Array, " R"]
    kills: Int[Array, " P"]
    exponent: int = eqx.field(static=True, default=0)


def device(x: np.ndarray) -> jax.Array:
    """A table on the default device: a concrete array even when made while
    a function is being traced (the table outlives the trace)."""
    with jax.ensure_compile_time_eval():
        return jax.device_put(np.ascontiguousarray(x))


def source_arrays(pm) -> tuple:
    """The arrays of ``pm`` the derived tables depend on, in a fixed order."""
    a = pm.attributes
    return (pm.vertices, pm.faces, pm.child1, pm.child2, pm.parent, pm.killer, pm.kills, a.center, a.axis,
            a.radius, a.alpha, a.sin_alpha, a.cos_alpha, a.delta, a.mu)


def has_contents(pm) -> bool:
    """Whether ``pm``'s arrays are known (not traced), so tables can be derived."""
    return not any(_content.is_traced(x) for x in source_arrays(pm))


class Derived:
    """The tables of one mesh content, each made when first asked for.

    Attributes:
        bounds: the :func:`pmjax._subtree.subtree_bounds` of the pcols (host).
        plan: the JAX front engine's buffer capacities
            (:class:`pmjax.engines._front_jax.FrontPlan`).
    """

    def __init__(self, pm):
        self.n_original, self.n_pcols, self.n_faces = pm.n_original_vertices, pm.n_pcols, pm.n_faces
        self.batch_offsets = pm.batch_offsets
        host = {k: np.asarray(v) for k, v in zip(_SOURCE_NAMES, source_arrays(pm))}
        # Every table holds the attributes in model units (pmjax._units).
        self.exponent = unit_exponent(host["radius"])
        self._host = host_lengths_in_model_units(host, self.exponent)
        self._lock = threading.RLock()
        self._made: dict = {}

    def _once(self, name, make):
        made = self._made.get(name)  # a dict read is atomic: no lock once made
        if made is not None:
            return made
        with self._lock:
            if name not in self._made:
                self._made[name] = make()
            return self._made[name]

    def memo(self, name: str, make):
        """``make()`` once per mesh content (for callers' own derived values)."""
        return self._once(("memo", name), make)

    @property
    def total_kills(self) -> int:
        """Faces all pcols together remove."""
        return self._once("total_kills", lambda: int(self._host["kills"].sum(dtype=np.int64)))

    @property
    def bounds(self) -> dict:
        h = self._host
        return self._once("bounds", lambda: subtree_bounds(
            h["center"].T, h["axis"].T, h["radius"], h["sin_alpha"], h["cos_alpha"], h["delta"], h["mu"],
            h["child1"], h["child2"], self.batch_offsets))

    def seed_bounds(self, bounds: dict) -> None:
        """Bounds computed elsewhere from the same arrays (``pmjax.load`` runs
        the pass once, checking the attributes' nesting on the way)."""
        with self._lock:
            self._made.setdefault("bounds", bounds)

    @property
    def children(self) -> np.ndarray:
        """``int32 [P, 2]``: the pcols that made each pcol's endpoints (-1: original)."""
        return self._once("children", lambda: np.stack([self._host["child1"], self._host["child2"]], 1).astype(np.int32))

    @property
    def roots(self) -> np.ndarray:
        """The pcols no pcol consumes, in increasing order."""
        return self._once("roots", lambda: np.flatnonzero(self._host["parent"][self.n_original:] < 0).astype(np.int32))

    @property
    def generation_sizes(self) -> np.ndarray:
        """Pcols at each depth below a root."""
        def make():
            parent = self._host["parent"][self.n_original:]
            depth = np.zeros(self.n_pcols, np.int32)
            offsets = self.batch_offsets
            # Parents are in later batches: resolved from the last batch down.
            for lo, hi in reversed(list(zip(offsets[:-1], offsets[1:]))):
                up = parent[lo:hi]
                depth[lo:hi] = np.where(up >= 0, depth[np.maximum(up, 0)] + 1, 0)
            return np.bincount(depth, minlength=1) if self.n_pcols else np.zeros(0, np.int64)
        return self._once("generations", make)

    def _attribute_columns(self) -> list:
        h = self._host
        return [h["center"], h["axis"]] + [h[k].reshape(1, -1) for k in TABLE_ATTRIBUTES[2:]]

    @property
    def jax(self) -> JaxTables:
        def make():
            rows = front_bounds(self.bounds, self._host["axis"])
            table = np.concatenate(self._attribute_columns() + [rows[k].reshape(1, -1) for k in TABLE_BOUNDS]).T
            return JaxTables(table=device(np.asarray(table, np.float32)), children=device(self.children),
                             roots=device(self.roots), kills=device(np.asarray(self._host["kills"], np.int32)),
                             exponent=self.exponent)
        return self._once("jax", make)

    @property
    def layout(self) -> dict:
        """The breadth-first layout: ``order`` (pcol at each position),
        ``first`` (each position's first child's position), ``count`` (its
        created children)."""
        def make():
            children = self.children
            level, order, first, count = self.roots.astype(np.int64), [], [], []
            placed = 0
            while len(level):
                order.append(level)
                kids = children[level]
                n_kids = (kids >= 0).sum(1)
                placed += len(level)
                first.append(placed + np.concatenate([[0], np.cumsum(n_kids)[:-1]]))
                count.append(n_kids)
                level = kids.reshape(-1)[kids.reshape(-1) >= 0].astype(np.int64)
            cat = lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.int64)
            order, first, count = cat(order), cat(first), cat(count)
            if len(order) != self.n_pcols:  # every pcol lies below a root (the structure check's forest)
                raise ValueError(f"the pcol forest reaches {len(order)} of {self.n_pcols} pcols from its roots")
            if self.n_pcols >= 1 << 29:
                raise ValueError(f"{self.n_pcols} pcols: the C core holds positions below 2^29")
            return dict(order=order.astype(np.int32), first=first, count=count)
        return self._once("layout", make)

    def _core(self, bounds: dict) -> CoreTables:
        h, lay = self._host, self.layout
        order = lay["order"]
        rows = front_bounds(bounds, h["axis"])
        table = np.concatenate(self._attribute_columns() + [rows[k].reshape(1, -1) for k in TABLE_BOUNDS]).T
        rows = np.ascontiguousarray(table[order], np.float32)
        kills = np.ascontiguousarray(h["kills"][order], np.int32)
        # The last column (1 / |axis|, which the core does not read): the
        # first child's position << 2 | the number of created children, and
        # in the sign bit whether the pcol kills other than two faces.
        kids = (lay["first"] << 2) | lay["count"] | (kills != 2).astype(np.int64) << 31
        rows[:, -1] = kids.astype(np.uint32).view(np.float32)
        return CoreTables(rows=device(rows), kills=device(kills), order=device(order),
                          n_roots=len(self.roots), exponent=self.exponent)

    @property
    def core(self) -> CoreTables:
        """The core's tables for one camera at a time: each row's bounds over
        the pcols strictly below it (a pcol whose children all collapse is
        decided by its own test, its children not visited)."""
        h = self._host
        return self._once("core", lambda: self._core(below_bounds(h["center"].T, h["axis"].T, self.bounds,
                                                                  h["child1"], h["child2"])))

    @property
    def core_words(self) -> CoreTables:
        """The core's tables for words of frames: each row's bounds over its
        whole subtree (a frame whose bound holds at a pcol has it run)."""
        return self._once("core_words", lambda: self._core(self.bounds))

    @property
    def depth_first(self) -> dict:
        """The depth-first numbering of the forest's original vertices and the
        front mesh's host arrays (:mod:`pmjax.engines._front_mesh`)."""
        return self._once("depth_first", lambda: depth_first(self._host, self.children, self.roots,
                                                             self.n_original, self.batch_offsets))

    @property
    def core_mesh(self) -> CoreMesh:
        """The C core's front-mesh records."""
        return self._once("core_mesh", lambda: core_records(self.depth_first, self._host, self.layout["order"],
                                                            self.n_original, self.n_faces))


_SOURCE_NAMES = ("vertices", "faces", "child1", "child2", "parent", "killer", "kills", "center", "axis", "radius",
                 "alpha", "sin_alpha", "cos_alpha", "delta", "mu")

_cache: collections.OrderedDict = collections.OrderedDict()
_cache_lock = threading.Lock()
# The last mesh object asked for, and its tables: a call on the same object
# (whose arrays are immutable JAX arrays) skips the digests.
_last = (None, None)


def derived(pm) -> Derived:
    """The derived tables of ``pm``'s contents (cached; ``ValueError`` for a
    mesh being traced)."""
    global _last
    ref, tables = _last
    if ref is not None and ref() is pm:
        return tables
    arrays = source_arrays(pm)
    key = _content.key(*arrays, static=(pm.batch_offsets, pm.n_original_vertices))
    with _cache_lock:
        tables = _cache.get(key)
        if tables is None:
            tables = _cache[key] = Derived(pm)
            while len(_cache) > CACHE_SIZE:
                _cache.popitem(last=False)
        _cache.move_to_end(key)
    # Only a mesh of immutable arrays may be remembered by identity.
    if all(isinstance(x, jax.Array) for x in arrays):
        _last = (weakref.ref(pm), tables)
    return tables


def table_columns(rows):
    """``(PcolAttributes, FrontBounds)`` of table rows as columns ``[16, C]``
    (the attributes' columns are the same in every table; the bounds' are
    those of the table's kind)."""
    # Columns 0-2 centre, 3-5 axis, then one column per remaining attribute
    # (not alpha: the tests read its sine and cosine), then the bounds.
    scalars = {k: rows[4 + i] for i, k in enumerate(TABLE_ATTRIBUTES) if i >= 2}
    attrs = PcolAttributes(center=rows[0:3], axis=rows[3:6], alpha=None, **scalars)
    bounds = FrontBounds(**{k: rows[11 + i] for i, k in enumerate(TABLE_BOUNDS)})
    return attrs, bounds
