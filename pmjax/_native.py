"""The output-sensitive engine's C loops (``pmjax/_front_native.c``), called through ctypes.

On the CPU, the front traversal as JAX kernels pays a fixed cost of about a
dozen XLA kernels per generation of the pcol forest, whatever their size
(docs/front.md). The same traversal as a C loop costs only the pcols it
visits. Its results are the dense engine's bits:

- the subtree bound is evaluated in float64 with the margins of
  :mod:`pmjax._subtree` (sound);
- each visited pcol's own decision is *certified*: the C code evaluates every
  comparison of the float32 predicate exactly enough, with a bound on how far
  any float32 evaluation of it can be (fused multiply-adds or not, flush to
  zero). A comparison closer than that bound is left "unsure", and those few
  pcols are decided here by the float32 predicate itself
  (:func:`pmjax._predicate.view_collapse_mask` on their gathered rows, the
  function the dense engine applies), so no float tie can differ.

The library is built by ``pip install`` as the optional extension
``pmjax._front_native``; where it is missing (no C compiler at install time),
or ``PMJAX_NATIVE=0`` is set, :func:`available` is false and the front engine
runs as JAX kernels.
"""

from __future__ import annotations

import ctypes
import functools
import importlib.util
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np

from ._view import View

# Flags of the C entry points.
TEST_FRUSTUM, TEST_ORIENTATION, TEST_SCREEN, ORTHOGRAPHIC = 1, 2, 4, 8
# State of a slot (the C enum): own decision NO / YES / UNSURE.
NO, YES, UNSURE = 0, 1, 2

_p = ctypes.c_void_p
_i64 = ctypes.c_int64


def _load():
    if os.environ.get("PMJAX_NATIVE", "1") == "0":
        return None
    spec = importlib.util.find_spec("pmjax._front_native")
    if spec is None or not spec.origin:
        return None
    lib = ctypes.CDLL(spec.origin)
    lib.pmx_refine.restype = _i64
    lib.pmx_refine.argtypes = [_p, _p, _p, _i64, _p, _i64, _p, ctypes.c_int, _p, _p, _p, _p, _p, _p]
    lib.pmx_resolve.restype = None
    lib.pmx_resolve.argtypes = [_p, _i64, _p, _p, _p, _p, _p]
    lib.pmx_refine_many.restype = None
    lib.pmx_refine_many.argtypes = [_p, _p, _p, _i64, _p, _i64, _p, ctypes.c_int, _i64, _i64] + [_p] * 8
    lib.pmx_decide_all.restype = None
    lib.pmx_decide_all.argtypes = [_p, _i64, _p, ctypes.c_int, _p]
    lib.pmx_front_mesh.restype = _i64
    lib.pmx_front_mesh.argtypes = [_i64, _i64, _i64, _p, _i64, _p, _p, _p, _i64, _p, _p, _i64, _p, _i64, _p, _p,
                                   _i64] + [_p] * 10
    return lib


_LIB = _load()


def available() -> bool:
    """Whether the front engine runs as the compiled C loops
    (``pmjax.native_available``); else it runs as JAX kernels."""
    return _LIB is not None and _enabled


# Tests switch the C loops off to run the JAX traversal (use_native).
_enabled = True


class use_native:
    """``with use_native(False): ...`` runs the front engine as JAX kernels
    (for comparisons); ``True`` restores the C loops where they are built."""

    def __init__(self, on: bool):
        self.on = on

    def __enter__(self):
        global _enabled
        self.before, _enabled = _enabled, self.on
        return self

    def __exit__(self, *exc):
        global _enabled
        _enabled = self.before


def decide_all(pm, camera, tau, tests) -> np.ndarray:
    """``uint8[P]``: every pcol's certified decision (``NO``, ``YES``,
    ``UNSURE``) with bit 4 set where its subtree bound decides its subtree."""
    host = native_mesh(pm)
    out = np.empty(host.n_pcols, np.uint8)
    values = view_values(camera, tau)  # held: the call reads it
    _LIB.pmx_decide_all(_ptr(host.table), host.n_pcols, _ptr(values), flags_of(tests, camera.orthographic),
                        _ptr(out))
    return out


def _ptr(a: np.ndarray) -> int:
    return a.ctypes.data


def flags_of(tests, orthographic: bool) -> int:
    return (TEST_FRUSTUM * bool(tests.frustum) | TEST_ORIENTATION * bool(tests.orientation)
            | TEST_SCREEN * bool(tests.screen) | ORTHOGRAPHIC * bool(orthographic))


class _Scratch:
    """One thread's buffers for one mesh: the traversal's slots (capacity
    P), and the mesh's bitmaps and tables (zero between calls)."""

    def __init__(self, n_original, n_pcols, n_faces):
        P, V0 = n_pcols, n_original
        self.ids = np.empty(P, np.int32)
        self.kid = np.empty(2 * P, np.int32)
        self.state = np.empty(P, np.uint8)
        self.ran = np.empty(P, np.uint8)
        self.unsure = np.empty(P, np.int32)
        self.out = np.zeros(3, np.int64)
        # Front mesh.
        self.mark = np.zeros(P, np.uint8)
        self.start_bits = np.zeros(V0 // 64 + 1, np.uint64)
        self.face_bits = np.zeros(n_faces // 64 + 1, np.uint64)
        self.vertex_bits = np.zeros((V0 + P) // 64 + 1, np.uint64)
        self.rank_base = np.empty(V0 // 64 + 1, np.int32)
        self.owner_at = np.empty(V0, np.int32)
        self.sorted = np.empty(max(V0, 1), np.int32)
        self.new_index = np.empty(V0 + P, np.int32)


class NativeMesh:
    """Host arrays of one :class:`pmjax.ProgressiveMesh` for the C loops,
    built once per mesh (``pm.plan.host``), and per-thread scratch."""

    def __init__(self, pm):
        self.n_pcols, self.n_original, self.n_faces = pm.n_pcols, pm.n_original_vertices, pm.n_faces
        self.table = np.ascontiguousarray(np.asarray(pm.table), np.float32)
        self.children = np.ascontiguousarray(np.asarray(pm.children), np.int32)
        self.kills = np.ascontiguousarray(np.asarray(pm.kills), np.int32)
        self.roots = np.ascontiguousarray(np.asarray(pm.roots), np.int32)
        self.total_kills = int(self.kills.sum(dtype=np.int64))
        self._local = threading.local()
        self._mesh = None
        self._mesh_lock = threading.Lock()

    def scratch(self) -> _Scratch:
        s = getattr(self._local, "scratch", None)
        if s is None:
            s = self._local.scratch = _Scratch(self.n_original, self.n_pcols, self.n_faces)
        return s

    def counts(self, n_not_run: int, kept: int):
        """``(faces, vertices, executed)`` from the pcols that did not run."""
        n_exec = self.n_pcols - n_not_run
        return (np.int32(self.n_faces - self.total_kills + kept), np.int32(self.n_original - n_exec),
                np.int32(n_exec))

    def mesh_arrays(self, pm):
        """The front mesh's host arrays (:class:`pmjax._front_mesh._HostMesh`), int32."""
        with self._mesh_lock:
            if self._mesh is None:
                from ._front_mesh import _host

                h = _host(pm)
                c32 = lambda a: np.ascontiguousarray(a, np.int32)
                self._mesh = dict(
                    kill_starts=np.ascontiguousarray(h.kill_starts, np.int64), kill_faces=c32(h.kill_faces),
                    base_faces=c32(h.base_faces), pair=c32(h.pair), roots=c32(h.roots), lone=c32(h.lone),
                    start=c32(h.start), face_start=c32(h.face_start), vertices=h.vertices)
            return self._mesh


_HOST_LOCK = threading.Lock()


def native_mesh(pm) -> NativeMesh:
    with _HOST_LOCK:
        host = pm.plan.host.get("native")
        if host is None or host.n_faces != pm.n_faces:
            host = pm.plan.host["native"] = NativeMesh(pm)
        return host


@jax.jit
def _view_values(camera, tau):
    # The constants the dense engine computes inside its own kernel, by the
    # same function.
    return View.of(camera, tau).values


@jax.jit
def _views_values(cameras, tau):
    return View.batch(cameras, tau).values.T  # [K, 22]


def view_values(camera, tau) -> np.ndarray:
    """``float32[22]`` :class:`View` constants of one camera, as the dense engine sees them."""
    return np.ascontiguousarray(np.asarray(_view_values(camera, jnp.asarray(tau, jnp.float32))))


def views_values(cameras, tau) -> np.ndarray:
    """``float32[K, 22]`` for a camera batch."""
    return np.ascontiguousarray(np.asarray(_views_values(cameras, jnp.asarray(tau, jnp.float32))))


def _bucket(n: int) -> int:
    """Padded size of an unsure set: a power of two from 16 (few compilations)."""
    return max(16, 1 << int(np.ceil(np.log2(max(n, 1)))))


@functools.partial(jax.jit, static_argnames=("tests", "orthographic"))
def _decide(pm, ids, values, tests, orthographic):
    from ._front import _gathered
    from ._predicate import view_collapse_mask

    attrs, _ = _gathered(pm, ids)
    return view_collapse_mask(attrs, View(values, orthographic), tests, rows=False)


def decide_unsure(pm, ids: np.ndarray, values: np.ndarray, tests, orthographic: bool) -> np.ndarray:
    """The float32 predicate's own decisions for pcols ``ids`` (the unsure ones)."""
    n = len(ids)
    padded = np.zeros(_bucket(n), np.int32)
    padded[:n] = ids
    return np.asarray(_decide(pm, padded, jnp.asarray(values), tests, orthographic))[:n]


def refine_one(pm, camera, tau, tests):
    """One camera through the C traversal.

    Returns:
        ``(visited int32[n], executed bool[n], n_faces, n_vertices, n_executed)``.
    """
    host = native_mesh(pm)
    s = host.scratch()
    values = view_values(camera, tau)
    flags = flags_of(tests, camera.orthographic)
    n = _LIB.pmx_refine(_ptr(host.table), _ptr(host.children), _ptr(host.kills), host.n_pcols, _ptr(host.roots),
                        len(host.roots), _ptr(values), flags, _ptr(s.ids), _ptr(s.kid), _ptr(s.state),
                        _ptr(s.ran), _ptr(s.unsure), _ptr(s.out))
    n_unsure = int(s.out[0])
    if n_unsure:
        slots = s.unsure[:n_unsure]
        s.state[slots] = np.where(decide_unsure(pm, s.ids[slots], values, tests, camera.orthographic), YES, NO)
        _LIB.pmx_resolve(_ptr(host.kills), n, _ptr(s.ids), _ptr(s.kid), _ptr(s.state), _ptr(s.ran),
                         _ptr(s.out[1:]))
    return (s.ids[:n].copy(), s.ran[:n].astype(bool)) + host.counts(int(s.out[1]), int(s.out[2]))


def refine_many(pm, cameras, tau, tests, want_masks: bool, threads: int | None = None):
    """A camera batch through the C traversal, the cameras split over threads.

    Returns:
        ``(faces, vertices, executed_count)`` int32 ``[K]`` and, with
        ``want_masks``, ``executed bool[K, P]``.
    """
    from ._camera import index_camera

    host = native_mesh(pm)
    values = views_values(cameras, tau)
    K = values.shape[0]
    flags = flags_of(tests, cameras.orthographic)
    counts = np.zeros((K, 3), np.int64)
    status = np.zeros(K, np.uint8)
    masks = np.empty((K, host.n_pcols), np.uint8) if want_masks else None
    threads = max(1, min(threads or _cores(), K))

    def run(k0, k1):
        s = host.scratch()
        _LIB.pmx_refine_many(_ptr(host.table), _ptr(host.children), _ptr(host.kills), host.n_pcols,
                             _ptr(host.roots), len(host.roots), _ptr(values), flags, k0, k1, _ptr(s.ids),
                             _ptr(s.kid), _ptr(s.state), _ptr(s.ran), _ptr(s.unsure), _ptr(counts), _ptr(status),
                             _ptr(masks) if masks is not None else None)

    bounds = np.linspace(0, K, threads + 1).astype(int)
    if threads == 1:
        run(0, K)
    else:
        # ctypes releases the GIL for the call: the threads run in parallel.
        workers = [threading.Thread(target=run, args=(int(a), int(b))) for a, b in zip(bounds[:-1], bounds[1:])]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
    n_exec = host.n_pcols - counts[:, 1]
    faces = host.n_faces - host.total_kills + counts[:, 2]
    out = [faces.astype(np.int32), (host.n_original - n_exec).astype(np.int32), n_exec.astype(np.int32)]
    # A camera with an unsure decision is refined alone (it then asks the
    # float32 predicate for those pcols).
    for k in np.flatnonzero(status):
        ids, ran, f, v, e = refine_one(pm, index_camera(cameras, int(k)), tau[k] if np.ndim(tau) else tau, tests)
        out[0][k], out[1][k], out[2][k] = f, v, e
        if masks is not None:
            masks[k] = 1
            masks[k, ids[~ran]] = 0
    if masks is not None:
        out.append(masks.view(bool))
    return tuple(out)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def front_mesh(pm, visited: np.ndarray, visited_executed: np.ndarray, n_faces: int, n_vertices: int):
    """:func:`pmjax._front_mesh.front_mesh` through the C loop (same arrays)."""
    host = native_mesh(pm)
    m = host.mesh_arrays(pm)
    s = host.scratch()
    not_run = np.ascontiguousarray(visited[(visited < pm.n_pcols) & ~visited_executed], np.int32)
    faces = np.empty((n_faces, 3), np.int32)
    ids = np.empty(max(n_vertices, 1), np.int32)
    n_ids = _LIB.pmx_front_mesh(
        host.n_original, host.n_pcols, host.n_faces, _ptr(not_run), len(not_run), _ptr(m["kill_starts"]),
        _ptr(m["kill_faces"]), _ptr(m["base_faces"]), len(m["base_faces"]), _ptr(m["pair"]), _ptr(m["roots"]),
        len(m["roots"]), _ptr(m["lone"]), len(m["lone"]), _ptr(m["start"]), _ptr(m["face_start"]), n_faces,
        _ptr(faces), _ptr(ids), _ptr(s.mark), _ptr(s.start_bits), _ptr(s.face_bits), _ptr(s.vertex_bits),
        _ptr(s.rank_base), _ptr(s.owner_at), _ptr(s.sorted), _ptr(s.new_index))
    if n_ids < 0:
        raise RuntimeError("front mesh: the faces drawn do not match the refinement's face count")
    ids = ids[:n_ids].copy()
    return m["vertices"][ids], faces, ids
