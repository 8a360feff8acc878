"""View-dependent refinement for one camera or many: the public calls in front of the engines.

``executed(p) = collapse(p) and exists(v1) and exists(v2)`` (docs/design.md).
Each call asks :func:`pmjax.engines.select` which engine runs it (the dense
JAX kernels, the front engine's C core as XLA FFI calls, or the front engine
as JAX kernels); all give the same bits. Every call here is a JAX function:
eager, under ``jax.jit`` and under ``jax.vmap`` (over cameras and
tolerances), with the mesh closed over (front engine) or traced (dense).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Int

from ._arguments import check_camera, check_mesh
from ._scalars import host_scalar
from ._bitsets import WORD
from ._camera import Camera, camera_count
from ._model import ProgressiveMesh
from ._predicate import ALL_TESTS, Tests, UserPredicate
from .engines import _core, _dense, _front_jax
from .engines._choose import FRONT_FROM_PCOLS, is_traced, select
from .engines._dense import DenseRefinement, critical_tolerances, propagate, representatives
from .engines._front_mesh import numpy_mesh
from .engines._tables import derived

__all__ = ["Refinement", "critical_tolerances", "faces_for_budget", "faces_for_budget_batch", "propagate", "refine",
           "refine_batch", "representatives"]


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["pm", "visited", "visited_executed", "dense", "n_faces", "n_vertices", "n_executed",
                                "front_positions", "core_ran", "core_counts", "core_item", "n_slots"],
                   meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Refinement:
    """The result of refining a progressive mesh for one view.

    An immutable pytree (a frozen dataclass registered with JAX): it is made
    and read on the host once per view, where an ``equinox.Module``'s
    construction checks and bound methods cost more than a small refine.

    The front engines keep only the pcols their traversal visited and
    whether each ran; every other pcol lies under a decided subtree and ran.
    The full arrays (``executed``, ``active``, ``rep``) are computed from that
    when asked; the dense engine computes them eagerly.

    Attributes:
        pm: the :class:`ProgressiveMesh` refined (shared, not copied).
        visited: ``int32[C]`` pcols the traversal visited, ``P`` in unused slots
            (``None`` from the dense engine). Eagerly, NumPy arrays of the
            visited pcols; under ``jit``, capacity ``P + 16``.
        visited_executed: ``bool[C]`` whether each ran (``True`` in unused slots).
        dense: :class:`DenseRefinement` from the dense engine, else ``None``.
        n_faces, n_vertices, n_executed: counts (``n_vertices`` = V0 − executed,
            the vertex front).
        front_positions, core_ran, core_counts, core_item, n_slots: what
            the C core's mesh reads (``None`` from the other engines): the
            visited pcols' places in its breadth-first layout and whether
            each ran (``[L]`` uint8: eagerly NumPy arrays of exactly the
            slots used, under ``jit`` the core's capacity ``P + 16``; or a
            path's ``[W, L]`` frame bits, shared by its frames), the core's
            counts (``[4]``, or a path's ``[W * 16, 4]``, row ``core_item``
            being this refinement's) and the slots used.
    """

    pm: ProgressiveMesh
    visited: Optional[Int[Array, " C"]]
    visited_executed: Optional[Bool[Array, " C"]]
    dense: Optional[DenseRefinement]
    n_faces: Int[Array, ""]
    n_vertices: Int[Array, ""]
    n_executed: Int[Array, ""]
    front_positions: Optional[Int[Array, " C"]] = None
    core_ran: Optional[Array] = None
    core_counts: Optional[Int[Array, "*M 4"]] = None
    core_item: Optional[Int[Array, ""]] = None
    n_slots: Optional[Int[Array, ""]] = None

    def __getattr__(self, name):
        # A frame of a path made by its word's lists (pmjax._path) holds
        # its ran bits as the word's bit rows and its lane ("_lane": bits,
        # slots, bit) until visited_executed is first read: most frames'
        # readers never read it, and the word's bits are already held.
        lane = self.__dict__.get("_lane") if name == "visited_executed" else None
        if lane is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        bits, m, bit = lane
        value = (bits[:m] & (1 << bit)) != 0
        self.__dict__["visited_executed"] = value
        return value

    @property
    def executed(self) -> Bool[Array, " P"]:
        """``bool[P]`` pcols executed."""
        if self.dense is not None:
            return self.dense.executed
        if isinstance(self.visited, np.ndarray):  # host lists (C core, paths): no compile per length
            out = np.ones(self.pm.n_pcols, bool)
            keep = self.visited < self.pm.n_pcols
            out[self.visited[keep]] = np.asarray(self.visited_executed)[keep]
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
    def n_visited(self):
        """Pcols whose decision the engine looked at (``P`` for the dense engine)."""
        if self.visited is None:
            return self.pm.n_pcols
        if self.n_slots is not None:
            return self.n_slots if is_traced(self.n_slots) else int(self.n_slots)
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
            drawn. Under ``jit`` the arrays have fixed capacities
            (``[V0, 3]``, ``[F, 3]``, ``[V0]``): rows past the ``n_faces``
            faces hold -1, and past the vertices used, ids -1 and zero
            positions.
        """
        if pm is not None and pm is not self.pm and (pm.n_pcols, pm.n_faces, pm.n_original_vertices) != (
                self.pm.n_pcols, self.pm.n_faces, self.pm.n_original_vertices):
            raise ValueError("Refinement.mesh: pm is not the mesh this refinement was made for "
                             f"({pm.n_pcols} pcols, {pm.n_faces} faces; refined: {self.pm.n_pcols}, {self.pm.n_faces})")
        traced = is_traced(self.n_faces, self.visited, self.dense)
        if self.dense is not None:
            if traced:
                return _padded(*_dense_mesh(self.pm, self.dense))
            active = np.asarray(self.dense.active)
            faces = np.asarray(self.dense.rep)[np.asarray(self.pm.faces)[active]]
            ids, inverse = np.unique(faces, return_inverse=True)
            return np.asarray(self.pm.vertices)[ids], inverse.reshape(-1, 3).astype(np.int32), ids.astype(np.int32)
        if self.core_ran is not None:
            if traced:
                faces, ids, vertices, n_ids = _core_mesh(derived(self.pm).core_mesh, self.core_ran,
                                                         self.front_positions, self.core_counts, self.core_item)
                return _padded(vertices, faces, ids, self.n_faces, n_ids)
            return _core_mesh_eager(self.pm, self.core_ran, self.front_positions, self.core_counts,
                                    self.core_item, int(self.n_faces), int(self.n_vertices))
        return numpy_mesh(derived(self.pm).depth_first, self.pm.n_pcols, np.asarray(self.visited),
                          np.asarray(self.visited_executed))

    def to_trimesh(self, pm: Optional[ProgressiveMesh] = None):
        """The refined mesh as a ``trimesh.Trimesh`` (not processed)."""
        import trimesh

        v, f, _ = self.mesh(pm)
        return trimesh.Trimesh(v, f, process=False)


@jax.jit
def _padded(vertices, faces, ids, n_faces, n_ids):
    """A mesh in fixed-capacity arrays, the rows past the counts cleared."""
    face_rows = jnp.arange(faces.shape[0])[:, None] < n_faces
    vertex_rows = jnp.arange(ids.shape[0]) < n_ids
    return (jnp.where(vertex_rows[:, None], vertices, 0), jnp.where(face_rows, faces, -1),
            jnp.where(vertex_rows, ids, -1))


_dense_mesh = jax.jit(_dense.mesh)


def _core_mesh_eager(pm, ran, positions, counts, item, n_faces: int, n_vertices: int):
    """The core's mesh of an eager refinement as NumPy arrays, from the core
    called directly (``_pmx.front_mesh``): faces of exactly the refinement's
    rows, vertices and ids shrunk in place to those it uses."""
    d = derived(pm)
    tables, V0, F = d.memo("core_mesh_host", lambda: _mesh_host(d.core_mesh))
    faces = np.empty((n_faces, 3), np.int32)
    ids, vertices = np.empty(n_vertices, np.int32), np.empty((n_vertices, 3), np.float32)
    k = _core.front_mesh_eager(tables, ran, positions, counts, 0 if item is None else item, V0, F, faces, ids,
                               vertices)
    ids.resize((k,), refcheck=False)  # the arrays are this call's own
    vertices.resize((k, 3), refcheck=False)
    return vertices, faces, ids


def _mesh_host(mesh) -> tuple:
    """The front mesh's records as NumPy arrays, and the mesh's sizes."""
    records = (mesh.pcols, mesh.kill_data, mesh.base, mesh.tops, mesh.top_at)
    return tuple(np.asarray(a) for a in records), mesh.n_original, mesh.n_faces


@functools.partial(jax.jit, static_argnames=("n_original", "n_faces"))
def _core_mesh_arrays(pcols, kill_data, base, tops, top_at, ran, positions, counts, item, n_original, n_faces):
    mesh = _core.CoreMesh(pcols, kill_data, base, tops, top_at, n_original, n_faces)
    return _core.front_mesh(mesh, ran, positions, counts, 0 if item is None else item)


def _core_mesh(mesh, ran, positions, counts, item=None):
    """The core's mesh of a traced refinement (jitted; the tables passed as
    arrays; whole-mesh buffers)."""
    return _core_mesh_arrays(mesh.pcols, mesh.kill_data, mesh.base, mesh.tops, mesh.top_at, ran, positions, counts,
                             item, mesh.n_original, mesh.n_faces)


@functools.partial(jax.jit, static_argnums=2)
def _spread_executed(visited, visited_executed, n_pcols):
    # Unused slots hold P: dropped.
    return jnp.ones(n_pcols, bool).at[visited].set(visited_executed, mode="drop")


_active_faces = _dense._active_faces
_representatives = _dense._representatives


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


def _host_tau(tau, call: str = "refine"):
    """A host scalar tau as float32 (a new value does not recompile), checked;
    a traced tau is passed on and checked inside the compiled call."""
    if isinstance(tau, jax.core.Tracer):
        return tau
    if isinstance(tau, jax.Array):
        tau = np.asarray(tau)  # concrete: checked here, not inside the compiled call
    tau = host_scalar(tau, "tau", call)
    check_tau(tau)
    return tau


def _checked_tau(tau):
    """``tau`` as float32 with a NaN or negative value refused inside the
    compiled call (``eqx.error_if``)."""
    tau = jnp.asarray(tau, jnp.float32)
    return eqx.error_if(tau, ~(tau >= 0), "tau must be >= 0 (and not NaN)")


class _Counts:
    """The constants that turn the front engine's counts (pcols that did not
    run, the faces they keep) into face, vertex and executed counts."""

    def __init__(self, d):
        self.P, self.F, self.V0 = d.n_pcols, d.n_faces, d.n_original
        self.base_faces = self.F - d.total_kills

    @staticmethod
    def of(pm) -> "_Counts":
        d = derived(pm)
        return d.memo("counts", lambda: _Counts(d))

    def __call__(self, not_run, kept, xp=jnp):
        n_exec = self.P - not_run
        return (xp.asarray(self.base_faces + kept, xp.int32), xp.asarray(self.V0 - n_exec, xp.int32),
                xp.asarray(n_exec, xp.int32))


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
            by subtree bounds (cost ∝ the pcols near the front; the C core
            where it is built, else JAX kernels); ``"dense"``: every pcol
            tested and propagated (the reference); ``"auto"`` (default): the
            front engine where it is faster (docs/front.md), the dense engine
            with a user predicate, on a GPU, and for a mesh being traced.
            All give the same bits (:func:`pmjax.engines.select` decides).

    Returns:
        :class:`Refinement`. Under ``jax.jit`` and ``jax.vmap`` (over cameras
        and tolerances) it holds traced arrays; ``vmap`` of the front engine
        is one batched call into its core.
    """
    check_mesh(pm, "refine")
    check_camera(camera, "refine", batch=False)
    tau = _host_tau(tau)
    traced = is_traced(camera, tau)
    engine = select(pm, method, predicate=predicate, traced=traced)
    if engine == "core":
        return _refine_core(pm, camera, tau, tests, traced)
    if engine == "jax":
        visited, ran, n_faces, n_vertices, n_executed = _front_jax.refine(pm, camera, tau, tests)
        return Refinement(pm=pm, visited=visited, visited_executed=ran, dense=None, n_faces=n_faces,
                          n_vertices=n_vertices, n_executed=n_executed)
    # As under eqx.filter_jit, the context's arrays are traced and its other
    # leaves (Python numbers, strings) are static.
    if context is None or eqx.is_array(context):  # the common cases, without the partition's cost
        arrays, others = context, _dense._NOTHING_STATIC
    else:
        arrays, others = eqx.partition(context, eqx.is_array)
        others = _dense._Static(others)
    dense, n_faces, n_vertices, n_executed = _dense.refine(pm, camera, tau, arrays, others, tests, predicate, combine)
    return Refinement(pm=pm, visited=None, visited_executed=None, dense=dense, n_faces=n_faces,
                      n_vertices=n_vertices, n_executed=n_executed)


def _test_flags(tests: Tests) -> tuple:
    """A :class:`Tests` as a tuple: a static argument hashed in C++ at each
    call, where a module is hashed in Python."""
    if tests is ALL_TESTS:
        return _ALL_FLAGS
    return bool(tests.frustum), bool(tests.orientation), bool(tests.screen)


_ALL_FLAGS = (True, True, True)


@functools.partial(jax.jit, static_argnames=("n_roots", "exponent", "tests", "lists", "check"))
def _core_one_arrays(rows, kills, order, camera, tau, n_roots, exponent, tests, lists, check):
    tau = _checked_tau(tau) if check else tau
    tables = _core.CoreTables(rows=rows, kills=kills, order=order, n_roots=n_roots, exponent=exponent)
    return _core.one_camera(Tests(*tests), camera.orthographic, lists)(tables, _core.camera_rows(camera, tau, exponent))


def _core_one(tables, camera, tau, tests, lists, check):
    """One camera through the core (jitted; the tables passed as arrays)."""
    return _core_one_arrays(tables.rows, tables.kills, tables.order, camera, tau, tables.n_roots, tables.exponent,
                            _test_flags(tests), lists, check)


def _core_one_eager(d, camera, tau, tests):
    """:func:`_core_one` with lists, eagerly (``_core.refine_one_eager``):
    NumPy lists ``[P + 16]`` and counts."""
    host, n_roots = d.memo("core_host", lambda: (tuple(np.asarray(a) for a in (d.core.rows, d.core.kills,
                                                                                d.core.order)), d.core.n_roots))
    return _core.refine_one_eager(d.core, host, n_roots, _core.eager_camera_row(camera, tau, d.exponent), tests,
                                  vars(camera)["orthographic"])


def _refine_core(pm, camera, tau, tests, traced: bool) -> Refinement:
    d = derived(pm)
    counts_of = _Counts.of(pm)
    P = counts_of.P
    if not traced:  # tau was checked on the host
        pcols, ran, positions, counts = _core_one_eager(d, camera, tau, tests)
        n, not_run, kept = counts[:3].tolist()
        n_exec = P - not_run
        # The call's P + 16 buffers shrunk in place to the slots visited: a
        # refinement kept holds what it visited, and nothing is copied.
        for lst in (pcols, ran, positions):
            lst.resize((n,), refcheck=False)  # the arrays are this call's own
        return Refinement(pm=pm, visited=pcols, visited_executed=ran.view(bool),
                          dense=None, n_faces=np.int32(counts_of.base_faces + kept),
                          n_vertices=np.int32(counts_of.V0 - n_exec), n_executed=np.int32(n_exec),
                          front_positions=positions, core_ran=ran, core_counts=counts[:4], n_slots=np.int32(n))
    # Traced: the counts from a call without lists, the lists from one with
    # them; XLA drops whichever the caller does not use.
    tables = d.core
    counts = _core_one(tables, camera, tau, tests, False, True)[3]
    pcols, ran, positions, listed = _core_one(tables, camera, tau, tests, True, True)
    n = listed[..., 0]
    valid = jnp.arange(pcols.shape[-1]) < n[..., None]
    n_faces, n_vertices, n_executed = counts_of(counts[..., 1], counts[..., 2])
    return Refinement(pm=pm, visited=jnp.where(valid, pcols, P), visited_executed=jnp.where(valid, ran != 0, True),
                      dense=None, n_faces=n_faces, n_vertices=n_vertices, n_executed=n_executed,
                      front_positions=positions, core_ran=ran, core_counts=listed, n_slots=n)


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
    """Refine for K cameras at once, ``chunk`` cameras per call so memory stays
    bounded for any K.

    Args:
        pm: :class:`ProgressiveMesh`.
        cameras: a camera batch (leading axis K).
        tau: tolerance in pixels (shared by all cameras).
        tests: :class:`Tests` (which of the three tests to apply).
        predicate, context, combine: optional user test, as :func:`refine`
            (:func:`pmjax.collapse_mask`); a user test runs on the dense
            engine.
        chunk: cameras per call, rounded up to a multiple of 32 (one bitset
            word); the last chunk is padded.
        return_masks: also return ``executed`` masks ``bool[K, P]``.
        progress: a progress bar over the chunks.
        method: ``"dense"``, ``"front"`` (each camera traversed by the C core,
            the cameras shared by its threads; as JAX kernels where the core
            is not built, per group of 32 cameras the union of their fronts)
            or ``"auto"``: the core from ``FRONT_BATCH_FROM_PCOLS`` pcols on,
            else dense (docs/front.md). Same results.

    Returns:
        dict ``faces``, ``vertices``, ``executed_count`` (``int32[K]``) and, on
        request, ``executed`` (``bool[K, P]``): NumPy arrays, or JAX arrays
        under ``jit`` (the whole batch in one call).
    """
    check_mesh(pm, "refine_batch")
    K = check_camera(cameras, "refine_batch", batch=True)
    traced = is_traced(cameras, tau)
    if not traced:
        if isinstance(tau, jax.Array):
            tau = np.asarray(tau)  # concrete: checked here as a host value
        tau = check_tau(host_scalar(tau, "tau (one for all cameras)", "refine_batch"))
    engine = select(pm, method, predicate=predicate, batch=True, traced=traced)
    if traced:
        return _refine_batch_traced(pm, cameras, tau, tests, predicate, context, combine, return_masks, engine)
    chunk = -(-max(1, min(int(chunk), K)) // WORD) * WORD
    outs = []
    starts = range(0, K, chunk)
    if progress:
        from tqdm import tqdm

        starts = tqdm(starts, unit="chunk", desc="refine")
    # The front engines take nearby cameras together (their fronts share
    # cache lines): chunks of cameras close in space. Results go back to the caller's order.
    order = nearby_order(np.asarray(cameras.eye)) if engine != "dense" else np.arange(K)
    # Chunks are cut on the host (one transfer of the batch, then NumPy
    # indexing: slicing device arrays costs a dispatch per field and chunk),
    # and their results are read only after every chunk is dispatched, so
    # cutting overlaps computing.
    host = jax.tree.map(np.asarray, cameras)
    counts_of = _Counts.of(pm) if engine == "core" else None
    exponent = derived(pm).exponent if engine == "core" else 0
    taus = np.full(chunk, tau, np.float32)
    for s in starts:
        idx = order[np.minimum(np.arange(s, s + chunk), K - 1)]  # pad by repeating the last
        part = jax.tree.map(lambda a: a[idx], host)
        if engine == "core":
            res = _core_many(derived(pm).core, _core.host_camera_rows(part, taus, exponent), tests,
                             cameras.orthographic, return_masks)
        elif engine == "jax":
            res = _front_jax.counts(pm, part, np.float32(tau), tests, return_masks)
        else:
            res = _dense.counts_chunk(pm, part, jnp.float32(tau), tests, predicate, context, combine, return_masks)
        outs.append((res, min(chunk, K - s)))
    columns = []
    for res, n in outs:
        if engine == "core":
            counts = np.asarray(res[0])[:n]
            cols = list(counts_of(counts[:, 1], counts[:, 2], np))
            if return_masks:
                cols.append(np.asarray(res[1])[:n].view(bool))
        else:
            cols = [np.asarray(r)[:n] for r in res]
        columns.append(cols)
    cols = [np.empty_like(c) for c in (np.concatenate(c) for c in zip(*columns))]
    for col, parts in zip(cols, zip(*columns)):
        col[order] = np.concatenate(parts)
    out = dict(faces=cols[0], vertices=cols[1], executed_count=cols[2])
    if return_masks:
        out["executed"] = cols[3]
    return out


@functools.partial(jax.jit, static_argnames=("tests", "orthographic", "masks"))
def _core_many(tables, camera_rows, tests, orthographic, masks):
    counts, mask, _ = _core.many_cameras(tests, orthographic, masks, False)(tables, camera_rows)
    return counts, mask


def _refine_batch_traced(pm, cameras, tau, tests, predicate, context, combine, return_masks, engine):
    """The whole batch in one call of the engine (under ``jit``)."""
    K = camera_count(cameras)
    tau = _checked_tau(tau)
    if engine == "core":
        tables = derived(pm).core
        rows = _core.camera_rows(cameras, jnp.broadcast_to(tau, (K,)), tables.exponent)
        counts, masks = _core_many(tables, rows, tests, cameras.orthographic, return_masks)
        out = dict(zip(("faces", "vertices", "executed_count"), _Counts.of(pm)(counts[:, 1], counts[:, 2])))
        if return_masks:
            out["executed"] = masks.astype(bool)
        return out
    # The dense engine packs 32 cameras per word: pad to whole words.
    idx = jnp.minimum(jnp.arange(-(-K // WORD) * WORD), K - 1)
    res = _dense.counts_chunk(pm, jax.tree.map(lambda a: a[idx], cameras), tau, tests, predicate, context, combine,
                              return_masks)
    out = dict(zip(("faces", "vertices", "executed_count"), (r[:K] for r in res[:3])))
    if return_masks:
        out["executed"] = res[3][:K]
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


# -- face budgets -------------------------------------------------------------------


def check_budget(budget) -> int:
    """A face budget as an ``int``: a whole number >= 0 (``ValueError`` otherwise)."""
    ok = isinstance(budget, (int, np.integer)) and not isinstance(budget, bool)
    if not ok and isinstance(budget, (float, np.floating)) and np.isfinite(budget) and float(budget).is_integer():
        ok, budget = True, int(budget)
    if not ok or budget < 0:
        raise ValueError(f"a face budget must be a whole number >= 0, got {budget!r}")
    return int(budget)


def kernel_budgets(pm: ProgressiveMesh, budget, call: str):
    """Face budgets as the kernels take them (``int32``, any shape): host
    values checked (:func:`check_budget`) and capped at the mesh's face count
    (a larger budget has the same answer, every face fitting, and may not fit
    int32); traced ones must be integers, and a negative one raises inside
    the traced computation (``eqx.error_if``).

    Raises:
        ValueError: a host budget that is negative, fractional, NaN or not a
            number; TypeError: a traced budget of a non-integer dtype.
    """
    if is_traced(budget):
        budget = jnp.asarray(budget)
        if not jnp.issubdtype(budget.dtype, jnp.integer):
            raise TypeError(f"{call}: a traced face budget must be an integer array, got {budget.dtype}")
        budget = eqx.error_if(budget, budget < 0, f"{call}: a face budget must be >= 0")
        return jnp.minimum(budget, pm.n_faces).astype(jnp.int32)
    return jnp.asarray(np.minimum(host_budgets(budget), pm.n_faces), jnp.int32)


def host_budgets(budget) -> np.ndarray:
    """Host face budgets (one or an array of any shape) as ``int64`` of the
    same shape, each checked by :func:`check_budget` (``ValueError``)."""
    values = np.asarray(budget, dtype=object) if not isinstance(budget, np.ndarray) else budget
    checked = [check_budget(b.item() if isinstance(b, np.generic) else b) for b in np.ravel(values)]
    return np.array(checked, np.int64).reshape(np.shape(values))


def faces_for_budget(pm: ProgressiveMesh, camera: Camera, budget: int, tests: Tests = ALL_TESTS,
                     method: str = "auto"):
    """The smallest ``tau`` whose face count is the largest not above ``budget``.

    Dense: one sort of the critical tolerances: a pcol runs at ``tau`` iff
    ``eps < tau``, so the face count at ``tau`` is ``F`` minus the faces killed
    by the pcols with ``eps < tau``. Even ``tau = 0`` runs the pcols with
    ``eps < 0`` (culled: outside the frustum or facing away). Front: a
    search over the float32 bit patterns of ``tau`` (a bracket, then regula
    falsi on ``log tau``) on exact counts of the C core (about 24
    refinements, each costing what the view's front costs, in one compiled
    loop); the same answer (docs/design.md). For many cameras,
    :func:`faces_for_budget_batch` gives the same answers at a few refines'
    cost per camera.

    Args:
        pm: :class:`ProgressiveMesh`.
        camera: one camera.
        budget: faces, a whole number >= 0 (under ``jit``: an integer array).
        tests: :class:`Tests`.
        method: ``"front"`` (the C core's search), ``"dense"`` or ``"auto"``
            (the search from ``FRONT_FROM_PCOLS`` pcols on, else the sort).

    Returns:
        ``(tau, faces)``: ``tau`` (pixels, float32) and the face count there,
        which :func:`pmjax.refine` reproduces. ``tau = 0`` when even the finest
        view fits; when no tolerance meets the budget, ``tau = inf`` and the
        coarsest count, which is then above ``budget``. Host numbers, or JAX
        arrays under ``jit``/``vmap``.

    Raises:
        ValueError: a budget that is negative, fractional, NaN or not a number.
    """
    check_mesh(pm, "faces_for_budget")
    check_camera(camera, "faces_for_budget", batch=False)
    traced = is_traced(camera, budget)
    if not traced:
        # Any budget from F on has the answer of F (every face fits).
        budget = min(check_budget(budget), pm.n_faces)
    else:
        budget = kernel_budgets(pm, budget, "faces_for_budget")
    engine = select(pm, method, traced=traced)
    # The search pays about 24 refines: faster than the sort from about
    # FRONT_FROM_PCOLS pcols on (measured in docs/front.md).
    if engine == "core" and (method == "front" or pm.n_pcols >= FRONT_FROM_PCOLS):
        counts_of = _Counts.of(pm)
        tau, faces = _core_budget(derived(pm).core, _core.camera_rows(camera, jnp.float32(1.0), derived(pm).exponent),
                                  jnp.asarray(budget, jnp.int32), tests, camera.orthographic, counts_of.base_faces)
        return (tau, faces) if traced else (np.float32(tau), int(faces))
    eps = critical_tolerances(pm, camera, tests)
    if traced:
        return _dense.budget_sort_traced(pm, eps, jnp.asarray(budget, jnp.int32))
    return _dense.budget_sort(pm, eps, budget)


@functools.partial(jax.jit, static_argnames=("tests", "orthographic", "base_faces"))
def _core_budget(tables, camera_row, budget, tests, orthographic, base_faces):
    one = _core.one_camera(tests, orthographic, False)

    def faces_at(tau):
        counts = one(tables, camera_row.at[-1].set(tau))[3]
        return jnp.int32(base_faces) + counts[2]

    return budget_search(faces_at, budget)


def budget_search(faces_at, budget):
    """The smallest float32 ``tau`` with ``faces_at(tau) <= budget`` (and its
    count), for a count that does not increase with ``tau``.

    Non-negative float32 values are ordered as their bit patterns, so the
    answer is the upper end of a bracket of two adjacent patterns, one count
    above the budget and one within it. The bracket is found by steps of 8x
    from ``tau = 1`` (``tau = 0`` and ``inf`` only when the search reaches
    them) and narrowed by regula falsi on ``log tau`` (the Illinois variant:
    an end kept twice has its weight halved), every third step the midpoint
    of the patterns, so that the bracket at least halves in bits. One
    ``faces_at`` per step of a ``lax.while_loop``.

    Returns:
        ``(tau float32, faces int32)``: ``tau = 0`` when even ``tau = 0`` fits,
        ``inf`` and its count when nothing does.
    """
    f32, i32 = jnp.float32, jnp.int32
    bits = lambda t: lax.bitcast_convert_type(jnp.asarray(t, f32), i32)
    value = lambda b: lax.bitcast_convert_type(jnp.asarray(b, i32), f32)
    down, up, narrow, done = 0, 1, 2, 3
    weight = lambda f: (f - budget).astype(f32) - 0.5
    f1 = faces_at(f32(1.0))
    fits = f1 <= budget
    # (phase, lo, f_lo, hi, f_hi, w_lo, w_hi, kept (0 none, 1 lo, 2 hi), step, tau, faces)
    state = (jnp.where(fits, down, up), f32(1.0), f1, f32(1.0), f1, f32(0.0), f32(0.0), i32(0), i32(0), f32(0.0),
             f1)

    def cond(s):
        return s[0] != done

    def body(s):
        phase, lo, f_lo, hi, f_hi, w_lo, w_hi, kept, step, _, _ = s
        lo_b, hi_b = bits(lo), bits(hi)
        # The tolerance this step tries.
        t_down = hi / 8
        t_down = jnp.where(t_down < f32(1e-30), f32(0.0), t_down)
        t_up = lo * 8
        t_up = jnp.where(t_up > f32(1e30), f32(jnp.inf), t_up)
        step1 = step + 1
        mid = lo_b + (hi_b - lo_b) // 2
        x_lo, x_hi = jnp.log(jnp.maximum(lo, f32(1e-38))), jnp.log(jnp.where(jnp.isfinite(hi), hi, f32(1.0)))
        guess = bits(jnp.exp(x_lo + (x_hi - x_lo) * w_lo / (w_lo - w_hi)))
        guess = jnp.clip(guess, lo_b + 1, hi_b - 1)
        use_falsi = (step1 % 3 != 0) & (lo > 0) & jnp.isfinite(hi)
        t_narrow = value(jnp.where(use_falsi, guess, mid))
        t = jnp.where(phase == down, t_down, jnp.where(phase == up, t_up, t_narrow))
        f = faces_at(t)
        within = f <= budget
        # Bracketing down: hi moves down until a count above the budget (lo);
        # at tau = 0 that fits, the answer is 0.
        d_done = (phase == down) & (t == 0) & within
        d_lo = (phase == down) & ~within
        # Bracketing up: lo moves up until a count within it (hi); at inf above
        # it, the answer is inf.
        u_done = (phase == up) & jnp.isinf(t) & ~within
        u_hi = (phase == up) & within
        n_hi, n_lo = (phase == narrow) & within, (phase == narrow) & ~within
        new_lo = jnp.where(d_lo | (phase == up) & ~within | n_lo, t, lo)
        new_f_lo = jnp.where(d_lo | (phase == up) & ~within | n_lo, f, f_lo)
        new_hi = jnp.where((phase == down) & within | u_hi | n_hi, t, hi)
        new_f_hi = jnp.where((phase == down) & within | u_hi | n_hi, f, f_hi)
        # Weights: set on entering the narrowing, updated (Illinois) within it.
        entering = d_lo | u_hi
        new_w_lo = jnp.where(entering, weight(new_f_lo), jnp.where(n_lo, weight(f), jnp.where(
            n_hi & (kept == 1), w_lo / 2, w_lo)))
        new_w_hi = jnp.where(entering, weight(new_f_hi), jnp.where(n_hi, weight(f), jnp.where(
            n_lo & (kept == 2), w_hi / 2, w_hi)))
        new_kept = jnp.where(n_hi, 1, jnp.where(n_lo, 2, kept))
        new_phase = jnp.where(entering, narrow, phase)
        new_step = jnp.where(phase == narrow, step1, step)
        tau = jnp.where(d_done, f32(0.0), jnp.where(u_done, f32(jnp.inf), f32(0.0)))
        faces = f
        finished = d_done | u_done
        # Narrowed to adjacent patterns: the answer is the upper end.
        adjacent = (new_phase == narrow) & (bits(new_hi) - bits(new_lo) <= 1)
        tau = jnp.where(adjacent, new_hi, tau)
        faces = jnp.where(adjacent, new_f_hi, faces)
        new_phase = jnp.where(finished | adjacent, done, new_phase)
        return (new_phase, new_lo, new_f_lo, new_hi, new_f_hi, new_w_lo, new_w_hi, new_kept, new_step, tau, faces)

    out = lax.while_loop(cond, body, state)
    return out[9], out[10]


_INF_BITS = 0x7F800000


def faces_for_budget_batch(pm: ProgressiveMesh, cameras: Camera, budget, *, tests: Tests = ALL_TESTS,
                           chunk: int = 256, method: str = "auto", path: bool = False) -> dict:
    """:func:`faces_for_budget` for K cameras at once: the same ``(tau, faces)``
    per camera (and per budget), and the counts there.

    With the C core, each chunk of cameras is one threaded call that
    traverses each camera once at a tolerance below its smallest answer and
    guesses the answer of each of its budgets from the critical tolerances
    of the pcols that do not run there (docs/design.md); exact counts at the
    guess and just below it, batched over the chunk, confirm it (or a few
    more counts, galloping then bisecting over the float32 bit patterns,
    correct it). Without the core (or under ``jit``/``vmap``) each camera
    and budget is :func:`faces_for_budget`.

    Args:
        pm: :class:`ProgressiveMesh`.
        cameras: a camera batch (leading axis K).
        budget: faces, whole numbers >= 0: one for all cameras, ``[K]`` one
            per camera, or ``[K, B]``: B budgets per camera, answered by one
            guess traversal per camera (several budgets of the same cameras
            cost little more than the largest alone).
        tests: :class:`Tests`.
        chunk: cameras per guess call, rounded up to a multiple of 32 (the
            exact counts of whole chunks, up to 4,096 cameras, run together).
        method: ``"auto"``, ``"front"`` or ``"dense"`` (as :func:`faces_for_budget`).
        path: the cameras are the frames of one path, in order (an orbit, a
            fly-through): every 32nd frame is guessed alone, the frames
            between word by word inside the coherent path engine, starting
            below the answers the sampled frames around them predict, and
            the exact counts run through it too
            (:func:`pmjax.path_counts`, per-frame tolerances). The same
            answers; only the cost differs.

    Returns:
        dict ``tau`` (``float32``, pixels; ``0`` when even the finest view
        fits, ``inf`` when nothing does), ``faces``, ``vertices``,
        ``executed_count`` (``int32``, the refinement at ``tau``), each ``[K]``,
        or ``[K, B]`` for a ``[K, B]`` budget: NumPy arrays, or JAX arrays
        under ``jit``.

    Raises:
        ValueError: a budget that is negative, fractional, NaN or not a number,
            or a budget array of another shape than ``[K]`` or ``[K, B]``.
    """
    check_mesh(pm, "faces_for_budget_batch")
    K = check_camera(cameras, "faces_for_budget_batch", batch=True)
    traced = is_traced(cameras, budget)
    if traced:
        budgets = kernel_budgets(pm, budget, "faces_for_budget_batch")
        if budgets.ndim > 2 or (budgets.ndim >= 1 and budgets.shape[0] != K) or (budgets.ndim == 2 and
                                                                                    budgets.shape[1] < 1):
            raise ValueError(f"faces_for_budget_batch: budget must be one number, [{K}] or [{K}, B], "
                             f"got shape {list(budgets.shape)}")
        columns = budgets.ndim == 2
        budgets = budgets if columns else jnp.broadcast_to(budgets, (K,))[:, None]

        def one(camera, b):
            tau, faces = faces_for_budget(pm, camera, b, tests, method)
            r = refine(pm, camera, tau, tests=tests, method=method)
            return tau, faces, r.n_vertices, r.n_executed

        out = jax.vmap(jax.vmap(one, in_axes=(None, 0)))(cameras, budgets)
        tau, faces, vertices, executed = (x if columns else x[:, 0] for x in out)
        return dict(tau=tau, faces=faces, vertices=vertices, executed_count=executed)
    budgets = np.asarray(budget, dtype=object) if not isinstance(budget, np.ndarray) else budget
    if np.ndim(budgets) == 0:
        budgets, columns = np.full((K, 1), check_budget(budget), np.int64), False
    else:
        shape = np.shape(budgets)
        if not (shape == (K,) or (len(shape) == 2 and shape[0] == K and shape[1] >= 1)):
            raise ValueError(f"faces_for_budget_batch: budget must be one number, one per camera ([{K}]) or B per "
                             f"camera ([{K}, B]), got shape {list(shape)}")
        columns = len(shape) == 2
        budgets = host_budgets(budgets).reshape(K, -1)
    B = budgets.shape[1]
    shaped = lambda out: out if columns else {k: v[:, 0] for k, v in out.items()}
    engine = select(pm, method, batch=True)
    if engine != "core" or K == 0:
        out = dict(tau=np.zeros((K, B), np.float32), faces=np.zeros((K, B), np.int32),
                   vertices=np.zeros((K, B), np.int32), executed_count=np.zeros((K, B), np.int32))
        for k in range(K):
            camera = jax.tree.map(lambda a: a[k], cameras)
            for j in range(B):
                tau, faces = faces_for_budget(pm, camera, int(budgets[k, j]), tests, method)
                r = refine(pm, camera, float(tau), tests=tests, method=method)
                out["tau"][k, j], out["faces"][k, j] = tau, faces
                out["vertices"][k, j], out["executed_count"][k, j] = int(r.n_vertices), int(r.n_executed)
        return shaped(out)
    chunk = -(-max(1, min(int(chunk), K)) // WORD) * WORD
    host = jax.tree.map(np.asarray, cameras)
    d = derived(pm)
    counts_of = _Counts.of(pm)
    # A count never exceeds F: budgets above it are the same as F (and fit int32).
    budgets = np.minimum(budgets, counts_of.F)
    if path:
        return shaped(_path_budgets(pm, host, budgets, tests, chunk))
    order = nearby_order(np.asarray(cameras.eye))
    tau = np.empty((K, B), np.float32)
    cols = [np.empty((K, B), np.int32) for _ in range(3)]
    # The guesses chunk by chunk; the exact counts of whole chunks up to
    # POOLED cameras at once, so that each round of counts (most of them left
    # to a few cameras after the first) is one set of calls for all of them,
    # not one per chunk.
    pool = chunk * max(1, POOLED // chunk)
    for s in range(0, K, pool):
        idx = order[s:s + pool]
        n = len(idx)
        guess, alt = _guesses(d, counts_of, host, idx, np.zeros(n, np.float32), budgets, tests, chunk)
        rows = _core.host_camera_rows(jax.tree.map(lambda a: a[idx], host), np.zeros(n, np.float32), d.exponent)
        # Every (camera, budget) pair its own probe row.
        t, c = _exact_from_guess(d.core, np.repeat(rows, B, axis=0), budgets[idx].ravel(), guess.ravel(),
                                 alt.ravel(), tests, cameras.orthographic, counts_of)
        tau[idx] = t.reshape(n, B)
        for col, v in zip(cols, c):
            col[idx] = v.reshape(n, B)
    return shaped(dict(tau=tau, faces=cols[0], vertices=cols[1], executed_count=cols[2]))


# Cameras whose exact counts run together in faces_for_budget_batch, in whole
# chunks (at least one): their probe rows, B per camera, are held at once.
POOLED = 4096


# Along a path, every PATH_SAMPLE-th frame is guessed first (each from the
# answer of the frame its thread did before, START times above, so usually
# two traversals); the others are guessed word by word, each frame's traversal
# at PATH_START times the smallest answer the sampled frames around it
# predict (log tau interpolated along the path, held past the last sampled
# frame), where it finds the answers at once.
PATH_SAMPLE = 32
PATH_START = 0.95


def _padded_chunk(n: int, chunk: int) -> int:
    """Cameras per call for ``n`` single-camera guesses along a path: the
    smallest ``WORD * 2**k`` that holds them (few compiled sizes; a call
    pads with repeats of its last camera, which make no guess), at most
    ``chunk``."""
    size = WORD
    while size < n:
        size *= 2
    return min(size, chunk)


def _path_budgets(pm, host, budgets, tests, chunk):
    """:func:`faces_for_budget_batch` of one path's frames in order (``host``
    NumPy cameras, ``budgets`` int64 [K, B] at most F; results [K, B]):
    guesses of sampled frames, then of the others word by word, then exact
    counts through the core's words: the first two rounds' (at the guess and
    one pattern below it, all frames) one pass of the path per budget, the
    later rounds' (the guesses that were off) budget by budget in the path's
    order."""
    K, B = budgets.shape
    d, counts_of = derived(pm), _Counts.of(pm)
    sampled = np.arange(0, K, PATH_SAMPLE)
    guess, alt = np.zeros((K, B), np.int32), np.zeros((K, B), np.int32)
    guess[sampled], alt[sampled] = _guesses(d, counts_of, host, sampled, np.zeros(len(sampled), np.float32),
                                            budgets, tests, _padded_chunk(len(sampled), chunk))
    # The smallest answer (the largest budget's) predicts where a frame's
    # traversal starts; sampled answers at 0 or inf predict nothing: those
    # frames start as the core would.
    top = np.argmax(budgets[sampled], axis=1)
    g = guess[sampled, top].astype(np.int64)
    finite = (g > 0) & (g <= _INF_BITS)
    start = np.zeros(K, np.float32)
    if finite.any():
        log_tau = np.log(g[finite].astype(np.int32).view(np.float32).astype(np.float64))
        predicted = PATH_START * np.exp(np.interp(np.arange(K), sampled[finite], log_tau))
        start = np.where(np.isfinite(predicted), predicted, 0.0).astype(np.float32)
    rest = np.setdiff1d(np.arange(K), sampled)
    if len(rest):
        # The other frames guessed word by word along the path, each at its
        # start (a frame without one at inf: a traversal that stops at the
        # roots, its guess unused); those whose answers lie below it, or
        # that have no start, are guessed alone (all of them, without a word
        # traversal, where no frame has a start).
        if (start[rest] > 0).any():
            guess[rest], alt[rest] = (x[rest] for x in _word_guesses(d, counts_of, host, np.where(
                start > 0, start, np.float32(np.inf)), budgets, tests))
        alone = rest[~(start[rest] > 0) | (guess[rest] < 0).any(axis=1)]
        if len(alone):
            guess[alone], alt[alone] = _guesses(d, counts_of, host, alone, start[alone], budgets, tests,
                                                _padded_chunk(len(alone), chunk))
    rows = _core.host_camera_rows(host, np.zeros(K, np.float32), d.exponent)

    # The (frame, budget) pairs of all budgets at both patterns (at the
    # guess, then just below it), one pass along the path per budget: each
    # word of 16 frames traversed once for its frames at the budget's
    # patterns (a set of words, :func:`_word_set_counts`), whose fronts
    # share most of their slots.
    def along_path(*bits):
        G = len(bits)
        # Budget by budget, the finest pattern first (the core decides a set's
        # frames from the finer sets' collapses where it can).
        tols = np.stack([b.reshape(B, K) for b in bits[::-1]], axis=1).reshape(B * G, K)
        got = np.concatenate([_word_set_counts(d, counts_of, rows, tols[s:s + G], tests, host.orthographic)
                              for s in range(0, B * G, G)])
        return got.reshape(B, G, K, 3)[:, ::-1].transpose(1, 0, 2, 3).reshape(G, B * K, 3)

    # Pairs far off after the second round: their frames guessed again, each
    # alone from its start (its unsure decisions also taken as collapses, the
    # other guess), where the word's one guess read them as "keep".
    def reguess(cams):
        frames, at = np.unique(cams % K, return_inverse=True)
        g, a = _guesses(d, counts_of, host, frames, start[frames], budgets, tests,
                        _padded_chunk(len(frames), chunk))
        return g[at, cams // K], a[at, cams // K]

    # The later rounds' probes (a few per guess that missed) through the
    # core's words too, budget by budget and in the path's order, so that a
    # word's frames lie near each other on the path.
    def probes_along_path(cams, bits):
        frame = cams % K
        order = np.lexsort((bits, frame, cams // K))
        counted = np.empty((len(cams), 3), np.int64)
        counted[order] = _word_set_counts(d, counts_of, rows[frame[order]], bits[order][None], tests,
                                          host.orthographic)[0]
        return counted

    tau, cols = _exact_from_guess(d.core, np.tile(rows, (B, 1)), budgets.T.ravel(), guess.T.ravel(),
                                  alt.T.ravel(), tests, host.orthographic, counts_of, along_path,
                                  probes_along_path, reguess)
    return dict(tau=tau.reshape(B, K).T.copy(), faces=cols[0].reshape(B, K).T.astype(np.int32),
                vertices=cols[1].reshape(B, K).T.astype(np.int32),
                executed_count=cols[2].reshape(B, K).T.astype(np.int32))


def _word_calls(K: int):
    """The frames of a path of ``K`` frames per call of the core's words:
    the path padded to whole words by its last frame, whole blocks of words
    per call, then the rest in powers of two words (few compiled sizes).
    A repeated frame gets the same results as the frame itself."""
    F = _core.FRAMES
    words = -(-K // F)
    # The padding repeats frame K - 1 with its own budgets and tolerance
    # (never a budget below every mesh, as a call of one-camera guesses
    # pads): the callers scatter the results by these indices, the last
    # write to frame K - 1 winning, so the padding's results must be that
    # frame's own.
    order = np.minimum(np.arange(words * F), K - 1)
    for start, n in _core.word_spans(words, _core.WORDS_PER_CALL):
        yield order[start * F:(start + n) * F]


@functools.partial(jax.jit, static_argnames=("tests", "orthographic", "sets"))
def _core_word_counts(tables, one_tables, rows, tests, orthographic, sets=1):
    return _core.refine_words(tables, one_tables, rows, tests, orthographic, False, sets=sets)[0]


def _word_set_counts(d, counts_of, rows, bits, tests, orthographic):
    """Exact ``(faces, vertices, executed)`` (``int64 [T, K, 3]``) of a
    path's frames ``rows`` (``float32 [K, CAMERA]``, in order) at T
    tolerances each (``bits``: ``[T, K]`` float32 bit patterns of tau,
    ``T <= _core.MOST_SETS``): each word of frames (:func:`_word_calls`) traversed
    once for all T tolerances, as a set of T words that differ only in
    their tolerances."""
    T, K = bits.shape
    if not 1 <= T <= _core.MOST_SETS:
        raise ValueError(f"word sets hold 1 to {_core.MOST_SETS} tolerances, got {T}")
    F = _core.FRAMES
    out = np.empty((T, K, 3), np.int64)
    tau = np.asarray(bits, np.int64).astype(np.int32).view(np.float32)
    for lanes in _word_calls(K):
        n = len(lanes) // F
        # Word j's set: its frames at tolerance 0, then at 1, ... (rows
        # [j, t, frame]).
        at = np.repeat(rows[lanes].reshape(n, 1, F, -1), T, axis=1)
        at[..., -1] = tau[:, lanes].reshape(T, n, F).transpose(1, 0, 2)
        counts = np.asarray(_core_word_counts(d.core_words, d.core, at.reshape(n * T * F, -1), tests,
                                              orthographic, sets=T))
        got = np.stack(counts_of(counts[:, 1], counts[:, 2], np), 1).reshape(n, T, F, 3)
        out[:, lanes] = got.transpose(1, 0, 2, 3).reshape(T, n * F, 3)
    return out


def _guesses(d, counts_of, host, frames, start, budgets, tests, chunk):
    """The core's ``(guess, alt)`` (``int32 [len(frames), B]``) of cameras
    ``host[frames]`` for their budgets ``budgets[frames]`` (``[K, B]``), each
    traversal starting at ``start`` (0: from the thread's last answer),
    ``chunk`` cameras per call (the last chunk padded by repeating its last
    camera with no budget to meet, which costs no traversal)."""
    B = budgets.shape[1]
    guess, alt = np.empty((len(frames), B), np.int32), np.empty((len(frames), B), np.int32)
    for s in range(0, len(frames), chunk):
        pick = np.minimum(np.arange(s, s + chunk), len(frames) - 1)
        part = jax.tree.map(lambda a: a[frames[pick]], host)
        rows = _core.host_camera_rows(part, start[pick], d.exponent)
        n = min(chunk, len(frames) - s)
        # The padding's budgets below every mesh (-1): the core answers them
        # inf without a traversal.
        want = budgets[frames[pick]].astype(np.int32)
        want[n:] = -1
        got = _core_guesses(d.core, rows, want, tests, host.orthographic, counts_of.base_faces)
        guess[s:s + n], alt[s:s + n] = (np.asarray(x)[:n] for x in got)
    return guess, alt


def _word_guesses(d, counts_of, host, start, budgets, tests):
    """The core's ``(guess, alt)`` (``int32 [K, B]``) of a path's frames
    ``host`` in order for their budgets (``[K, B]``), each word of frames
    traversed once at the frames' own tolerances ``start`` (``float32
    [K]``, > 0), -1 for a frame whose answers lie below its tolerance; the
    calls as :func:`_word_calls` makes them."""
    K, B = budgets.shape
    rows = _core.host_camera_rows(host, start, d.exponent)
    guess, alt = np.empty((K, B), np.int32), np.empty((K, B), np.int32)
    for lanes in _word_calls(K):
        got = _core_guesses(d.core_words, rows[lanes], budgets[lanes].astype(np.int32), tests, host.orthographic,
                            counts_of.base_faces, words=True)
        # lanes repeats frame K - 1 in the padding (last write wins): the
        # padding's guesses are that frame's own, as its budgets are.
        guess[lanes], alt[lanes] = (np.asarray(x) for x in got)
    return guess, alt


@functools.partial(jax.jit, static_argnames=("tests", "orthographic", "base_faces", "words"))
def _core_guesses(tables, rows, budgets, tests, orthographic, base_faces, words=False):
    return _core.budget_guesses(tables, rows, budgets, tests, orthographic, base_faces, words=words)


# Patterns probed next to a wrong guess in the second round of counts: the
# guesses' misses are mostly one to three patterns (the own tolerances'
# float32 terms rounded otherwise than the predicate's).
NEAR = 3


def _exact_from_guess(tables, rows, budgets, guess, alt, tests, orthographic, counts_of, along_path=None,
                      probes=None, reguess=None):
    """The exact answers from the guesses, by rounds of exact counts.

    Over the float32 bit patterns ``b`` of ``tau`` (``0 .. INF_BITS``; a
    virtual ``-1`` below, whose count exceeds every budget, and ``INF_BITS +
    1`` above, within every budget), each camera keeps a bracket ``lo < hi``
    with ``faces(lo) > budget >= faces(hi)``; the answer is ``hi`` once they
    are adjacent (``INF_BITS + 1``: ``tau = inf`` with the count at inf). The
    first round counts at the guess and just below it, the second at the
    other guess (``alt``, the core's unsure decisions taken the other way)
    and just below it where that differs, else at the :data:`NEAR` patterns
    next to the bracket's known end; later rounds
    gallop from a virtual end (steps growing geometrically) or split the
    bracket. Each round is one batched call of exact counts over the cameras
    still open. With ``along_path`` (``bits_0 [n], bits_1 [n] -> counts
    int64 [2, n, 3]``: all the cameras as a path, each at both patterns) the
    first round's two sets of counts come from one call of it instead, and
    with ``probes`` (``cams [m], bits [m] -> counts int64 [m, 3]``) the
    later rounds' counts. With ``reguess``
    (``cams [m] -> (guess, alt) int [m]``: new guesses of those cameras,
    each alone) the third round probes the new guesses of the cameras the
    second left open.
    """
    n = len(budgets)
    lo = np.full(n, -1, np.int64)
    hi = np.full(n, _INF_BITS + 1, np.int64)
    at_hi = np.zeros((n, 3), np.int64)   # counts at hi (faces, vertices, executed)
    at_inf = np.zeros((n, 3), np.int64)  # counts at INF_BITS, where counted
    step = np.ones(n, np.int64)
    g = np.clip(guess.astype(np.int64), 0, _INF_BITS + 1)
    # Groups of probes, at most one per camera in each: (cameras, bit patterns).
    groups = [(np.arange(n), g), (np.arange(n), g - 1)]
    rounds = 0
    while True:
        groups = [(c[(b >= 0) & (b <= _INF_BITS)], b[(b >= 0) & (b <= _INF_BITS)]) for c, b in groups]
        cams, bits = np.concatenate([c for c, _ in groups]), np.concatenate([b for _, b in groups])
        if len(cams) and along_path is not None and rounds == 0:
            # Every camera at the guess and one pattern below it, in one call
            # as a path (patterns out of range counted at inf, unused).
            ats = []
            for c, b in groups:
                at = np.full(n, _INF_BITS, np.int64)
                at[c] = b
                ats.append(at)
            got = along_path(*ats)
            counted = np.concatenate([got[q][c] for q, (c, _) in enumerate(groups)])
        elif len(cams) and probes is not None:
            counted = probes(cams, bits)
        elif len(cams):
            counted = np.stack(_counts_at(tables, rows, cams, bits, tests, orthographic, counts_of), 1)
        if len(cams):
            start = 0
            for c, b in groups:
                got = counted[start:start + len(c)]
                start += len(c)
                at_inf[c[b == _INF_BITS]] = got[b == _INF_BITS]
                within = got[:, 0] <= budgets[c]
                lower = within & (b < hi[c])
                hi[c[lower]], at_hi[c[lower]] = b[lower], got[lower]
                raise_ = ~within & (b > lo[c])
                lo[c[raise_]] = b[raise_]
        open_ = hi - lo > 1
        if not open_.any():
            break
        c = np.flatnonzero(open_)
        l, h, st = lo[c], hi[c], step[c]
        below, above = l < 0, h > _INF_BITS
        # The second round probes the NEAR patterns next to the known end
        # (most guesses are one to three ulps off: one round settles them);
        # later ones, left to the few guesses far off, probe `m` points each,
        # galloping on from there.
        m = NEAR if rounds == 0 else 8
        groups = []
        if rounds == 0:  # the other guess, where it differs and lies inside the bracket
            a = np.clip(alt[c].astype(np.int64), 0, _INF_BITS + 1)
            other = (a != g[c]) & (a > l) & (a <= h)
            groups += [(c[other], a[other]), (c[other], a[other] - 1)]
            c, l, h, st, below, above = (x[~other] for x in (c, l, h, st, below, above))
        if rounds == 1 and reguess is not None and len(c):
            # Guesses still open after the NEAR patterns are far off (mostly
            # an unsure decision read as "keep"): guessed again, the new guess
            # and its other one probed with the pattern below each, where they
            # lie inside the bracket, instead of galloping this round.
            new = [np.clip(x.astype(np.int64), 0, _INF_BITS + 1) for x in reguess(c)]
            taken = np.zeros(len(c), bool)
            for q, x in enumerate(new):
                inside = (x > l) & (x <= h) & ((q == 0) | (x != new[0]))
                groups += [(c[inside], x[inside]), (c[inside], x[inside] - 1)]
                taken |= inside
            c, l, h, st, below, above = (x[~taken] for x in (c, l, h, st, below, above))
        for j in range(m):
            reach = st * (j + 1) if rounds == 0 else st << j
            inner = l + (h - l) * (j + 1) // (m + 1)
            b = np.where(below, np.maximum(h - reach, 0), np.where(above, np.minimum(l + reach, _INF_BITS), inner))
            groups.append((c, b))
        step[c] = np.where(below | above, st * (m + 1) if rounds == 0 else st << m, st)
        rounds += 1
    tau = np.where(hi > _INF_BITS, np.inf, hi.astype(np.int32).view(np.float32) if n else 0.0).astype(np.float32)
    counted = np.where((hi > _INF_BITS)[:, None], at_inf, at_hi)
    return tau, (counted[:, 0], counted[:, 1], counted[:, 2])


# Probe rows per call of exact counts at most (32 times a power of 4).
MOST_PROBES = 2048


def _count_calls(m: int):
    """The ``(start, size)`` of the calls that count ``m`` probes: sizes 32
    times a power of 4 up to :data:`MOST_PROBES` (few compiled sizes), as
    many of the largest as fit, then of the next, and so on; the last call
    padded to 32. A padding row still costs a traversal of the roots, so
    calls are filled with probes rather than padded."""
    q = MOST_PROBES // WORD  # the sizes step by 4 from MOST_PROBES down to WORD
    assert MOST_PROBES == q * WORD and q & (q - 1) == 0 and q.bit_length() % 2 == 1, MOST_PROBES
    calls, start, size = [], 0, MOST_PROBES
    while start < m:
        while size > WORD and m - start < size:
            size //= 4
        calls.append((start, size))
        start += size
    return calls


def _counts_at(tables, rows, cams, bits, tests, orthographic, counts_of):
    """Exact counts of cameras ``rows[cams]`` at ``tau`` of bit patterns
    ``bits``: batched calls (:func:`_count_calls`), the last one padded by
    rows at ``tau = inf``, whose traversal stops at the roots."""
    m = len(cams)
    out = np.empty((m, 2), np.int64)
    for start, size in _count_calls(m):
        k = min(size, m - start)
        probe = np.empty((size, rows.shape[1]), np.float32)
        probe[:k] = rows[cams[start:start + k]]
        probe[k:] = rows[cams[start]]
        probe[:k, -1] = bits[start:start + k].astype(np.int32).view(np.float32)
        probe[k:, -1] = np.inf
        out[start:start + k] = np.asarray(_core_many(tables, probe, tests, orthographic, False)[0])[:k, 1:3]
    faces, vertices, executed = counts_of(out[:, 0], out[:, 1], np)
    return faces.astype(np.int64), vertices.astype(np.int64), executed.astype(np.int64)
