"""The output-sensitive engine's C loops (``pmjax/_front_native.c``), called through ctypes.

On the CPU, the front traversal as JAX kernels pays a fixed cost of about a
dozen XLA kernels per generation of the pcol forest, whatever their size
(docs/front.md). The same traversal as a C loop costs only the pcols it
visits. Its results are the dense engine's bits:

- the subtree bound is :func:`pmjax._subtree.subtree_collapses`, with its
  margins and range guards, in float32 (sound as it is there: the margins
  dominate the rounding of the bound and of the tests below);
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

import contextlib
import ctypes
import functools
import importlib.util
import math
import os
import sys
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


def open_library(module: str):
    """The compiled extension ``module`` (a dotted name) as a ctypes library,
    or ``None`` where it is not built or ``PMJAX_NATIVE=0`` is set."""
    if os.environ.get("PMJAX_NATIVE", "1") == "0":
        return None
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin:
        return None
    return ctypes.CDLL(spec.origin)


def _load():
    lib = open_library("pmjax._front_native")
    if lib is None:
        return None
    lib.pmx_refine.restype = _i64
    lib.pmx_refine.argtypes = [_p, _p, _p, _i64, _p, _i64, _p, ctypes.c_int, _p, _p, _p, _p, _p, _p, _p, _p]
    lib.pmx_resolve.restype = None
    lib.pmx_resolve.argtypes = [_p, _p, _i64, _p, _p, _p, _p, _p, _p, _p]
    lib.pmx_refine_many.restype = _i64
    lib.pmx_refine_many.argtypes = [_p, _p, _p, _i64, _p, _i64, _p, ctypes.c_int, _i64, _i64] + [_p] * 14 + [
        _i64, _p]
    lib.pmx_refine_word.restype = _i64
    lib.pmx_refine_word.argtypes = [_p, _p, _p, _i64, _p, ctypes.c_int, ctypes.c_int] + [_p] * 9
    lib.pmx_count_words.restype = _i64
    lib.pmx_count_words.argtypes = [_p, _p, _p, _p, _i64, _p, _p, _i64, _i64, ctypes.c_int] + [_p] * 14 + [
        _i64, _p, _i64, _p]
    lib.pmx_unsure_nodes.restype = _i64
    lib.pmx_unsure_nodes.argtypes = [_p, _i64, _p, _p, _p, _p]
    lib.pmx_apply_unsure.restype = None
    lib.pmx_apply_unsure.argtypes = [_p, _i64, _i64, ctypes.c_int, _p, _p, _p, _p, _i64]
    lib.pmx_resolve_word.restype = None
    lib.pmx_resolve_word.argtypes = [_p, _p, _i64] + [_p] * 9
    lib.pmx_fat_cameras.restype = ctypes.c_int
    lib.pmx_fat_cameras.argtypes = [_p, _i64, ctypes.c_int, _p]
    lib.pmx_decide_fat_all.restype = None
    lib.pmx_decide_fat_all.argtypes = [_p, _i64, _p, ctypes.c_int, ctypes.c_int, _p, _p]
    lib.pmx_slot_loops.restype = ctypes.c_int
    lib.pmx_slot_loops.argtypes = [ctypes.c_int]
    lib.pmx_decide_all.restype = None
    lib.pmx_decide_all.argtypes = [_p, _i64, _p, ctypes.c_int, _p]
    lib.pmx_front_mesh.restype = _i64
    lib.pmx_front_mesh.argtypes = [_i64, _i64, _i64, _p, _p, _i64, _p, _p, _p, _p, _i64, _p, _p, _i64,
                                   _i64] + [_p] * 14
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
    (for comparisons); ``True`` restores the C loops where they are built.
    (A subclass with another ``switched`` module switches that module's
    ``_enabled`` flag instead.)"""

    switched = sys.modules[__name__]

    def __init__(self, on: bool):
        self.on = on

    def __enter__(self):
        self.before, self.switched._enabled = self.switched._enabled, self.on
        return self

    def __exit__(self, *exc):
        self.switched._enabled = self.before


# How the C loops keep their slots (pmx_slot_loops in _front_native.c).
SLOT_LOOPS = ("plain", "avx2", "avx512")


def slot_loops(kind: str | None = None) -> str:
    """How the C loops keep their slots (queue, children, bottom-up pass):
    ``"avx512"`` (mask instructions) or ``"avx2"`` where the processor has
    them, else ``"plain"``. ``kind`` switches that (to the best the
    processor has up to ``kind``; the results are the same bits) and the
    previous kind is returned (``"plain"`` where the C loops are not built).
    """
    if kind is not None and kind not in SLOT_LOOPS:
        raise ValueError(f"slot loops must be one of {SLOT_LOOPS}, got {kind!r}")
    if _LIB is None:
        return "plain"
    return SLOT_LOOPS[_LIB.pmx_slot_loops(-1 if kind is None else SLOT_LOOPS.index(kind))]


def decide_all(pm, camera, tau, tests) -> np.ndarray:
    """``uint8[P]``: every pcol's certified decision (``NO``, ``YES``,
    ``UNSURE``) with bit 4 set where its subtree bound decides its subtree."""
    host = native_mesh(pm)
    out = np.empty(host.n_pcols, np.uint8)
    values = host_view(camera, tau)  # held: the call reads it
    _LIB.pmx_decide_all(_ptr(host.table), host.n_pcols, _ptr(values), flags_of(tests, camera.orthographic),
                        _ptr(out))
    return out


# Floats of a fat camera (FAT_N in _front_native.c): eye 3, rho, pivot 3,
# rotation rows 9 (right, up, forward), t 3, eps, tau, start 3, step 3,
# 1 / |step|^2, capsule.
FAT_VALUES = 29
# The most frames one fat camera covers (FAT_MAX_FRAMES in _front_native.c).
FAT_MAX_FRAMES = 64


def fat_cameras(views: np.ndarray) -> np.ndarray:
    """The fat cameras of words of frames: per word, one set of bounds that
    covers all its frames (a ball and a capsule about the eyes, a reference
    rotation about the point the frames look at; "the fat camera of a word"
    in ``_front_native.c`` defines them), computed in double from the
    frames' constants and rounded up to float32, so that they hold for the
    exact values.

    Args:
        views: ``float32 [W, F, 22]``, the view constants
            (:func:`host_views`) of ``W`` words of ``F`` frames each,
            ``1 <= F <= FAT_MAX_FRAMES``.

    Returns:
        ``float32 [W, FAT_VALUES]``; a word whose bounds are not finite has
        NaN ones (under which nothing is decided at once).
    """
    views = np.ascontiguousarray(views, np.float32)
    if views.ndim != 3 or views.shape[2] != 22 or not 1 <= views.shape[1] <= FAT_MAX_FRAMES:
        raise ValueError(f"fat_cameras: views must be [W, F, 22] with 1 <= F <= {FAT_MAX_FRAMES}, got "
                         f"{views.shape}")
    out = np.empty((views.shape[0], FAT_VALUES), np.float32)
    _LIB.pmx_fat_cameras(_ptr(views), views.shape[0], views.shape[1], _ptr(out))
    return out


def decide_fat_all(pm, cameras, taus, tests) -> np.ndarray:
    """``uint8[P]``: every pcol under the fat camera of a few frames
    (``FAT_OPEN`` 0, ``FAT_WHOLE`` 1: every frame's subtree collapses,
    ``FAT_NO`` 2: no frame's own test collapses it); all 0 where the fat
    camera does not apply."""
    host = native_mesh(pm)
    out = np.empty(host.n_pcols, np.uint8)
    views = np.ascontiguousarray(host_views(cameras, taus), np.float32)
    fat = fat_cameras(views[None])[0]
    _LIB.pmx_decide_fat_all(_ptr(host.table), host.n_pcols, _ptr(views), len(views),
                            flags_of(tests, cameras.orthographic), _ptr(fat), _ptr(out))
    return out


def _ptr(a: np.ndarray) -> int:
    return a.ctypes.data


def flags_of(tests, orthographic: bool) -> int:
    return (TEST_FRUSTUM * bool(tests.frustum) | TEST_ORIENTATION * bool(tests.orientation)
            | TEST_SCREEN * bool(tests.screen) | ORTHOGRAPHIC * bool(orthographic))


# The records of the front mesh (PcolRecord, FaceRecord, FrontVertex in
# _front_native.c): all fields 4 bytes, so no padding on either side.
PCOL_RECORD = np.dtype([("kill_first", "<i4"), ("kill_count", "<i4"), ("vertex", "<i4", 2), ("start", "<i4", 2),
                        ("made_at", "<i4", 2), ("position", "<f4", (2, 3))])
FACE_RECORD = np.dtype([("face", "<i4"), ("start", "<i4", 3)])
FRONT_VERTEX = np.dtype([("start", "<i4"), ("vertex", "<i4"), ("position", "<f4", 3)])


class _Addresses:
    """Buffers whose addresses ``p_NAME`` (of array ``NAME``) are taken once."""

    def __getattr__(self, name):
        if name.startswith("p_"):
            value = _ptr(getattr(self, name[2:]))
            setattr(self, name, value)
            return value
        raise AttributeError(name)


class _Scratch(_Addresses):
    """One thread's buffers for one mesh: the traversal's slots (capacity
    P), and the mesh's bitmaps and tables (zero between calls); ``p_*`` are
    their addresses, taken once."""

    def __init__(self, n_original, n_pcols, n_faces):
        P, V0 = n_pcols, n_original
        self.ids = np.empty(P + 10, np.int32)  # spare slots (traverse and push_block_avx2 in _front_native.c)
        self.kid = np.empty(2 * P, np.int32)
        self.state = np.empty(P, np.uint8)
        self.kill = np.empty(P, np.int32)  # the faces each slot's pcol kills
        self.ran = np.empty(P + 4, np.uint8)  # resolve gathers 4 bytes a child (_front_native.c)
        self.pcols = np.empty(P, np.int32)
        self.unsure = np.empty(P, np.int32)
        # A mark per slot or position, zero between calls: the unsure records
        # of camera batches and the front mesh both use it.
        self.mark = np.zeros(P, np.uint8)
        # Camera batches' unsure records: each slot's parent slot, the chains'
        # slots, the int32 used.
        self.parent, self.chain = np.empty(P + 10, np.int32), np.empty(P, np.int32)
        self.used = np.zeros(1, np.int64)
        self.out = np.zeros(3, np.int64)
        # Front mesh: the pcols that did not run (marked by breadth-first
        # position), bitmaps (zero between calls), their prefix counts, the
        # front vertices as found and in depth-first order, the drawn faces,
        # each front vertex's output index.
        self.not_run_at = np.empty(P, np.int32)
        self.start_bits = np.zeros(V0 // 64 + 1, np.uint64)
        self.face_bits = np.zeros(n_faces // 64 + 1, np.uint64)
        self.vertex_bits = np.zeros((V0 + P) // 64 + 1, np.uint64)
        self.start_prefix = np.empty(V0 // 64 + 1, np.int32)
        self.face_prefix = np.empty(n_faces // 64 + 1, np.int32)
        self.vertex_prefix = np.empty((V0 + P) // 64 + 1, np.int32)
        self.front = np.empty(V0 + 1, FRONT_VERTEX)  # one slot past the front (_front_native.c)
        self.sorted = np.empty(max(V0, 1), FRONT_VERTEX)
        self.drawn = np.empty(max(n_faces, 1), FACE_RECORD)
        self.front_index = np.empty(max(V0, 1), np.int32)


def _cache_aligned(a: np.ndarray) -> np.ndarray:
    """A C-contiguous copy of ``a`` starting on a 64-byte boundary: a table
    row (16 float32) is then one cache line, where NumPy's own alignment (16
    bytes) can split every row over two (3.5 % of a dragon camera's time)."""
    buf = np.empty(a.nbytes + 64, np.uint8)
    skip = -buf.ctypes.data % 64
    out = buf[skip:skip + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


class NativeMesh:
    """Host arrays of one :class:`pmjax.ProgressiveMesh` for the C loops,
    built once per mesh (``pm.plan.host``), and per-thread scratch."""

    def __init__(self, pm):
        self.n_pcols, self.n_original, self.n_faces = pm.n_pcols, pm.n_original_vertices, pm.n_faces
        self.table = _cache_aligned(np.asarray(pm.table, np.float32))  # by pcol (decide_all)
        kills = np.asarray(pm.kills).astype(np.int32)
        self.total_kills = int(kills.sum(dtype=np.int64))
        # Breadth-first layout of the forest: the roots, then their created
        # children side by side, generation by generation, so that a pruned
        # breadth-first walk reads the table in increasing order.
        children = np.asarray(pm.children)
        level, order, first, count = np.asarray(pm.roots).astype(np.int64), [], [], []
        placed = 0
        while len(level):
            order.append(level)
            kids = children[level]
            n_kids = (kids >= 0).sum(1)
            placed += len(level)
            first.append(placed + np.concatenate([[0], np.cumsum(n_kids)[:-1]]))
            count.append(n_kids)
            level = kids.reshape(-1)[kids.reshape(-1) >= 0].astype(np.int64)
        order = np.concatenate(order) if order else np.zeros(0, np.int64)
        first = np.concatenate(first) if first else np.zeros(0, np.int64)
        count = np.concatenate(count) if count else np.zeros(0, np.int64)
        if len(order) != self.n_pcols:  # every pcol lies below a root (the structure check's forest)
            raise ValueError(f"the pcol forest reaches {len(order)} of {self.n_pcols} pcols from its roots")
        self.order = order.astype(np.int32)
        # Each row's last column (1 / |axis|, which the C loops do not read)
        # holds its first child's position << 2 | its number of children, and
        # in its sign bit whether the pcol kills other than two faces (KIDS in
        # _front_native.c).
        self.bfs_kills = np.ascontiguousarray(kills[order])
        if self.n_pcols >= 1 << 29:
            raise ValueError(f"{self.n_pcols} pcols: the C loops hold positions below 2^29")
        kids = (first << 2) | count | (self.bfs_kills != 2).astype(np.int64) << 31
        self.bfs_table = _cache_aligned(self.table[order])
        self.bfs_table[:, -1] = kids.astype(np.uint32).view(np.float32)
        self._pm = pm
        self.roots = np.arange(len(np.asarray(pm.roots)), dtype=np.int32)  # positions
        self._local = threading.local()
        self._pool, self._pool_lock = [], threading.Lock()
        self._mesh = None
        self._mesh_lock = threading.Lock()

    @functools.cached_property
    def below_table(self) -> np.ndarray:
        """``bfs_table`` with the bounds over each pcol's subtree replaced by
        the bounds over the pcols strictly below it
        (:func:`pmjax._subtree.below_bounds`): the one-camera traversal decides
        a pcol by its own test and leaves its children unvisited where those
        say that everything below collapses."""
        from ._front import TABLE_ATTRIBUTES, TABLE_BOUNDS
        from ._subtree import below_bounds, front_bounds

        pm = self._pm
        center, axis = np.asarray(pm.attributes.center).T, np.asarray(pm.attributes.axis).T
        subtree = {k: np.asarray(getattr(pm.subtree, k)) for k in ("reach", "spread", "cone", "error")}
        rows = front_bounds(below_bounds(center, axis, subtree, np.asarray(pm.child1), np.asarray(pm.child2)), axis.T)
        table = _cache_aligned(self.bfs_table)
        first = len(TABLE_ATTRIBUTES) + 4  # center and axis take three columns each
        for i, k in enumerate(("reach", "spread", "facing", "error")):
            assert TABLE_BOUNDS[i] == k
            table[:, first + i] = rows[k][self.order]
        return table

    def __getattr__(self, name):  # p_NAME: the address of array NAME, taken once
        if name.startswith("p_"):
            value = _ptr(getattr(self, name[2:]))
            setattr(self, name, value)
            return value
        raise AttributeError(name)

    def scratch(self) -> _Scratch:
        s = getattr(self._local, "scratch", None)
        if s is None:
            s = self._local.scratch = _Scratch(self.n_original, self.n_pcols, self.n_faces)
        return s

    @contextlib.contextmanager
    def borrowed(self):
        """A scratch that no other thread uses meanwhile, kept for later
        calls by any thread (fresh buffers would cost their page faults
        again)."""
        with self._pool_lock:
            s = self._pool.pop() if self._pool else None
        if s is None:
            s = _Scratch(self.n_original, self.n_pcols, self.n_faces)
        try:
            yield s
        finally:
            with self._pool_lock:
                self._pool.append(s)

    def counts(self, n_not_run, kept):
        """``(faces, vertices, executed)`` (int32) from the pcols that did not
        run and the faces they keep: numbers, or arrays of them."""
        n_exec = self.n_pcols - n_not_run
        return (np.int32(self.n_faces - self.total_kills + kept), np.int32(self.n_original - n_exec),
                np.int32(n_exec))

    def mesh_arrays(self, pm) -> dict:
        """The front mesh's records, built once from the depth-first layout of
        :class:`pmjax._front_mesh._HostMesh`: per pcol its two vertices with
        their starts and positions and its kill list's place; per killed face
        (in kill order) and per base face, the face and its corners' starts;
        the tops (roots, with their breadth-first position, and lone
        originals, with -1)."""
        with self._mesh_lock:
            if self._mesh is None:
                from ._front_mesh import _host

                h = _host(pm)
                # By breadth-first position, kill lists concatenated in that
                # order: a refinement's pcols are read in nearly increasing order.
                pair, count = h.pair[self.order], np.diff(h.kill_starts)[self.order]
                first = np.concatenate([[0], np.cumsum(count)[:-1]])
                killed = h.kill_faces[np.repeat(h.kill_starts[:-1][self.order] - first, count) +
                                      np.arange(int(count.sum()))]
                records = np.zeros(self.n_pcols, PCOL_RECORD)
                records["kill_first"] = first
                records["kill_count"] = count
                records["vertex"] = pair
                records["start"] = h.start[pair]
                # Where the pcol that made each vertex sits (-1: an original).
                at = np.empty(self.n_pcols, np.int32)
                at[self.order] = np.arange(self.n_pcols, dtype=np.int32)
                made = pair - self.n_original
                records["made_at"] = np.where(made >= 0, at[np.maximum(made, 0)], -1)
                records["position"] = h.vertices[pair]
                faces = lambda ids: np.rec.fromarrays([ids, h.face_start[ids]], dtype=FACE_RECORD)
                top_vertex = np.concatenate([self.n_original + h.roots, h.lone])
                tops = np.rec.fromarrays([h.start[top_vertex], top_vertex, h.vertices[top_vertex]],
                                         dtype=FRONT_VERTEX)
                self._mesh = dict(records=records, kill_data=faces(killed), base=faces(h.base_faces),
                                  tops=tops, top_at=np.concatenate([at[h.roots], np.full(len(h.lone), -1)]).astype(
                                      np.int32))
                # Their addresses, taken once (a few microseconds each).
                self._mesh.update({"p_" + k: _ptr(v) for k, v in list(self._mesh.items())})
            return self._mesh


_HOST_LOCK = threading.Lock()


def native_mesh(pm) -> NativeMesh:
    with _HOST_LOCK:
        host = pm.plan.host.get("native")
        if host is None or host.n_faces != pm.n_faces:
            host = pm.plan.host["native"] = NativeMesh(pm)
        return host


def host_view(camera, tau) -> np.ndarray:
    """``float32[22]``: :func:`host_views` of one camera, in scalar arithmetic
    (a quarter of the time of the array version on one camera)."""
    f = lambda a: float(np.asarray(a))
    eye, rot = np.asarray(camera.eye, np.float64).reshape(3), np.asarray(camera.rotation, np.float64).reshape(3, 3)
    near, far, width, height = f(camera.near), f(camera.far), f(camera.width), f(camera.height)
    aspect = width / height
    if camera.orthographic:
        ortho_height = f(camera.ortho_height)
        b_y = 0.5 * ortho_height
        consts = [0.0, 0.0, b_y * aspect, b_y, 1.0, 1.0]
        unit = ortho_height / height
    else:
        a_y = math.tan(0.5 * f(camera.fov_y))
        a_x = a_y * aspect
        consts = [a_x, a_y, 0.0, 0.0, math.sqrt(1 + a_x * a_x), math.sqrt(1 + a_y * a_y)]
        unit = 2 * a_y / height
    kappa = unit * float(tau)
    values = list(eye) + list(rot[:, 0]) + list(rot[:, 1]) + list(-rot[:, 2]) + consts + [near, far, unit]
    with np.errstate(over="ignore"):
        return np.array(values + [kappa * kappa], np.float32)


def host_views(cameras, tau) -> np.ndarray:
    """``float32[K, 22]`` :class:`View` constants of a camera batch (or
    ``[22]`` of one camera), computed on the host.

    Eye, axes and clip distances are the camera's own float32 values, as in
    :class:`View`; the slopes, plane scales and ``kappa²`` come from
    ``tan``/``sqrt`` in float64 here and in float32 in XLA, so they differ by
    a few float32 ulps, inside the 2^-20 relative the C certification allows
    (``VIEW`` in ``_front_native.c``; tests/test_native.py checks 2^-21).
    Computing them here saves a compiled call per camera.
    """
    f64 = lambda a: np.asarray(a, np.float64)
    eye, rot = f64(cameras.eye), f64(cameras.rotation)
    single = eye.ndim == 1
    eye, rot = eye.reshape(-1, 3), rot.reshape(-1, 3, 3)
    n = len(eye)
    col = lambda a: np.broadcast_to(f64(a).reshape(-1), (n,))
    fov, near, far, ortho_height = col(cameras.fov_y), col(cameras.near), col(cameras.far), col(cameras.ortho_height)
    width, height = col(cameras.width), col(cameras.height)
    aspect = width / height
    zero, one = np.zeros(n), np.ones(n)
    if cameras.orthographic:
        b_y = 0.5 * ortho_height
        consts = [zero, zero, b_y * aspect, b_y, one, one]
        unit = ortho_height / height
    else:
        a_y = np.tan(0.5 * fov)
        a_x = a_y * aspect
        consts = [a_x, a_y, zero, zero, np.sqrt(1 + a_x * a_x), np.sqrt(1 + a_y * a_y)]
        unit = 2 * a_y / height
    kappa = unit * col(tau)
    out = np.concatenate([eye, rot[:, :, 0], rot[:, :, 1], -rot[:, :, 2], np.stack(consts + [near, far], 1),
                          unit[:, None], (kappa * kappa)[:, None]], axis=1)
    with np.errstate(over="ignore"):
        out = np.ascontiguousarray(out, np.float32)
    return out[0] if single else out


@jax.jit
def _view_values(camera, tau):
    # The constants the dense engine computes inside its own kernel, by the
    # same function.
    return View.of(camera, tau).values


def view_values(camera, tau) -> np.ndarray:
    """``float32[22]`` :class:`View` constants of one camera, as the dense engine
    sees them (XLA's own; the unsure decisions are asked with these)."""
    return np.ascontiguousarray(np.asarray(_view_values(camera, jnp.asarray(tau, jnp.float32))))


def _bucket(n: int) -> int:
    """Padded size of an unsure set: a power of two from 16 (few compilations)."""
    return max(16, 1 << int(np.ceil(np.log2(max(n, 1)))))


@functools.partial(jax.jit, static_argnames=("tests", "orthographic"))
def _decide(rows, values, tests, orthographic):
    from ._front import table_columns
    from ._predicate import view_collapse_mask

    attrs, _ = table_columns(rows.T)
    return view_collapse_mask(attrs, View(values, orthographic), tests, rows=False)


def _rows(host, pcols: np.ndarray) -> np.ndarray:
    """Table rows of ``pcols`` padded to a :func:`_bucket` (gathered here: a
    compiled call that takes the mesh's arrays and gathers them measured 1.5x
    the dispatch time, 0.28 against 0.18 ms)."""
    padded = np.zeros(_bucket(len(pcols)), np.int64)
    padded[:len(pcols)] = pcols
    return host.table[padded]


def decide_unsure(pm, ids: np.ndarray, values: np.ndarray, tests, orthographic: bool) -> np.ndarray:
    """The float32 predicate's own decisions for pcols ``ids`` (the unsure ones)."""
    rows = _rows(native_mesh(pm), ids)
    return np.asarray(_decide(rows, jnp.asarray(values), tests, orthographic))[:len(ids)]


def refine_one(pm, camera, tau, tests, lists: bool = True):
    """One camera through the C traversal (``lists=False``: the counts only).

    Returns:
        ``(visited int32[n], executed bool[n], positions int32[n], n_faces,
        n_vertices, n_executed)``: the visited pcols, whether each ran, and
        their breadth-first positions (what the C front mesh reads).
    """
    host = native_mesh(pm)
    s = host.scratch()
    values = host_view(camera, tau)
    flags = flags_of(tests, camera.orthographic)
    n = _LIB.pmx_refine(host.p_below_table, host.p_bfs_kills, host.p_order, host.n_pcols, host.p_roots,
                        len(host.roots), _ptr(values), flags, s.p_ids, s.p_kid, s.p_state, s.p_kill, s.p_ran,
                        s.p_pcols, s.p_unsure, s.p_out)
    n_unsure = int(s.out[0])
    if n_unsure:
        slots = s.unsure[:n_unsure]
        # Asked of the float32 predicate with XLA's own constants.
        exact = view_values(camera, tau)
        pcols = host.order[s.ids[slots]]  # ids hold positions
        s.state[slots] = np.where(decide_unsure(pm, pcols, exact, tests, camera.orthographic), YES, NO)
        _LIB.pmx_resolve(host.p_bfs_kills, host.p_order, n, s.p_ids, s.p_kid, s.p_state, s.p_kill, s.p_ran,
                         s.p_pcols, _ptr(s.out[1:]))
    counts = host.counts(int(s.out[1]), int(s.out[2]))
    if not lists:
        return counts
    return (s.pcols[:n].copy(), s.ran[:n].view(bool).copy(), s.ids[:n].copy()) + counts


@functools.partial(jax.jit, static_argnames=("tests", "orthographic"))
def _decide_pairs(rows, cameras, tau, tests, orthographic):
    """The float32 predicate's decision for table row ``rows[i]`` under camera ``i``."""
    from ._front import table_columns
    from ._predicate import view_collapse_mask

    attrs, _ = table_columns(rows.T)
    views = View.batch(cameras, tau)
    one = lambda a, v: view_collapse_mask(a, View(v, orthographic), tests, rows=False)
    return jax.vmap(one, in_axes=(0, 1))(jax.tree.map(lambda x: x.T[:, :, None] if x.ndim == 2 else x[:, None],
                                                      attrs), views.values)[:, 0]


def counts_one(pm, camera, tau, tests):
    """``(n_faces, n_vertices, n_executed)`` of one camera through the C
    traversal, without the lists (:func:`refine_one`)."""
    return refine_one(pm, camera, tau, tests, lists=False)


def faces_for_budget(pm, camera, budget: int, tests):
    """:func:`pmjax.faces_for_budget` from exact counts of the C traversal.

    The face count is non-increasing in ``tau`` and non-negative float32 values
    are ordered as their bit patterns, so the answer (the smallest ``tau``
    whose count is not above ``budget``) is the upper end of a bracket of two
    adjacent patterns, one count above the budget and one within it: the same
    answer as the sort of every pcol's critical tolerance. The bracket is
    found by steps of 8x from ``tau = 1`` (``tau = 0`` and ``inf``, whose
    fronts are the largest, only when the search reaches them) and narrowed
    by regula falsi on ``log tau``, every third step a midpoint of the patterns;
    11-36 refinements (about 24 typically, bunny and dragon), each costing
    what its front costs.
    """
    faces = lambda t: int(counts_one(pm, camera, np.float32(t), tests)[0])
    bits = lambda t: int(np.float32(t).view(np.int32))
    value = lambda b: np.int32(b).view(np.float32)
    # Bracket: lo above the budget, hi within it.
    t = np.float32(1.0)
    f = faces(t)
    if f <= budget:
        hi, f_hi = t, f
        while True:
            t = np.float32(t / 8)
            if t < np.float32(1e-30):
                f0 = faces(0.0)
                if f0 <= budget:
                    return np.float32(0.0), f0
                lo, f_lo = np.float32(0.0), f0
                break
            f = faces(t)
            if f > budget:
                lo, f_lo = t, f
                break
            hi, f_hi = t, f
    else:
        lo, f_lo = t, f
        while True:
            t = np.float32(t * 8)
            if t > np.float32(1e30):
                f_inf = faces(np.inf)
                if f_inf > budget:
                    return np.float32(np.inf), f_inf
                hi, f_hi = np.float32(np.inf), f_inf
                break
            f = faces(t)
            if f <= budget:
                hi, f_hi = t, f
                break
            lo, f_lo = t, f
    # Narrow to adjacent patterns: regula falsi on log tau (the Illinois
    # variant: an end kept twice has its weight halved), every third step the
    # midpoint of the patterns, so that the bracket at least halves in bits.
    lo_b, hi_b = bits(lo), bits(hi)
    w_lo, w_hi = f_lo - budget - 0.5, f_hi - budget - 0.5  # > 0, < 0
    kept, step = None, 0
    while hi_b - lo_b > 1:
        step += 1
        guess = lo_b + (hi_b - lo_b) // 2
        if step % 3 and lo > 0 and np.isfinite(hi):
            x_lo, x_hi = np.log(float(lo)), np.log(float(hi))
            g = bits(np.exp(x_lo + (x_hi - x_lo) * w_lo / (w_lo - w_hi)))
            guess = min(max(g, lo_b + 1), hi_b - 1)
        t = value(guess)
        f = faces(t)
        if f <= budget:
            hi_b, hi, f_hi, w_hi = guess, t, f, f - budget - 0.5
            w_lo = w_lo / 2 if kept == "lo" else w_lo
            kept = "lo"
        else:
            lo_b, lo, f_lo, w_lo = guess, t, f, f - budget - 0.5
            w_hi = w_hi / 2 if kept == "hi" else w_hi
            kept = "hi"
    return value(hi_b), f_hi


def _refine_part(host, s, values, flags, K, cursor, counts, masks) -> np.ndarray:
    """Cameras of a batch of ``K`` taken one at a time from ``cursor``
    (int64[1], shared by the threads) through pmx_refine_many with scratch
    ``s``, its records growing as needed; returns their records."""
    records = np.empty(RECORD_ROOM, np.int32)
    s.used[0] = 0
    k = -1  # none to redo: the first from the cursor
    while True:
        k = _LIB.pmx_refine_many(host.p_below_table, host.p_bfs_kills, host.p_order, host.n_pcols, host.p_roots,
                                 len(host.roots), _ptr(values), flags, k, K, _ptr(cursor), s.p_ids, s.p_kid,
                                 s.p_state, s.p_kill, s.p_ran, s.p_pcols, s.p_unsure, _ptr(counts),
                                 None if masks is None else _ptr(masks), s.p_parent, s.p_chain, s.p_mark,
                                 _ptr(records), len(records), s.p_used)
        if k >= K:
            return records[:s.used[0]]
        # camera k's record did not fit: twice the room, and on with k
        larger = np.empty(2 * len(records), np.int32)
        larger[:s.used[0]] = records[:s.used[0]]
        records = larger


_POOL, _POOL_SIZE = None, 0
_POOL_LOCK = threading.Lock()


def _helpers(task, n: int) -> list:
    """``task`` submitted ``n`` times to the batch's helper threads, started
    once and kept (starting a thread held the calling thread 0.25 ms more,
    2-3 % of a dragon batch); returns the futures."""
    global _POOL, _POOL_SIZE
    with _POOL_LOCK:  # submitted under the lock: a larger pool may replace this one
        if _POOL_SIZE < n:
            import concurrent.futures

            if _POOL is not None:  # its threads end once idle
                _POOL.shutdown(wait=False)
            _POOL, _POOL_SIZE = concurrent.futures.ThreadPoolExecutor(n, thread_name_prefix="pmjax-front"), n
        return [_POOL.submit(task) for _ in range(n)]


def refine_many(pm, cameras, tau, tests, want_masks: bool, threads: int | None = None):
    """A camera batch through the C traversal, the cameras shared by threads.

    The calling thread and ``threads - 1`` helpers (default: one per core)
    take the cameras one at a time from a shared cursor, so they finish
    together however the cameras' costs differ. A camera with unsure
    decisions is resolved as if each were "keep" and leaves a record of the
    slots they can change (as :func:`count_words`); the pairs of the whole
    batch are decided in one call of the float32 predicate and the cameras'
    counts and masks corrected.

    Returns:
        ``(faces, vertices, executed_count)`` int32 ``[K]`` and, with
        ``want_masks``, ``executed bool[K, P]``.
    """
    host = native_mesh(pm)
    values = host_views(cameras, tau)
    K = values.shape[0]
    flags = flags_of(tests, cameras.orthographic)
    counts = np.zeros((K, 3), np.int64)
    masks = np.empty((K, host.n_pcols), np.uint8) if want_masks else None
    threads = max(1, min(threads or _cores(), K))
    cursor = np.zeros(1, np.int64)

    def run():
        with host.borrowed() as s:
            return _refine_part(host, s, values, flags, K, cursor, counts, masks)

    # ctypes releases the GIL for the call: the threads run in parallel.
    helpers = _helpers(run, threads - 1) if threads > 1 else []
    found = []
    try:
        found.append(run())
    finally:
        # A helper that has not started (the pool busy with another batch)
        # is not waited for: the cameras are done.
        found += [h.result() for h in helpers if not h.cancel()]
    not_run, kept = counts[:, 1].copy(), counts[:, 2].copy()
    records = np.concatenate(found)
    if len(records):
        _decide_records(host, records, np.arange(K), cameras, np.broadcast_to(np.asarray(tau, np.float32), (K,)),
                        tests, 0, 1, not_run, kept, masks)
    n_exec = host.n_pcols - not_run
    faces = host.n_faces - host.total_kills + kept
    out = [faces.astype(np.int32), (host.n_original - n_exec).astype(np.int32), n_exec.astype(np.int32)]
    if masks is not None:
        out.append(masks.view(bool))
    return tuple(out)


# Frames of a path traversed together (FRAMES in _front_native.c).
FRAMES = 16


class _WordScratch(_Addresses):
    """One thread's buffers for words of FRAMES frames (capacity P slots;
    ``p_*`` their addresses)."""

    def __init__(self, n_pcols):
        P = n_pcols
        self.ids, self.kid, self.pcols = np.empty(P, np.int32), np.empty(2 * P, np.int32), np.empty(P, np.int32)
        self.visit, self.whole, self.yes, self.ran = (np.empty(P, np.uint16) for _ in range(4))
        self.unsure_slots, self.unsure_lanes = np.empty(P, np.int32), np.empty(P, np.uint16)
        self.out = np.zeros(3, np.int64)  # unsure slots, slots, slots decided by the fat camera
        self.not_run, self.kept = np.zeros(FRAMES, np.int64), np.zeros(FRAMES, np.int64)
        # Records of words with unsure pairs (pmx_count_words): each slot's
        # parent, the chains' slots, a mark per slot (zero between calls).
        self.parent, self.chain, self.mark = np.empty(P, np.int32), np.empty(P, np.int32), np.zeros(P, np.uint8)
        self.used = np.zeros(1, np.int64)


def _word_scratch(host) -> _WordScratch:
    s = getattr(host._local, "words", None)
    if s is None:
        s = host._local.words = _WordScratch(host.n_pcols)
    return s


def _decide_lanes(host, positions, lanes, lane_frames, cameras, taus, tests) -> np.ndarray:
    """The float32 predicate's decisions for the unsure frames of a few
    slots, all in one call.

    Args:
        positions: ``[m]`` the slots' breadth-first positions.
        lanes: ``[m]`` each slot's unsure frames (bit l: lane l).
        lane_frames: ``int [m, FRAMES]`` the frame in ``cameras`` of each
            slot's lanes.
        cameras, taus: the frames.

    Returns:
        ``uint16 [m]``: the frames (bits) whose decision is yes.
    """
    lanes = np.asarray(lanes, np.int64)
    out = np.zeros(len(lanes), np.uint16)
    # Every (slot, frame) pair.
    slot_of, lane_of = np.nonzero((lanes[:, None] >> np.arange(FRAMES)) & 1)
    if len(slot_of) == 0:
        return out
    yes = _decide_pairs_at(host, np.asarray(positions)[slot_of], np.asarray(lane_frames)[slot_of, lane_of], cameras,
                           taus, tests)
    np.bitwise_or.at(out, slot_of[yes], (1 << lane_of[yes]).astype(np.uint16))
    return out


def _decide_pairs_at(host, positions, frames, cameras, taus, tests) -> np.ndarray:
    """``bool [n]``: the float32 predicate's decision for the pcol at
    breadth-first position ``positions[i]`` under frame ``frames[i]`` of
    ``cameras`` (with ``taus``), all in one call padded to a :func:`_bucket`."""
    n = len(positions)
    if n == 0:
        return np.zeros(0, bool)
    pad = np.zeros(_bucket(n), np.int64)
    pad[:n] = np.arange(n)
    frame = np.asarray(frames)[pad]
    batch = jax.tree.map(lambda a: np.asarray(a)[frame] if np.ndim(a) else a, cameras)
    return np.asarray(_decide_pairs(_rows(host, host.order[np.asarray(positions)[pad]]), batch,
                                    np.asarray(taus, np.float32)[frame], tests, cameras.orthographic))[:n]


def count_words(pm, cameras, taus, tests, values, fats=None, first_word=0):
    """Whole words of FRAMES frames through the C word traversal, counts only.

    A word with unsure decisions is counted as if each were "keep" and
    leaves a record of the slots whose outcome they can change (their chains
    to the roots); :func:`resolve_unsure` decides the pairs of many words in
    one call of the float32 predicate (a call costs 0.3-1 ms after a
    traversal, whatever its size) and corrects their counts.

    Args:
        cameras: a host camera batch of ``W * FRAMES`` frames, word by word.
        taus: ``float32 [W * FRAMES]``.
        values: the frames' :func:`host_views`.
        fats: the words' :func:`fat_cameras`, or ``None`` (every frame
            decided alone).
        first_word: the number of the first word in the records (its lanes
            start at ``first_word * FRAMES`` in the arrays
            :func:`resolve_unsure` corrects).

    Returns:
        ``(not_run, kept, records)``: int64 per lane, the pcols that did not
        run and the faces they keep (:meth:`NativeMesh.counts` makes the
        counts), unsure pairs taken as "keep"; and the words' records
        (int32) for :func:`resolve_unsure`.
    """
    host = native_mesh(pm)
    s = _word_scratch(host)
    views = np.ascontiguousarray(values, np.float32)
    words = len(views) // FRAMES
    fat = None if fats is None else np.ascontiguousarray(fats, np.float32)  # the C loops check it applies
    not_run, kept = np.zeros(words * FRAMES, np.int64), np.zeros(words * FRAMES, np.int64)
    flags = flags_of(tests, cameras.orthographic)
    found = np.empty(RECORD_ROOM, np.int32)
    s.used[0] = 0
    w = 0
    while True:
        w = _LIB.pmx_count_words(host.p_bfs_table, host.p_bfs_kills, host.p_order, host.p_roots, len(host.roots),
                                 _ptr(views), None if fat is None else _ptr(fat), w, words, flags, s.p_ids,
                                 s.p_kid, s.p_visit, s.p_whole, s.p_yes, s.p_ran, s.p_unsure_slots,
                                 s.p_unsure_lanes, s.p_out, _ptr(not_run), _ptr(kept), s.p_parent, s.p_chain,
                                 s.p_mark, first_word, _ptr(found), len(found), s.p_used)
        if w == words:
            break
        # Word w's record did not fit: twice the room, and on from w (traversed again).
        larger = np.empty(2 * len(found), np.int32)
        larger[:s.used[0]] = found[:s.used[0]]
        found = larger
    return not_run, kept, found[:s.used[0]].copy()


def resolve_unsure(pm, records, lane_frames, cameras, taus, tests, not_run, kept, first_word=0):
    """The unsure pairs of :func:`count_words`' records decided in one call
    of the float32 predicate, and the counts of their words corrected.

    Args:
        records: int32, records concatenated.
        lane_frames: ``int [L]`` the frame in ``cameras`` of each lane of
            ``not_run``.
        not_run, kept: ``int64 [L]``, lane ``l`` of word ``w`` at
            ``(w - first_word) * FRAMES + l``; corrected in place.
    """
    records = np.ascontiguousarray(records, np.int32)
    if len(records):
        _decide_records(native_mesh(pm), records, lane_frames, cameras, taus, tests, first_word, FRAMES, not_run,
                        kept, None)


def _decide_records(host, records, lane_frames, cameras, taus, tests, first_word, frames, not_run, kept, masks):
    """The unsure pairs of records (int32, concatenated; words of ``frames``
    lanes, ``frames`` 1 for single cameras) decided in one call, their yes
    bits set and the lanes' counts (and executed ``masks [L, P]``, if given)
    corrected in place."""
    n = len(records) // NODE_VALUES + 1  # at least one node per record
    at, word, positions, lanes = np.empty(n, np.int64), np.empty(n, np.int32), np.empty(n, np.int32), \
        np.empty(n, np.int32)
    m = _LIB.pmx_unsure_nodes(_ptr(records), len(records), _ptr(at), _ptr(word), _ptr(positions), _ptr(lanes))
    if frames == 1:  # single cameras: each unsure node is one pair, its yes bit 1
        yes = _decide_pairs_at(host, positions[:m], np.asarray(lane_frames)[word[:m] - first_word], cameras, taus,
                               tests)
    else:
        first_lane = (word[:m].astype(np.int64) - first_word) * frames
        lane_frames = np.concatenate([np.asarray(lane_frames), np.zeros(FRAMES, np.int64)])  # lanes past a word's
        yes = _decide_lanes(host, positions[:m], lanes[:m], lane_frames[first_lane[:, None] + np.arange(FRAMES)],
                            cameras, taus, tests)
    records[at[:m]] |= yes.astype(np.int32)
    _LIB.pmx_apply_unsure(_ptr(records), len(records), first_word, frames, _ptr(not_run), _ptr(kept), host.p_order,
                          None if masks is None else _ptr(masks), host.n_pcols)


# int32 per node of a record (NODE_N in _front_native.c), and the room for
# records a count_words call starts with (it grows when a word needs more).
NODE_VALUES = 12
RECORD_ROOM = 1 << 14


def refine_word(pm, cameras, taus, tests, frames: bool, values=None, fat=True):
    """Up to FRAMES consecutive frames of a path through the C word traversal.

    Args:
        cameras: a host camera batch of at most FRAMES consecutive frames.
        taus: ``float32`` per frame.
        frames: also return each frame's lists for a :class:`pmjax.Refinement`.
        values: the frames' :func:`host_views`, if the caller has them.
        fat: decide a pcol for all frames at once where a fat camera
            (:func:`fat_cameras`) can: ``True``, or the frames'
            :func:`fat_cameras` row if the caller has it;
            ``False`` decides every frame alone (the same results; for
            comparison).

    Returns:
        ``(counts, lists, union, at_once)``: ``counts`` ``(faces, vertices,
        executed)`` int arrays over the frames; ``lists``, with ``frames``,
        per frame ``(visited, executed, positions)`` (else ``None``): the
        word's slots for every frame, each frame's own ran bits;
        ``union`` the pcols the word visited, ``at_once`` those the fat
        camera decided for every frame.
    """
    host = native_mesh(pm)
    word = np.ascontiguousarray(host_views(cameras, taus) if values is None else values)
    nf = word.shape[0]
    s = _word_scratch(host)
    # The frames at once where they decide alike (the C loops check that
    # the fat camera applies: perspective, usual tests, shared intrinsics).
    if fat is True:
        fat = fat_cameras(word[None])[0]
    fat = None if fat is False else np.ascontiguousarray(fat, np.float32)
    n = _LIB.pmx_refine_word(host.p_bfs_table, host.p_order, host.p_roots, len(host.roots), _ptr(word),
                             nf, flags_of(tests, cameras.orthographic), None if fat is None else _ptr(fat),
                             s.p_ids, s.p_kid, s.p_visit, s.p_whole, s.p_yes, s.p_unsure_slots, s.p_unsure_lanes,
                             s.p_out)
    m = int(s.out[0])
    if m:
        slots = s.unsure_slots[:m]
        s.yes[slots] |= _decide_lanes(host, s.ids[slots], s.unsure_lanes[:m],
                                      np.broadcast_to(np.minimum(np.arange(FRAMES), nf - 1), (m, FRAMES)), cameras,
                                      taus, tests)
    # Each slot's pcol only for the frames' lists (a read at random per slot).
    _LIB.pmx_resolve_word(host.p_bfs_kills, host.p_order, n, s.p_ids, s.p_kid, s.p_visit, s.p_whole, s.p_yes,
                          s.p_ran, s.p_pcols if frames else None, s.p_not_run, s.p_kept)
    counts = host.counts(s.not_run[:nf], s.kept[:nf])
    at_once = int(s.out[2])
    if not frames:
        return counts, None, n, at_once
    # Every frame lists the word's slots: a slot a frame did not visit lies
    # under a subtree decided for it, so it ran (its ran bit is set). One
    # copy of the slots per word, each frame's ran bits a row of one array.
    pcols, at = s.pcols[:n].copy(), s.ids[:n].copy()
    bits = np.unpackbits(s.ran[:n].view(np.uint8).reshape(n, 2), axis=1, bitorder="little").T.copy().view(bool)
    return counts, [(pcols, bits[lane], at) for lane in range(nf)], n, at_once


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def front_mesh(pm, visited: np.ndarray, visited_executed: np.ndarray, positions: np.ndarray, n_faces: int,
               n_vertices: int):
    """:func:`pmjax._front_mesh.front_mesh` through the C loop (same arrays).

    Args:
        visited: the visited pcols (as for the NumPy version; the loop reads
            their ``positions`` instead).
        positions: the visited pcols' breadth-first positions (from :func:`refine_one`).
        n_faces, n_vertices: the refinement's counts (the sizes of the output;
            the vertices used are at most the front).
    """
    host = native_mesh(pm)
    m = host.mesh_arrays(pm)
    s = host.scratch()
    ran = np.ascontiguousarray(visited_executed).view(np.uint8)
    at = np.ascontiguousarray(positions, np.int32)
    faces = np.empty((n_faces, 3), np.int32)
    ids = np.empty(max(n_vertices, 1), np.int32)
    positions = np.empty((max(n_vertices, 1), 3), np.float32)
    n_ids = _LIB.pmx_front_mesh(
        host.n_original, host.n_pcols, host.n_faces, _ptr(ran), _ptr(at), len(at), s.p_not_run_at,
        m["p_records"], m["p_kill_data"], m["p_base"], len(m["base"]), m["p_tops"], m["p_top_at"], len(m["tops"]),
        n_faces, _ptr(faces), _ptr(ids), _ptr(positions), s.p_mark, s.p_start_bits, s.p_face_bits, s.p_vertex_bits,
        s.p_start_prefix, s.p_face_prefix, s.p_vertex_prefix, s.p_front, s.p_sorted, s.p_drawn, s.p_front_index)
    if n_ids < 0:
        raise RuntimeError("front mesh: the faces drawn do not match the refinement's face count")
    # The vertices used are a few fewer than the refinement's count (those
    # left without a face): views of the first n_ids, not copies.
    return positions[:n_ids], faces, ids[:n_ids]
