"""The front engine's C core as XLA FFI calls: one camera, camera batches, words of a path, meshes.

The core (``pmjax/engines/core``, API in ``pmx.h``) walks the pcol forest
from its roots and stops wherever a bound decides everything below a pcol;
its own decisions are certified equal to the float32 predicate's bits, and
the few it cannot certify ("unsure") are asked of the predicate itself. Here
each step is an XLA custom call registered for the CPU (``jax.ffi``), typed
buffers in and out, so every function below is a JAX function: it runs
eagerly, under ``jax.jit``, and under ``jax.vmap`` (a batch of cameras is one
call into the core, its threads taking the cameras, not a loop of calls).

A call whose output size depends on the data writes into buffers of fixed
capacity (the hierarchy's pcols; a pool of unsure records) and says how much
it used. The unsure decisions go through the dense engine's own predicate
in XLA between two calls:

- one camera: a first pass lists the unsure positions; XLA decides them; a
  second pass at the same SIMD level takes the answers (it returns at once
  when there were none);
- camera batches and words: each camera (word) with unsure decisions
  leaves a record of the chains they can change; XLA decides the pairs; a
  last call corrects counts, masks and lists from the records. A camera
  whose record does not fit the pool is refined again alone (rare: the
  pool holds hundreds of records per call).

Every result is the dense engine's, bit for bit.
"""

from __future__ import annotations

import functools
import os
import types

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._camera import Camera
from .._predicate import ALL_TESTS, view_collapse_mask
from .._units import camera_lengths_in_model_units
from .._view import View
from ._switch import core_allowed
from ._front_mesh import CoreMesh
from ._tables import CoreTables, table_columns

try:
    from . import _pmx
except ImportError as error:  # not built (no C compiler at install time)
    _pmx, LOAD_ERROR = None, f"{type(error).__name__}: {error}"
else:
    LOAD_ERROR = None

# The core's layout (pmx.h), checked against the library below.
ROW, VIEW, CAMERA, FRAMES, FAT, NODE, SPARE = 16, 22, 19, 16, 29, 12, 16
# Words of the same frames at other tolerances traversed together at most
# (refine_words' sets).
MOST_SETS = 8
FRUSTUM, ORIENTATION, SCREEN, ORTHOGRAPHIC = 1, 2, 4, 8
SIMD_LEVELS = ("plain", "avx2", "avx512")
# How the core's mesh takes its ranks: by the ratio of items to bitmap words,
# from bitmaps always, from sorts always.
MESH_RANKS = ("rule", "bitmaps", "sorts")
# Unsure pairs decided per step of the loop that asks the float32 predicate:
# for batches, and for one camera, whose unsure decisions are few (a bigger
# step makes XLA's cost estimate of the whole call grow past the point where
# the CPU client runs it on another thread, which costs an eager call more
# than the step saves).
CHUNK = 64
CHUNK_ONE = 4
# Words per call of the path targets (a path's words are taken by the core's
# threads, each its own word): whole blocks, then the rest in powers of two
# words, so that few shapes are compiled and a short path is padded little.
WORDS_PER_CALL = 64


def word_spans(words: int, most: int) -> list:
    """``(first word, words)`` per call of the path targets: whole blocks of
    ``most``, then the rest in powers of two."""
    spans, start = [], 0
    while start < words:
        n = min(most, 1 << int(np.log2(words - start)))
        spans.append((start, n))
        start += n
    return spans

if _pmx is not None:
    _layout = _pmx.layout()
    assert (_layout["row"], _layout["view"], _layout["camera"], _layout["frames"], _layout["fat"], _layout["node"],
            _layout["spare"], _layout["most_sets"]) == (ROW, VIEW, CAMERA, FRAMES, FAT, NODE, SPARE, MOST_SETS), _layout
    for _name, _capsule in _pmx.targets().items():
        jax.ffi.register_ffi_target(_name, _capsule, platform="cpu")


def built() -> bool:
    """Whether the core was compiled and loaded (``LOAD_ERROR`` says why not)."""
    return _pmx is not None


# PMJAX_NATIVE=0 in the environment when pmjax is imported switches the core off.
_SWITCHED_OFF = os.environ.get("PMJAX_NATIVE", "1") == "0"


def enabled() -> bool:
    """Whether calls may use the core: built, and not switched off by
    ``PMJAX_NATIVE=0`` (at import) or :func:`pmjax.engines.without_core`."""
    return _pmx is not None and not _SWITCHED_OFF and core_allowed()


def simd(level: str | None = None) -> str:
    """The SIMD kernels the core runs (``"plain"``, ``"avx2"``, ``"avx512"``);
    with ``level``, switch to the best the processor has up to it and return
    the previous (for tests: every level gives the same bits)."""
    if level is not None and level not in SIMD_LEVELS:
        raise ValueError(f"the SIMD level must be one of {SIMD_LEVELS}, got {level!r}")
    if _pmx is None:
        return "plain"
    return SIMD_LEVELS[_pmx.simd(-1 if level is None else SIMD_LEVELS.index(level))]


def mesh_ranks(way: str | None = None) -> str:
    """How the core's ``Refinement.mesh()`` ranks faces and vertex ids (the
    front's starts always in a bitmap): ``"rule"`` (a bitmap each, or a sort
    of the items where they are few for the bitmap's words), ``"bitmaps"``
    or ``"sorts"`` always.
    With ``way``, switch and return the previous (for tests: every way gives
    the same mesh)."""
    if way is not None and way not in MESH_RANKS:
        raise ValueError(f"the mesh ranks must be one of {MESH_RANKS}, got {way!r}")
    if _pmx is None:
        return "rule"
    return MESH_RANKS[_pmx.mesh_ranks(-1 if way is None else MESH_RANKS.index(way))]


def simd_best() -> str:
    """The best SIMD kernels this processor has (``"plain"`` without the core)."""
    return SIMD_LEVELS[_pmx.simd_best()] if _pmx is not None else "plain"


def flags_of(tests, orthographic: bool) -> int:
    """The core's flags for a set of tests and a projection."""
    if tests is ALL_TESTS:  # the default, without three module attribute reads per call
        chosen = FRUSTUM | ORIENTATION | SCREEN
    else:
        chosen = FRUSTUM * bool(tests.frustum) | ORIENTATION * bool(tests.orientation) | SCREEN * bool(tests.screen)
    return chosen | ORTHOGRAPHIC * bool(orthographic)


def camera_rows(cameras: Camera, taus, exponent: int, xp=jnp):
    """Cameras and their tolerances as the core reads them: ``float32 [...,
    CAMERA]`` rows (eye, rotation row-major, fov_y, near, far, ortho_height,
    width, height, tau), one per camera of the batch's leading axes, the
    lengths in the tables' model unit ``2^exponent`` (:mod:`pmjax._units`).
    The core computes each view's constants from them. ``xp``: ``jax.numpy``
    (traceable) or ``numpy`` (eager calls, on the host)."""
    f = lambda x: xp.asarray(x, xp.float32)
    eye, near, far, ortho_height = camera_lengths_in_model_units(cameras.eye, cameras.near, cameras.far,
                                                                 cameras.ortho_height, exponent, xp)
    eye = f(eye)
    lead = eye.shape[:-1]
    scalars = [cameras.fov_y, near, far, ortho_height, cameras.width, cameras.height, taus]
    scalars = xp.stack([xp.broadcast_to(f(x), lead) for x in scalars], axis=-1)
    return xp.concatenate([eye, f(cameras.rotation).reshape(lead + (9,)), scalars], axis=-1)


def host_camera_rows(cameras: Camera, taus, exponent: int) -> np.ndarray:
    """:func:`camera_rows` on the host (NumPy)."""
    return camera_rows(cameras, taus, exponent, np)


# The exponent is static: one per mesh, and a Python int is cheaper hashed than
# converted to an array at every call.
@functools.partial(jax.jit, static_argnames=("exponent",))
def _camera_row_of_fields(eye, rotation, fov_y, near, far, ortho_height, width, height, tau, exponent):
    fields = types.SimpleNamespace(eye=eye, rotation=rotation, fov_y=fov_y, near=near, far=far,
                                   ortho_height=ortho_height, width=width, height=height)
    return camera_rows(fields, tau, exponent)


def eager_camera_row(camera: Camera, tau, exponent: int) -> np.ndarray:
    """``float32 [CAMERA]``: :func:`camera_rows` of one camera for an eager
    call, as a NumPy array: one compiled call on the camera's fields, read
    from the instance's dictionary (an equinox module's attribute access
    runs Python code, a per-call cost here) and passed one by one."""
    f = vars(camera)
    return np.asarray(_camera_row_of_fields(f["eye"], f["rotation"], f["fov_y"], f["near"], f["far"],
                                            f["ortho_height"], f["width"], f["height"], tau, exponent=exponent))


def _view_of_rows(rows, orthographic: bool, step=None):
    """``float32 [..., 22]``: XLA's :class:`View` constants of camera rows
    (:func:`camera_rows`), the values the dense engine computes. ``step``
    (a loop counter) makes them depend on the loop that asks for them, so
    that XLA computes them where they are needed (inside a loop that usually
    runs no step) rather than before it."""
    if step is not None:  # tied to the loop counter: not hoisted out of the loop
        rows, _ = lax.optimization_barrier((rows, step))
    tau = rows[..., 18]
    lead = rows.shape[:-1]
    cam = Camera(rows[..., 0:3], rows[..., 3:12].reshape(lead + (3, 3)), rows[..., 12], rows[..., 13], rows[..., 14],
                 rows[..., 15], rows[..., 16].astype(jnp.int32), rows[..., 17].astype(jnp.int32), orthographic)
    if not lead:
        return View.of(cam, tau).values
    flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(lead):]), cam)
    return View.batch(flat, tau.reshape(-1)).values.T.reshape(lead + (VIEW,))


def _sds(shape, dtype):
    return jax.ShapeDtypeStruct(tuple(shape), dtype)


def _call(name, results, *args, aliases=None, vmap_method=None, **attrs):
    return jax.ffi.ffi_call(name, results, input_output_aliases=aliases or {}, vmap_method=vmap_method)(*args,
                                                                                                        **attrs)


def _hierarchy_args(tables: CoreTables):
    return tables.rows, tables.kills, tables.order


def check_hierarchy(tables: CoreTables) -> None:
    """The core's O(P) check of a layout's links (a forest laid out breadth
    first); ``jax.errors.JaxRuntimeError`` naming what is wrong otherwise."""
    _call("pmx_check_hierarchy", _sds((), jnp.int32), *_hierarchy_args(tables),
          n_roots=np.int64(tables.n_roots)).block_until_ready()


# -- the float32 predicate on the unsure pairs ----------------------------------


def _rows_at(tables: CoreTables, positions):
    """The attributes of the pcols at ``positions`` (rows of the table)."""
    attrs, _ = table_columns(tables.rows.at[positions].get(mode="promise_in_bounds").T)
    return attrs


def _answer_positions(tables, positions, count, yes, camera, tests, orthographic):
    """``yes[i]`` for ``i < count``: the float32 predicate's decision of the
    pcol at ``positions[i]`` under one camera (a :func:`camera_rows` row),
    CHUNK at a time."""
    capacity = positions.shape[0]

    def step(i, yes):
        view = View(_view_of_rows(camera, orthographic, i), orthographic)
        at = i * CHUNK_ONE + jnp.arange(CHUNK_ONE)
        valid = at < count
        pos = jnp.where(valid, positions[jnp.minimum(at, capacity - 1)], 0)
        bits = view_collapse_mask(_rows_at(tables, pos), view, tests, rows=False)
        return yes.at[jnp.where(valid, at, capacity)].set(bits.astype(jnp.int32), mode="drop")

    return lax.fori_loop(0, (count + CHUNK_ONE - 1) // CHUNK_ONE, step, yes)


def _decide_each(tables, positions, values, tests, orthographic):
    """``bool [n]``: the float32 predicate's decision of the pcol at
    ``positions[i]`` under the view ``values[i]`` (``[n, 22]``)."""
    attrs = _rows_at(tables, positions)
    columns = jax.tree.map(lambda x: x.T[:, :, None] if x.ndim == 2 else x[:, None], attrs)
    one = lambda a, v: view_collapse_mask(a, View(v, orthographic), tests, rows=False)
    return jax.vmap(one)(columns, values)[:, 0]


def _answer_pairs(tables, pairs, count, yes, cameras, tests, orthographic, frames):
    """``yes[i]`` for the first ``count`` pairs ``(at, item, position,
    frames)``: the frames (bits) of the pair's item whose float32 predicate
    collapses its pcol; ``cameras [items * frames, CAMERA]`` (:func:`camera_rows`),
    CHUNK pairs at a time."""
    capacity = pairs.shape[0]
    lanes = jnp.arange(frames)

    def step(i, yes):
        at = i * CHUNK + jnp.arange(CHUNK)
        valid = at < count
        pair = pairs[jnp.minimum(at, capacity - 1)]
        position = jnp.where(valid, pair[:, 2], 0)
        # Each pair's pcol under each frame of its item: [CHUNK, frames].
        frame = jnp.where(valid, pair[:, 1], 0)[:, None] * frames + lanes
        views = _view_of_rows(cameras[frame.reshape(-1)], orthographic, i)
        bits = _decide_each(tables, jnp.repeat(position, frames), views, tests, orthographic)
        word = jnp.sum(bits.reshape(CHUNK, frames).astype(jnp.int32) << lanes, axis=1) & pair[:, 3]
        return yes.at[jnp.where(valid, at, capacity)].set(word, mode="drop")

    return lax.fori_loop(0, (count + CHUNK - 1) // CHUNK, step, yes)


# -- one camera ------------------------------------------------------------------


def refine_one(tables: CoreTables, camera, tests, orthographic: bool, lists: bool):
    """One camera: ``(pcols, ran, positions, counts)``.

    Args:
        tables: :class:`CoreTables` (bounds below each pcol).
        camera: ``float32 [CAMERA]`` the camera and its tolerance (:func:`camera_rows`).
        lists: return the visited slots' lists (capacity ``P + SPARE``, the
            first ``counts[0]`` used); else they are empty.

    Returns:
        ``pcols int32 [L]``, ``ran uint8 [L]``, ``positions int32 [L]`` and
        ``counts int32 [4]``: slots visited, pcols that did not run, faces
        they keep, 0.
    """
    first = refine_one_first(tables, camera, tests, orthographic, lists)
    return refine_one_answered(tables, camera, tests, orthographic, first)


def refine_one_first(tables: CoreTables, camera, tests, orthographic: bool, lists: bool):
    """The first pass of :func:`refine_one`: unsure decisions taken as "keep"
    and listed. Returns ``(pcols, ran, positions, unsure, yes, counts)``,
    ``counts int32 [5]``: slots visited, pcols not run, faces kept, unsure
    decisions, the SIMD level; exact where ``counts[3]`` is 0."""
    P = tables.n_pcols
    L = P + SPARE if lists else 0
    return _call("pmx_refine_one", (_sds((L,), jnp.int32), _sds((L,), jnp.uint8), _sds((L,), jnp.int32),
                                    _sds((P + SPARE,), jnp.int32), _sds((P + SPARE,), jnp.int32),
                                    _sds((5,), jnp.int32)),
                 *_hierarchy_args(tables), camera, flags=np.int32(flags_of(tests, orthographic)),
                 n_roots=np.int64(tables.n_roots))


def refine_one_answered(tables: CoreTables, camera, tests, orthographic: bool, first):
    """The rest of :func:`refine_one` after its first pass: the unsure
    decisions asked of the float32 predicate and the second pass (which
    returns at once where there were none)."""
    pcols, ran, positions, unsure, yes, counts = first
    yes = _answer_positions(tables, unsure, counts[3], yes, camera, tests, orthographic)
    pcols, ran, positions, counts = _call(
        "pmx_refine_answered", (_sds(pcols.shape, jnp.int32), _sds(ran.shape, jnp.uint8),
                                _sds(positions.shape, jnp.int32), _sds((5,), jnp.int32)),
        *_hierarchy_args(tables), camera, pcols, ran, positions, unsure, yes, counts,
        aliases={4: 0, 5: 1, 6: 2}, flags=np.int32(flags_of(tests, orthographic)), n_roots=np.int64(tables.n_roots))
    return pcols, ran, positions, counts[:4].at[3].set(0)


def refine_one_eager(tables: CoreTables, host, n_roots: int, camera_row: np.ndarray, tests, orthographic: bool):
    """:func:`refine_one` with lists, eagerly: the core called from Python
    directly (``_pmx.refine_one``, with the XLA targets' checks; no XLA
    program around it), the unsure decisions asked of the float32 predicate
    in XLA and a second pass only where the first left some.

    Args:
        tables: :class:`CoreTables`.
        host: ``(rows, kills, order)`` of ``tables`` as NumPy arrays, and
            ``n_roots`` their roots (read once per mesh by the caller).
        camera_row: ``float32 [CAMERA]`` (:func:`eager_camera_row`).

    Returns:
        NumPy ``pcols int32 [L]``, ``ran uint8 [L]``, ``positions int32 [L]``
        (``L = P + SPARE``, the first ``counts[0]`` used) and ``counts int32
        [5]``: slots visited, pcols not run, faces they keep, 0, the SIMD level.
    """
    L = len(host[1]) + SPARE
    flags = flags_of(tests, orthographic)
    pcols, ran, positions = np.empty(L, np.int32), np.empty(L, np.uint8), np.empty(L, np.int32)
    unsure, counts = np.empty(L, np.int32), np.empty(5, np.int32)
    _pmx.refine_one(*host, camera_row, flags, n_roots, pcols, ran, positions, counts, unsure)
    m = int(counts[3])
    if m:
        # Padded to a power of two: a few compiled shapes serve every count.
        padded = np.zeros(max(64, 1 << (m - 1).bit_length()), np.int32)
        padded[:m] = unsure[:m]
        answered = padded[:m]
        yes = np.asarray(_answers(tables, padded, m, camera_row, tests, orthographic))[:m]
        _pmx.refine_one(*host, camera_row, flags, n_roots, pcols, ran, positions, counts, None, answered,
                        np.ascontiguousarray(yes, np.int32), int(counts[4]))
        if counts[3]:
            raise RuntimeError("refine: unsure decisions left after they were answered")
    return pcols, ran, positions, counts


@functools.partial(jax.jit, static_argnames=("tests", "orthographic"))
def _answers(tables, positions, count, camera_row, tests, orthographic):
    return _answer_positions(tables, positions, count, jnp.zeros(positions.shape, jnp.int32), camera_row, tests,
                             orthographic)


# -- camera batches ----------------------------------------------------------------


def record_capacity(items: int, frames: int = 1) -> int:
    """Int32 of unsure records held per call: room for a few hundred records
    (a record is a few chains of PMX_NODE int32 per slot)."""
    return 1 << 13 if frames == 1 and items <= 8 else 4096 + (256 if frames == 1 else 2048) * items


def _apply(tables, records, sizes, pairs, yes, counts, masks, ran, frames):
    return _call("pmx_apply_unsure", (_sds(records.shape, records.dtype), _sds(counts.shape, counts.dtype),
                                      _sds(masks.shape, masks.dtype), _sds(ran.shape, ran.dtype)),
                 records, sizes, pairs, yes, counts, masks, ran, tables.order, aliases={0: 0, 4: 1, 5: 2, 6: 3},
                 frames=np.int32(frames))


def refine_many(tables: CoreTables, cameras, tests, orthographic: bool, masks: bool, lists: bool, threads: int = 0,
                room: int | None = None):
    """K cameras in one call, the core's threads taking them in Morton order of
    their eyes.

    Args:
        cameras: ``float32 [K, CAMERA]`` the cameras and their tolerances
            (:func:`camera_rows`).
        masks: also return ``executed uint8 [K, P]``.
        lists: also return each camera's lists (``[K, P + SPARE]``).
        threads: threads at most (0: XLA's CPU thread pool).
        room: int32 of unsure records held (default :func:`record_capacity`;
            tests set it small to refine cameras alone).

    Returns:
        ``(counts int32 [K, 4], masks, (pcols, ran, positions))``, the
        missing parts empty.
    """
    P, K = tables.n_pcols, cameras.shape[0]
    L = P + SPARE
    R = record_capacity(K) if room is None else room
    N = R // NODE + 1
    list_shape = (K, L) if lists else (K, 0)
    out = _call("pmx_refine_many", (_sds((K, 4), jnp.int32), _sds((K, P) if masks else (K, 0), jnp.uint8),
                                    _sds(list_shape, jnp.int32), _sds(list_shape, jnp.uint8),
                                    _sds(list_shape, jnp.int32), _sds((R,), jnp.int32), _sds((N, 4), jnp.int32),
                                    _sds((N,), jnp.int32), _sds((2,), jnp.int32), _sds((K,), jnp.uint8)),
                *_hierarchy_args(tables), cameras, flags=np.int32(flags_of(tests, orthographic)),
                n_roots=np.int64(tables.n_roots), threads=np.int64(threads))
    counts, mask, pcols, ran, positions, records, pairs, yes, sizes, overflow = out
    yes = _answer_pairs(tables, pairs, sizes[1], yes, cameras, tests, orthographic, 1)
    records, counts, mask, ran = _apply(tables, records, sizes, pairs, yes, counts, mask, ran, 1)
    counts, mask, pcols, ran, positions = _redo_overflowed(tables, cameras, tests, orthographic, overflow, counts,
                                                           mask, pcols, ran, positions, masks, lists)
    return counts, mask, (pcols, ran, positions)


def _redo_overflowed(tables, cameras, tests, orthographic, overflow, counts, mask, pcols, ran, positions, masks,
                     lists):
    """The cameras whose records did not fit, refined alone (none, nearly
    always: the loop then runs no step)."""
    K, P = cameras.shape[0], tables.n_pcols
    todo = jnp.nonzero(overflow, size=K, fill_value=0)[0]

    def step(j, carry):
        counts, mask, pcols, ran, positions = carry
        k = todo[j]
        got = refine_one(tables, cameras[k], tests, orthographic, lists=masks or lists)
        counts = counts.at[k].set(got[3])
        if masks:
            slots = jnp.where(jnp.arange(P + SPARE) < got[3][0], got[0], P)
            mask = mask.at[k].set(jnp.ones(P, jnp.uint8).at[slots].set(got[1], mode="drop"))
        if lists:
            pcols, ran, positions = pcols.at[k].set(got[0]), ran.at[k].set(got[1]), positions.at[k].set(got[2])
        return counts, mask, pcols, ran, positions

    return lax.fori_loop(0, jnp.sum(overflow, dtype=jnp.int32), step, (counts, mask, pcols, ran, positions))


# -- face budgets -----------------------------------------------------------------------


def budget_guesses(tables: CoreTables, cameras, budgets, tests, orthographic: bool, base_faces: int,
                   threads: int = 0, words: bool = False):
    """Per camera and budget, a guess of the smallest float32 ``tau`` whose
    face count is within the budget: one traversal per camera at a tolerance
    below the smallest of its answers and the critical tolerances of the
    pcols that do not run there, estimated in double
    (``pmjax/engines/core/budget.c``); exact counts confirm or correct it.

    Args:
        cameras: ``float32 [K, CAMERA]`` (:func:`camera_rows`), the tolerance a
            first one to traverse at (the core lowers it where needed), or 0:
            one from the answers of the cameras before.
        budgets: ``int32 [K, B]`` faces, B budgets per camera (one traversal
            serves them all).
        base_faces: the coarsest mesh's faces.
        words: the cameras are a path's frames in words of FRAMES (K a
            multiple of FRAMES; ``tables`` with bounds over whole subtrees,
            ``Derived.core_words``), each with a tolerance > 0 to traverse
            at: each word is traversed once for its frames, and a frame
            whose answers lie below its tolerance gets -1 (left to a
            traversal of its own).

    Returns:
        ``(guess, guess_alt)`` ``int32 [K, B]``: float32 bit patterns,
        ``0x7F800001`` for ``tau = inf``; ``guess_alt`` takes the core's unsure
        decisions as collapses, ``guess`` as "keep" (a word's frame makes one
        guess, unsure decisions as "keep": its ``guess_alt`` equals ``guess``).
    """
    K, B = budgets.shape
    # One pixel as XLA computes it (the dense engine's value), which the
    # screen test's switch points depend on to the last bit.
    units = _view_of_rows(cameras, orthographic)[:, 20]
    return _call("pmx_budget_many", (_sds((K, B), jnp.int32), _sds((K, B), jnp.int32)), *_hierarchy_args(tables),
                 cameras, units, budgets,
                 flags=np.int32(flags_of(tests, orthographic)), n_roots=np.int64(tables.n_roots),
                 base_faces=np.int64(base_faces), threads=np.int64(threads), words=np.int32(words))


# -- words of a path -------------------------------------------------------------------


def refine_words(tables: CoreTables, one_tables: CoreTables, cameras, tests, orthographic: bool, lists: bool,
                 threads: int = 0, room: int | None = None, sets: int = 1):
    """Words of FRAMES consecutive frames, each traversed once for its frames.

    Args:
        tables: :class:`CoreTables` with bounds over whole subtrees
            (``Derived.core_words``); one_tables: those of one camera
            (``Derived.core``), for the frames of a word whose records did
            not fit (counted alone).
        cameras: ``float32 [W * FRAMES, CAMERA]`` the frames and their
            tolerances (:func:`camera_rows`), word by word.
        lists: also return each word's lists (``[W, P + SPARE]``, ``ran``
            the frames' bits as uint16).
        sets: the words come in groups of ``sets`` (1 to MOST_SETS) consecutive
            words; a group whose words hold the same frames at other
            tolerances (a face budget's patterns) is traversed once for all
            of them, with the same results. Without ``lists`` only.

    Returns:
        ``(counts int32 [W * FRAMES, 4], at_once int32 [W], (pcols, ran,
        positions), overflow uint8 [W])``: with ``lists``, a word that
        overflowed has its counts but not its lists corrected (the caller
        refines its frames alone); without, its frames' counts are redone here.
    """
    P = tables.n_pcols
    W = cameras.shape[0] // FRAMES
    L = P + SPARE
    R = record_capacity(W, FRAMES) if room is None else room
    N = R // NODE + 1
    list_shape = (W, L) if lists else (W, 0)
    if sets != 1 and lists:
        raise ValueError("refine_words: word sets have no lists")
    out = _call("pmx_refine_words", (_sds((W * FRAMES, 4), jnp.int32), _sds((W,), jnp.int32),
                                     _sds(list_shape, jnp.int32), _sds(list_shape, jnp.uint16),
                                     _sds(list_shape, jnp.int32), _sds((R,), jnp.int32), _sds((N, 4), jnp.int32),
                                     _sds((N,), jnp.int32), _sds((2,), jnp.int32), _sds((W,), jnp.uint8)),
                *_hierarchy_args(tables), cameras, flags=np.int32(flags_of(tests, orthographic)),
                n_roots=np.int64(tables.n_roots), threads=np.int64(threads), sets=np.int64(sets))
    counts, at_once, pcols, ran, positions, records, pairs, yes, sizes, overflow = out
    yes = _answer_pairs(tables, pairs, sizes[1], yes, cameras, tests, orthographic, FRAMES)
    records, counts, _, ran = _apply(tables, records, sizes, pairs, yes, counts, jnp.zeros((W, 0), jnp.uint8),
                                     ran, FRAMES)
    if not lists:
        counts = _recount_overflowed(one_tables, cameras, tests, orthographic, overflow, counts)
    return counts, at_once, (pcols, ran, positions), overflow


def _recount_overflowed(tables, cameras, tests, orthographic, overflow, counts):
    """The frames of the words whose records did not fit, counted alone."""
    W = overflow.shape[0]
    todo = jnp.nonzero(overflow, size=W, fill_value=0)[0]

    def step(j, counts):
        k = todo[j // FRAMES] * FRAMES + j % FRAMES
        return counts.at[k].set(refine_one(tables, cameras[k], tests, orthographic, lists=False)[3])

    return lax.fori_loop(0, FRAMES * jnp.sum(overflow, dtype=jnp.int32), step, counts)


# -- as JAX functions of cameras: vmap makes one batched call ------------------------------


def _no_batched_tables(tables_batched):
    if any(jax.tree.leaves(tables_batched)):
        raise ValueError("the front engine's tables cannot be batched: vmap over cameras, not over meshes "
                         "(or use method='dense')")


@functools.lru_cache(maxsize=None)
def one_camera(tests, orthographic: bool, lists: bool):
    """``f(tables, camera) -> (pcols, ran, positions, counts)``: :func:`refine_one`
    of one :func:`camera_rows` row, whose ``vmap`` over cameras is one
    :func:`refine_many` call."""

    @jax.custom_batching.custom_vmap
    def one(tables, camera):
        return refine_one(tables, camera, tests, orthographic, lists)

    @one.def_vmap
    def one_batched(axis_size, in_batched, tables, camera):
        _no_batched_tables(in_batched[0])
        cameras = camera if in_batched[1] else jnp.broadcast_to(camera, (axis_size,) + camera.shape)
        counts, _, (pcols, ran, positions) = many_cameras(tests, orthographic, False, lists)(tables, cameras)
        return (pcols, ran, positions, counts), (True,) * 4

    return one


@functools.lru_cache(maxsize=None)
def many_cameras(tests, orthographic: bool, masks: bool, lists: bool, threads: int = 0, room: int | None = None):
    """``f(tables, cameras) -> (counts, masks, lists)``: :func:`refine_many` of
    :func:`camera_rows` ``[K, CAMERA]``; ``vmap`` over it flattens the
    batches into one call."""

    @jax.custom_batching.custom_vmap
    def many(tables, cameras):
        return refine_many(tables, cameras, tests, orthographic, masks, lists, threads, room)

    @many.def_vmap
    def many_batched(axis_size, in_batched, tables, cameras):
        _no_batched_tables(in_batched[0])
        if not in_batched[1]:
            cameras = jnp.broadcast_to(cameras, (axis_size,) + cameras.shape)
        K = cameras.shape[1]
        out = many(tables, cameras.reshape(axis_size * K, CAMERA))
        out = jax.tree.map(lambda x: x.reshape((axis_size, K) + x.shape[1:]), out)
        return out, jax.tree.map(lambda _: True, out)

    return many


# -- the mesh ----------------------------------------------------------------------------


def front_mesh(mesh: CoreMesh, ran, positions, counts, item=0, face_rows=None, id_rows=None):
    """The refined mesh of a refinement's visited slots, in fixed-capacity buffers.

    Args:
        mesh: :class:`CoreMesh`.
        ran, positions: the lists ``[L]``, or a batch's ``[R, L]``: ``ran``
            uint8 for cameras (row ``item``), or a path's uint16 frame bits
            (row ``item // 16``, bit ``item % 16``).
        counts: the refinements' counts ``int32 [4]`` or ``[M, 4]`` (slots
            visited, pcols not run, faces they keep, 0); row ``item`` is this one's.
        face_rows, id_rows: the buffers' rows (static; default the whole
            mesh's ``F`` and ``V0``). The call fails when the refinement's
            faces or the vertices it uses do not fit.

    Returns:
        ``faces int32 [face_rows, 3]`` (the refinement's faces in the first
        rows), ``ids int32 [id_rows]`` and ``vertices float32 [id_rows, 3]``
        (the first ``n_ids``), ``n_ids``.
    """
    V0, F = mesh.n_original, mesh.n_faces
    face_rows = F if face_rows is None else face_rows
    id_rows = V0 if id_rows is None else id_rows
    return _call("pmx_front_mesh", (_sds((face_rows, 3), jnp.int32), _sds((id_rows,), jnp.int32),
                                    _sds((id_rows, 3), jnp.float32), _sds((), jnp.int32)),
                 mesh.pcols, mesh.kill_data, mesh.base, mesh.tops, mesh.top_at, ran, positions, counts,
                 jnp.asarray(item, jnp.int32), vmap_method="sequential", n_original=np.int64(V0),
                 n_faces_total=np.int64(F))


def front_mesh_eager(tables, ran, positions, counts, item: int, n_original: int, n_faces: int, faces, ids,
                     vertices) -> int:
    """:func:`front_mesh` eagerly, the core called from Python directly
    (``_pmx.front_mesh``, with the XLA target's checks).

    Args:
        tables: the mesh's records ``(pcols, kill_data, base, tops, top_at)``
            as NumPy arrays.
        ran, positions, counts, item: as for :func:`front_mesh` (NumPy or
            JAX arrays on the CPU).
        faces, ids, vertices: NumPy outputs ``int32 [rows, 3]`` (room for the
            refinement's faces), ``int32 [rows]`` and ``float32 [rows, 3]``
            (room for the vertices it uses), written.

    Returns:
        The vertices used (the first rows of ``ids`` and ``vertices``).
    """
    return _pmx.front_mesh(*tables, np.asarray(ran), np.asarray(positions), np.asarray(counts), int(item),
                           int(n_original), int(n_faces), faces, ids, vertices)


# -- whole-table passes (tests) -------------------------------------------------------------

# A pcol's own decision in the core (certify.h): keep, collapse, unsure; |
# WHOLE where its bound decides everything below it. Fat-camera passes:
# open, every frame's subtree collapses, no frame collapses it, only the
# screen test left to the frames, the frustum test settled for them, every
# frame collapses it (its subtree bound holding for none).
NO, YES, UNSURE, WHOLE = 0, 1, 2, 4
FAT_OPEN, FAT_WHOLE, FAT_NO, FAT_SCREEN, FAT_INSIDE, FAT_YES = 0, 1, 2, 3, 4, 5


@functools.partial(jax.jit, static_argnames=("orthographic",))
def views(cameras, orthographic: bool):
    """``float32 [K, 22]``: the view constants the core computes from camera
    rows ``[K, CAMERA]`` (:func:`camera_rows`; ``pmx_views_of``)."""
    return _call("pmx_views", _sds((cameras.shape[0], VIEW), jnp.float32), cameras,
                 orthographic=np.int32(orthographic))


@functools.partial(jax.jit, static_argnames=("flags",))
def decide_all(rows, view_values, flags: int):
    """``uint8 [P]``: every pcol's certified decision (``NO``, ``YES``,
    ``UNSURE``) | ``WHOLE`` where its bound decides everything below
    (``rows``: a table in any order)."""
    return _call("pmx_decide_all", _sds((rows.shape[0],), jnp.uint8), rows, view_values, flags=np.int32(flags))


@jax.jit
def fat_cameras(view_values):
    """``float32 [W, 29]``: the fat cameras of words of frames (``[W, F, 22]``)."""
    return _call("pmx_fat_cameras", _sds((view_values.shape[0], FAT), jnp.float32), view_values)


@functools.partial(jax.jit, static_argnames=("flags",))
def decide_fat_all(rows, view_values, fat, flags: int):
    """``uint8 [P]``: every pcol under the fat camera of ``[F, 22]`` view
    constants (``FAT_OPEN``, ``FAT_WHOLE``, ``FAT_NO``, ``FAT_SCREEN``: only
    the screen test left to the frames, ``FAT_INSIDE``: the frustum test
    settled, ``FAT_YES``: every frame collapses it, no frame's subtree bound
    holding)."""
    return _call("pmx_decide_fat_all", _sds((rows.shape[0],), jnp.uint8), rows, view_values, fat,
                 flags=np.int32(flags))
