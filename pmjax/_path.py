"""Coherent camera paths: every frame refined exactly as alone, consecutive frames together.

Consecutive cameras of a path see nearly the same front. The output-sensitive
traversal carries one bit per frame: a pcol is visited when any frame of a
word visits it, and each frame's tests and subtree bounds are evaluated as one
lane of the word. Run on consecutive frames, the union of their fronts is
little larger than one frame's, so each pcol near the front is fetched once for
the word and tested for all its frames in one vectorized pass: the coherence of
the path is what makes the word cheap. A word is 16 frames in the C core
(:func:`pmjax.engines._core.refine_words`) and 32 as JAX kernels (where the
core is not built; :mod:`pmjax.engines._front_jax`). In the core most pcols are
decided for all of a word's frames at once, under a fat camera that covers them
(``pmjax/engines/core/fat.c``).

Exactness. Frame ``c`` of a word gets, for every pcol, its own decision (the
float32 predicate's bit, certified or computed, or proved for every frame
under the fat camera) and a sound subtree bound (its own or the fat camera's),
and a pcol it does not visit lies under a subtree every pcol of which
collapses for it. So its executed set, counts, faces and ``vref`` are those of
``refine(pm, camera_c, tau_c)``, bit for bit. Its visited list is the word's:
every frame of a word lists the word's slots, those it did not visit marked
executed (they lie under a subtree decided for it). No state is carried
from one word to the next: a cut or a teleport costs nothing special, a frame's
result never depends on the frames before it (unlike SrMesh's adapted mesh),
and a path of any length runs in the memory of one word (or chunk of words).

A face budget per frame is solved per frame (:func:`pmjax.faces_for_budget`),
and the frames are then refined as a path at the tolerances found.
"""

from __future__ import annotations

import functools
import itertools
import time
from typing import Iterator

import jax
import jax.numpy as jnp
import numpy as np

from ._arguments import check_mesh
from ._scalars import check_camera_type
from ._bitsets import WORD
from ._camera import Camera, check_camera_values
from ._model import ProgressiveMesh
from ._predicate import ALL_TESTS, Tests
from ._refine import (Refinement, _checked_tau, _Counts, check_budget, check_tau, faces_for_budget,
                      kernel_budgets, refine)
from .engines import _core, _front_jax
from .engines._choose import is_traced, select
from .engines._core import WORDS_PER_CALL
from .engines._tables import derived

# Frames per compiled call: eight words. Memory is bounded by one chunk.
CHUNK = 8 * WORD


class PathError(ValueError):
    """A path that cannot be refined: empty, a bad camera or tolerance (the message names the frame)."""


def check_path(cameras: Camera, tau=1.0, budget=None, *, paths: bool = False):
    """Validate a camera path and its tolerances.

    Args:
        cameras: a camera batch, leading axis time ``[T]`` (or ``[K, T]``, K
            paths, when ``paths``).
        tau: a scalar or one per frame (``[T]`` or ``[K, T]``), pixels, >= 0.
        budget: ``None``, or a face budget, a scalar or one per frame.

    Returns:
        ``(host cameras with leading axes flattened, taus float32[N], budgets
        int64[N] or None, shape)``, ``shape`` the leading axes.

    Raises:
        PathError: naming the first bad frame.
    """
    eye = np.asarray(cameras.eye)
    axes = 2 if paths else 1
    if eye.ndim != axes + 1:
        want = "[K, T]" if paths else "[T]"
        raise PathError(f"a path needs cameras with leading axes {want} (time last), got eye of shape {eye.shape}")
    shape = eye.shape[:-1]
    if 0 in shape:
        raise PathError(f"the path is empty (cameras of shape {shape}): give at least one frame")
    host = jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + np.shape(a)[axes:]), cameras)
    n = int(np.prod(shape))
    where = lambda i: f"frame {np.unravel_index(i, shape)[-1]}" + (f" of path {i // shape[-1]}" if paths else "")
    rotation = host.rotation.reshape(n, 9)
    bad = np.flatnonzero(~np.all(np.isfinite(rotation), axis=1))
    if len(bad):
        raise PathError(f"{where(bad[0])}: the camera rotation must be finite")
    try:
        check_camera_values(host.eye, np.degrees(host.fov_y), host.near, host.far, host.ortho_height, host.width,
                            host.height, cameras.orthographic, row="frame")
    except ValueError as e:
        # Re-worded with the path's own frame numbering.
        frame = int(str(e).split(":")[0].split()[-1])
        raise PathError(f"{where(frame)}:{str(e).split(':', 1)[1]}") from None
    size = np.stack([host.width, host.height], axis=1)
    first = size.reshape(shape + (2,)).reshape(-1, shape[-1], 2)[:, :1]
    changed = np.flatnonzero(np.any(size.reshape(-1, shape[-1], 2) != first, axis=2).reshape(-1))
    if len(changed):
        i = changed[0]
        w, h = size[i]
        w0, h0 = size[i - i % shape[-1]]
        raise PathError(f"{where(i)}: image size {w}x{h} differs from the path's first frame ({w0}x{h0}); "
                        "a path keeps one image size")
    taus = _per_frame(tau, shape, "tau", where, lambda t: np.float32(check_tau(t)))
    budgets = None if budget is None else _per_frame(budget, shape, "budget", where, check_budget).astype(np.int64)
    return host, taus.astype(np.float32), budgets, shape


def _per_frame(value, shape, what, where, check) -> np.ndarray:
    """A scalar or per-frame value as a flat array, each entry checked."""
    values = np.asarray(value)
    if values.ndim == 0:
        return np.full(int(np.prod(shape)), check(values.item()))
    if values.shape != shape:
        raise PathError(f"{what} must be a scalar or one per frame (shape {shape}), got shape {values.shape}")
    out = []
    for i, v in enumerate(values.reshape(-1)):
        try:
            out.append(check(v.item()))
        except ValueError as e:
            raise PathError(f"{where(i)}: {e}") from None
    return np.asarray(out)


def _budget_taus(pm, host, budgets, tests):
    """Per frame, the tolerance :func:`pmjax.faces_for_budget` finds."""
    cam = lambda i: jax.tree.map(lambda a: a[i], host)
    return np.array([faces_for_budget(pm, cam(i), int(b), tests)[0] for i, b in enumerate(budgets)], np.float32)


def _budget_taus_traced(pm, cameras, budgets, tests):
    """:func:`_budget_taus` under a trace: the budgets' searches for all the
    frames at once (``vmap``)."""
    return jax.vmap(lambda c, b: faces_for_budget(pm, c, b, tests)[0])(cameras, budgets)


def _word_padded(n_frames: int, path_length: int, word: int = WORD) -> np.ndarray:
    """Frame indices with each path padded to whole words of ``word`` frames
    (repeating its last frame), so that no word straddles two paths."""
    per_path = -(-path_length // word) * word
    paths = n_frames // path_length
    within = np.minimum(np.arange(per_path), path_length - 1)
    return (np.arange(paths)[:, None] * path_length + within[None, :]).reshape(-1)


def _chunk_spans(n_frames: int) -> list[tuple[int, int]]:
    """``(start, size)`` of the compiled calls over ``n_frames`` (a multiple of
    32): whole chunks, then the rest in power-of-two words, so that few
    shapes are compiled and a short path is padded little."""
    spans, start = [], 0
    while start < n_frames:
        n = min(CHUNK, WORD << int(np.log2((n_frames - start) // WORD)))
        spans.append((start, n))
        start += n
    return spans


def _chunks(pm, host, taus, tests, path_length, want_front):
    """Run the word traversal chunk by chunk; yield ``(frames, outputs)``
    for each chunk, ``frames`` the flat frame index of each camera (``-1``
    for padding)."""
    order = _word_padded(len(taus), path_length)
    real = np.ones(len(order), bool)
    real[1:] = order[1:] != order[:-1]
    for start, n in _chunk_spans(len(order)):
        idx = order[start:start + n]
        part = jax.tree.map(lambda a: a[idx], host)
        out = _front_jax.counts(pm, part, taus[idx], tests, False, want_front=want_front)
        yield np.where(real[start:start + n], idx, -1), out


# -- the C core's words ------------------------------------------------------------------

FRAMES = _core.FRAMES
# Words per call when refine_path streams a path: the fewest and the most.
# Each call has a fixed cost that its frames share, so a small model's path
# takes the most words per call; a block's lists are held until its frames
# are read while the next block runs, so the words are halved (down to the
# fewest) until a block's lists fit STREAM_BYTES: a large model's memory
# stays that of a few words.
WORDS_STREAMED = (4, 16)
STREAM_BYTES = 8 << 20
# Bytes a word's lists take per slot: pcols and positions int32, ran uint16.
_LIST_BYTES = 4 + 2 + 4


def words_streamed(slots: int) -> int:
    """Words per call when streaming a path of a model with ``slots`` pcols
    (``P``): the most of :data:`WORDS_STREAMED` halved, not below the
    fewest, until a block's lists (``[words, P + SPARE]``) fit
    :data:`STREAM_BYTES`."""
    fewest, words = WORDS_STREAMED
    while words > fewest and words * _LIST_BYTES * (slots + _core.SPARE) > STREAM_BYTES:
        words //= 2
    return max(words, fewest)


def frames_per_word() -> int:
    """Consecutive frames traversed together: 16 in the C core, 32 as JAX kernels."""
    return FRAMES if _core.enabled() else WORD


@functools.lru_cache(maxsize=None)
def _path_words(tests, orthographic: bool, lists: bool, room=None):
    """``f(tables, one_tables, cameras, taus)``: :func:`pmjax.engines._core.refine_words`
    of frames padded to whole words; ``vmap`` over paths flattens them into
    one call (each path's words are its own)."""

    @jax.custom_batching.custom_vmap
    def words(tables, one_tables, cameras):
        return _core.refine_words(tables, one_tables, cameras, tests, orthographic, lists, room=room)

    @words.def_vmap
    def words_batched(axis_size, in_batched, tables, one_tables, cameras):
        if any(jax.tree.leaves(in_batched[:2])):
            raise ValueError("the front engine's tables cannot be batched: vmap over paths, not over meshes")
        if not in_batched[2]:
            cameras = jnp.broadcast_to(cameras, (axis_size,) + cameras.shape)
        T = cameras.shape[1]
        out = words(tables, one_tables, cameras.reshape(axis_size * T, -1))
        counts, at_once, lists_, overflow = out
        W = T // FRAMES
        unflat = lambda x, n: x.reshape((axis_size, n) + x.shape[1:])
        out = (unflat(counts, T), unflat(at_once, W), jax.tree.map(lambda x: unflat(x, W), lists_),
               unflat(overflow, W))
        return out, jax.tree.map(lambda _: True, out)

    return words


@functools.partial(jax.jit, static_argnames=("tests", "orthographic", "lists", "room"))
def _core_words(tables, one_tables, camera_rows, tests, orthographic, lists, room=None):
    return _path_words(tests, orthographic, lists, room)(tables, one_tables, camera_rows)


# Int32 of unsure records a call holds (None: the core's default); tests set
# it small, so that words with unsure decisions take the overflow path.
RECORD_ROOM = None


def _core_word_plan(pm, host, taus, path_length, words_per_call):
    """The core's tables for words and for single frames, the frames in word
    order (each path padded to whole words by repeating its last frame),
    which of them are real (not a repeat), the calls' spans of words and the
    frames' camera rows."""
    d = derived(pm)
    order = _word_padded(len(taus), path_length, FRAMES)
    real = np.ones(len(order), bool)
    real[1:] = order[1:] != order[:-1]
    spans = _core.word_spans(len(order) // FRAMES, words_per_call)
    return d.core_words, d.core, order, real, spans, _core.host_camera_rows(host, taus, d.exponent)


def _core_path_counts(pm, host, taus, tests, path_length, cols, ms, bar, timing):
    """:func:`path_counts` through the C core's words, a block of words per call."""
    tables, one_tables, order, real, spans, rows = _core_word_plan(pm, host, taus, path_length, WORDS_PER_CALL)

    def call(w0, n):
        return _core_words(tables, one_tables, rows[order[w0 * FRAMES:(w0 + n) * FRAMES]], tests, host.orthographic,
                           False, RECORD_ROOM)

    if timing:  # compiled for every block size before the clock starts
        for size in sorted({n for _, n in spans}):
            jax.block_until_ready(call(0, size))
    counts_of = _Counts.of(pm)
    t = time.perf_counter()
    for w0, n in bar(spans, len(spans), "block"):
        counts = np.asarray(call(w0, n)[0])
        lanes = slice(w0 * FRAMES, (w0 + n) * FRAMES)
        frames = order[lanes][real[lanes]]
        for col, v in zip(cols, counts_of(counts[:, 1], counts[:, 2], np)):
            col[frames] = v[real[lanes]]
        now = time.perf_counter()
        ms[frames] = 1e3 * (now - t) / max(1, len(frames))
        t = now


# Keys naming a block of words' lists for a MeshStream (its frames share them):
# one count for every block, so that no two blocks' lists share a key.
_BLOCK_KEYS = itertools.count(1)


def _frame_refinement(fields: dict) -> Refinement:
    """A :class:`Refinement` of a path's frame from its fields: the frozen
    dataclass's ``__init__`` sets each field through ``object.__setattr__``,
    which costs a path more than its frame's traversal; ``fields`` (a new
    dict, the instance's from here on) becomes its attributes at once
    instead (the same instance)."""
    r = object.__new__(Refinement)
    object.__setattr__(r, "__dict__", fields)
    return r


def _rounded_tail(order, real, spans, most):
    """The calls after the whole blocks of ``most`` words (the rest in
    powers of two) made one call of the next power of two when that adds
    at most one word per two calls it saves: a call has a fixed cost that
    a small model's few words do not outweigh (a large model's blocks of a
    few words leave a tail too short to pay for a word). The added words
    repeat the last frame and are not real.

    Returns:
        ``(order, real, spans)``, padded where the tail became one call.
    """
    whole = [span for span in spans if span[1] == most]
    tail = spans[len(whole):]
    rest = sum(n for _, n in tail)
    padded = 1 << max(rest - 1, 0).bit_length()
    if len(tail) < 2 or 2 * (padded - rest) > len(tail) - 1:
        return order, real, spans
    extra = (padded - rest) * FRAMES
    order = np.concatenate([order, np.full(extra, order[-1], order.dtype)])
    real = np.concatenate([real, np.zeros(extra, bool)])
    return order, real, whole + [(tail[0][0], padded)]


def _word_blocks(pm, host, taus, tests, path_length):
    """The word traversal of a path with lists, a block of words per call:
    each block an XLA program dispatched before the frames of the last are
    read, so that it runs meanwhile on XLA's threads.

    Returns:
        ``(order, real, blocks)``: the frames in word order, which of them
        are real (not a repeat), and an iterator of ``(first word, words,
        counts, (pcols, ran, positions), overflow)`` per block, NumPy arrays.
    """
    most = words_streamed(derived(pm).core_words.n_pcols)
    tables, one_tables, order, real, spans, rows = _core_word_plan(pm, host, taus, path_length, most)
    order, real, spans = _rounded_tail(order, real, spans, most)

    def call(w0, n):
        return _core_words(tables, one_tables, rows[order[w0 * FRAMES:(w0 + n) * FRAMES]], tests, host.orthographic,
                           True, RECORD_ROOM)

    def blocks():
        running = call(*spans[0]) if spans else None
        for i, (w0, n) in enumerate(spans):
            counts, _, lists, overflow = running
            # Dispatched before this block's frames are read: it runs meanwhile.
            running = call(*spans[i + 1]) if i + 1 < len(spans) else None
            yield w0, n, np.asarray(counts), tuple(np.asarray(a) for a in lists), np.asarray(overflow)

    return order, real, blocks()


def _core_path_frames(pm, host, taus, tests, path_length, stream=None) -> Iterator:
    """The frames of a path through the C core's words with their lists, a
    few words per call (:func:`_word_blocks`); the frames of a word whose
    unsure records did not fit are refined alone.

    Args:
        stream: ``None``, or a :class:`MeshStream` of ``pm`` that follows
            the frames (each frame's change made by its word's lists).

    Yields:
        each frame's :class:`Refinement`; with ``stream``, ``(refinement,
        MeshChange)``.
    """
    order, real, blocks = _word_blocks(pm, host, taus, tests, path_length)
    counts_of = _Counts.of(pm)
    real_lanes = real.tolist()  # Python bools: read once per frame
    lane_step = stream._step_lane if stream is not None and stream._stream is not None else None
    for w0, n, counts, (pcols, ran, positions), overflow in blocks:
        faces, vertices, executed = counts_of(counts[:, 1], counts[:, 2], np)
        # Each frame's counts and item in the block's counts as lists of
        # NumPy scalars (one pass each; a frame then reads them by index).
        faces, vertices, executed = list(faces), list(vertices), list(executed)
        items = list(np.arange(n * FRAMES, dtype=np.int32))
        block = next(_BLOCK_KEYS) << 20
        for w in range(n):
            lanes = range((w0 + w) * FRAMES, (w0 + w + 1) * FRAMES)
            if overflow[w]:
                for lane in lanes:
                    if real_lanes[lane]:
                        r = refine(pm, jax.tree.map(lambda a: a[order[lane]], host), taus[order[lane]], tests)
                        yield r if stream is None else (r, stream.update(r))
                continue
            m = int(counts[w * FRAMES, 0])  # the word's slots (every frame lists them)
            visited, word_ran, at = pcols[w, :m], ran[w], positions[w]
            slots = np.int32(m)
            # The word's lists as a stream steps to them (its frames then
            # pass their bit alone: MeshStream._step_lane).
            word = (at, word_ran, 0, m, block | w)
            for j, lane in enumerate(lanes):
                if not real_lanes[lane]:
                    continue
                k = w * FRAMES + j
                # Its executed bits are made from the word's when first read.
                r = _frame_refinement({
                    "pm": pm, "visited": visited, "_lane": (word_ran, m, j), "dense": None,
                    "n_faces": faces[k], "n_vertices": vertices[k], "n_executed": executed[k],
                    "front_positions": positions, "core_ran": ran, "core_counts": counts, "core_item": items[k],
                    "n_slots": slots})
                if stream is None:
                    yield r
                else:
                    yield r, (lane_step(word, j) if lane_step is not None else stream.update(r))


def refine_path(pm: ProgressiveMesh, cameras: Camera, tau=1.0, *, budget=None, tests: Tests = ALL_TESTS,
                coherent: bool = True) -> Iterator[Refinement]:
    """The refinements of an ordered camera path, one per frame, streamed.

    Each is exactly ``pmjax.refine(pm, camera_t, tau_t, tests)`` (executed
    set, faces, ``vref``, counts). With ``coherent`` (default) consecutive
    frames are traversed together, 16 per word in the C core (32 as JAX
    kernels; module doc); memory stays that of a few words (or a chunk of
    words), whatever the path's length. Under ``jax.jit`` each frame is
    refined as :func:`pmjax.refine` refines it there.

    Args:
        pm: :class:`ProgressiveMesh`.
        cameras: camera batch, leading axis time ``[T]``.
        tau: pixels, a scalar or ``[T]`` (a tolerance changing along the path).
        budget: optional face budget, a scalar or ``[T]``: each frame's
            tolerance is then :func:`pmjax.faces_for_budget`'s (``tau`` is
            ignored).
        tests: :class:`Tests`.
        coherent: ``False`` refines each frame alone with :func:`pmjax.refine`
            (same results; for comparison).

    Yields:
        :class:`Refinement` per frame, in order.

    Raises:
        PathError: an empty path, a non-finite camera, an image size that
            changes along the path, a bad ``tau`` or budget (naming the frame).
    """
    check_mesh(pm, "refine_path")
    check_camera_type(cameras, "refine_path", "cameras")
    if is_traced(cameras, tau, budget):
        T = _traced_path_length(cameras)
        taus = _traced_taus(pm, cameras, tau, budget, tests, (T,))
        for i in range(T):
            yield refine(pm, jax.tree.map(lambda a: a[i], cameras), taus[i], tests)
        return
    yield from _path_frames(pm, cameras, tau, budget, tests, coherent)


def _path_frames(pm, cameras, tau, budget, tests, coherent, stream=None):
    """:func:`refine_path` of concrete cameras: each frame's refinement, or
    with ``stream`` (a :class:`MeshStream`) ``(refinement, MeshChange)``,
    the stream following the frames (by the C core's word lists where they
    made the frame: :func:`_core_path_frames`)."""
    host, taus, budgets, shape = check_path(cameras, tau, budget)
    if budgets is not None:
        taus = _budget_taus(pm, host, budgets, tests)
    engine = select(pm, "front", batch=True) if coherent else "dense"
    if engine == "core":
        yield from _core_path_frames(pm, host, taus, tests, shape[-1], stream)
        return
    for r in _other_path_frames(pm, host, taus, tests, shape, coherent, engine):
        yield r if stream is None else (r, stream.update(r))


def _other_path_frames(pm, host, taus, tests, shape, coherent, engine):
    """The frames of a path refined alone (dense, or not ``coherent``) or by
    the JAX kernels' words of 32 frames."""
    if not coherent or engine == "dense":
        for i in range(len(taus)):
            yield refine(pm, jax.tree.map(lambda a: a[i], host), taus[i], tests)
        return
    for frames, (faces, vertices, executed, visited, ran) in _chunks(pm, host, taus, tests, shape[-1], True):
        faces, vertices, executed = np.asarray(faces), np.asarray(vertices), np.asarray(executed)
        visited, ran = np.asarray(visited), np.asarray(ran)
        for w in range(visited.shape[0]):
            # The word's visited pcols once; each frame reads its own bit.
            keep = visited[w] < pm.n_pcols
            ids, bits = visited[w][keep], ran[w][keep]
            for lane in range(WORD):
                k = w * WORD + lane
                if k >= len(frames) or frames[k] < 0:
                    continue
                yield Refinement(pm=pm, visited=ids, visited_executed=((bits >> lane) & 1).astype(bool), dense=None,
                                 n_faces=faces[k], n_vertices=vertices[k], n_executed=executed[k])


def path_mesh_changes(pm: ProgressiveMesh, cameras: Camera, tau=1.0, *, budget=None, tests: Tests = ALL_TESTS,
                      stream: "MeshStream | None" = None) -> Iterator[tuple[Refinement, "MeshChange"]]:
    """The frames of :func:`refine_path`, each with its drawable mesh's change.

    A :class:`MeshStream` follows the path: each frame's
    :class:`MeshChange` turns the last frame's mesh (in stable slots) into
    this frame's, at a cost that follows what changed. The stream then holds
    the frame's mesh (``stream.mesh()`` is ``refinement.mesh()``). Eager only
    (the stream is host-side).

    Args:
        pm, cameras, tau, budget, tests: as :func:`refine_path`.
        stream: a :class:`MeshStream` of ``pm`` to continue (a viewer's, or
            one that followed another path: the first change is then from
            its last mesh); ``None``: a new one (the first change writes
            every slot).

    Yields:
        ``(Refinement, MeshChange)`` per frame, in order.

    Raises:
        PathError: as :func:`refine_path`.
        ValueError: a stream of another mesh, or cameras being traced.
    """
    check_mesh(pm, "path_mesh_changes")
    if is_traced(cameras, tau, budget):
        raise ValueError("path_mesh_changes: the cameras are being traced; the mesh stream holds host arrays "
                         "(call it eagerly, or use refine_path under jax.jit)")
    if stream is None:
        stream = MeshStream(pm)
    elif stream.pm is not pm:
        raise ValueError("path_mesh_changes: stream is a MeshStream of another mesh; make one with MeshStream(pm)")
    check_camera_type(cameras, "refine_path", "cameras")
    yield from _path_frames(pm, cameras, tau, budget, tests, True, stream)


def _traced_path_length(cameras) -> int:
    eye = cameras.eye
    if eye.ndim != 2:
        raise PathError(f"a path needs cameras with a leading time axis [T], got eye of shape {eye.shape}")
    return int(eye.shape[0])


def _traced_taus(pm, cameras, tau, budget, tests, shape):
    """Per-frame tolerances of a traced path (``shape`` its leading axes)."""
    if budget is not None:
        flat = jax.tree.map(lambda a: a.reshape((-1,) + a.shape[len(shape):]), cameras)
        budgets = jnp.broadcast_to(kernel_budgets(pm, budget, "the path's budget"), shape).reshape(-1)
        return _budget_taus_traced(pm, flat, budgets, tests).reshape(shape)
    return jnp.broadcast_to(_checked_tau(tau), shape)


def path_counts(pm: ProgressiveMesh, cameras: Camera, tau=1.0, *, budget=None, tests: Tests = ALL_TESTS,
                coherent: bool = True, method: str = "auto", paths: bool = False, timing: bool = False,
                progress: bool = False) -> dict:
    """Per-frame counts along one path, or K paths advanced together.

    The counts of :func:`refine_path` without the per-frame results: what
    offline evaluation of camera paths needs.

    Args:
        pm: :class:`ProgressiveMesh`.
        cameras: camera batch, leading axes ``[T]``, or ``[K, T]`` with ``paths``.
        tau, budget, tests, coherent: as :func:`refine_path`.
        method: the engine of :func:`pmjax.refine` without ``coherent``.
        paths: the cameras are K paths of T frames (``[K, T]``); words never
            mix two paths.
        timing: also return ``milliseconds`` per frame: with ``coherent``,
            the wall time of the frame's block over its frames, after the
            calls of every block size were compiled on the path's first
            frames; else each frame's own ``refine`` (compiled beforehand).
        progress: a progress bar over the blocks (or frames).

    Returns:
        dict of arrays shaped like the leading axes: ``faces``, ``vertices``,
        ``executed_count`` (int32), ``tau`` (float32, the tolerance each
        frame was refined at) and, with ``timing``, ``milliseconds``
        (float64). NumPy arrays; JAX arrays under ``jit``/``vmap``, where
        the path is counted in one call (``vmap`` over paths: one call for
        all of them).
    """
    check_mesh(pm, "path_counts")
    check_camera_type(cameras, "path_counts", "cameras")
    if is_traced(cameras, tau, budget):
        return _traced_path_counts(pm, cameras, tau, budget, tests, coherent, method, paths)
    host, taus, budgets, shape = check_path(cameras, tau, budget, paths=paths)
    if budgets is not None:
        taus = _budget_taus(pm, host, budgets, tests)
    n = len(taus)
    cols = [np.zeros(n, np.int32) for _ in range(3)]
    ms = np.zeros(n)
    bar = lambda it, total, unit: it
    if progress:
        from tqdm import tqdm

        bar = lambda it, total, unit: tqdm(it, total=total, unit=unit, desc="path")
    engine = select(pm, "front", batch=True) if coherent else "dense"
    if engine == "dense":
        frame = lambda i: jax.tree.map(lambda a: a[i], host)
        if timing:  # compile outside the timings
            jax.block_until_ready(refine(pm, frame(0), taus[0], tests, method=method))
        for i in bar(range(n), n, "frame"):
            t = time.perf_counter()
            r = jax.block_until_ready(refine(pm, frame(i), taus[i], tests, method=method))
            ms[i] = 1e3 * (time.perf_counter() - t)
            for col, v in zip(cols, (r.n_faces, r.n_vertices, r.n_executed)):
                col[i] = int(v)
    elif engine == "core":
        _core_path_counts(pm, host, taus, tests, shape[-1], cols, ms, bar, timing)
    else:
        padded = len(_word_padded(n, shape[-1]))
        if timing:  # one call per chunk size on the first frames: compiled, and buffers fitted
            for size in sorted({size for _, size in _chunk_spans(padded)}):
                idx = np.minimum(np.arange(size), n - 1)
                _front_jax.counts(pm, jax.tree.map(lambda a: a[idx], host), taus[idx], tests, False)
        chunks = _chunks(pm, host, taus, tests, shape[-1], False)
        t = time.perf_counter()
        for frames, out in bar(chunks, len(_chunk_spans(padded)), "chunk"):
            real = frames >= 0
            for col, v in zip(cols, out):
                col[frames[real]] = np.asarray(v)[real]
            now = time.perf_counter()
            ms[frames[real]] = 1e3 * (now - t) / max(1, int(real.sum()))
            t = now
    out = dict(zip(("faces", "vertices", "executed_count"), (c.reshape(shape) for c in cols)))
    out["tau"] = taus.reshape(shape)
    if timing:
        out["milliseconds"] = ms.reshape(shape)
    return out


def _traced_path_counts(pm, cameras, tau, budget, tests, coherent, method, paths):
    """:func:`path_counts` under a trace: the whole path (or paths) in one call."""
    eye = cameras.eye
    axes = 2 if paths else 1
    if eye.ndim != axes + 1:
        want = "[K, T]" if paths else "[T]"
        raise PathError(f"a path needs cameras with leading axes {want} (time last), got eye of shape {eye.shape}")
    shape = tuple(eye.shape[:-1])
    taus = _traced_taus(pm, cameras, tau, budget, tests, shape)
    flat = jax.tree.map(lambda a: a.reshape((-1,) + a.shape[axes:]), cameras)
    engine = select(pm, "front" if coherent else method, batch=True, traced=True)
    counts_of = _Counts.of(pm)
    if engine == "core" and coherent:
        d = derived(pm)
        # Each path padded to whole words (repeating its last frame).
        idx = _word_padded(int(np.prod(shape)), shape[-1], FRAMES)
        rows = _core.camera_rows(flat, taus.reshape(-1), d.exponent)[idx]
        counts = _core_words(d.core_words, d.core, rows, tests, cameras.orthographic, False)[0]
        real = np.ones(len(idx), bool)
        real[1:] = idx[1:] != idx[:-1]
        counts = counts[np.flatnonzero(real)]
        cols = counts_of(counts[:, 1], counts[:, 2])
    else:
        cols = _batch_counts_traced(pm, flat, taus.reshape(-1), tests, method)
    out = dict(zip(("faces", "vertices", "executed_count"), (c.reshape(shape) for c in cols)))
    out["tau"] = taus
    return out


def _batch_counts_traced(pm, cameras, taus, tests, method):
    """Counts of traced cameras, each at its own tolerance (one refinement per camera, vmapped)."""
    def one(camera, tau):
        r = refine(pm, camera, tau, tests, method=method)
        return r.n_faces, r.n_vertices, r.n_executed

    return jax.vmap(one)(cameras, taus)


def path_refinement_pairs(pm: ProgressiveMesh, cameras: Camera, tau, *, tests: Tests = ALL_TESTS,
                          coherent: bool = True) -> Iterator[tuple[Refinement, Refinement]]:
    """Per frame, ``(refinement at tau, refinement at tau 0)``: the executed
    set and the pcols a view hides (culled or facing away: what runs even at
    tau 0, :func:`pmjax.hidden_pcols`), as a geomorphed path needs them."""
    return zip(refine_path(pm, cameras, tau, tests=tests, coherent=coherent),
               refine_path(pm, cameras, 0.0, tests=tests, coherent=coherent))


# -- drawable meshes along a path: each frame a change against the last ------------------


class MeshChange:
    """One frame's change to a :class:`MeshStream`'s mesh: the slots whose
    contents changed, each once, with their new contents. Writing these rows
    into buffers holding the last frame's slots gives this frame's.

    With the C core the change is one buffer the core packed, and each array
    is a view of it made when first read (a frame whose change is not read
    costs no arrays); it is the change's own (later frames do not change it).

    Attributes:
        face_slots: ``int32 [k]`` face slots changed.
        faces: ``int32 [k, 3]`` their vertex slots (corners in the original
            face's order); a row of -1: the slot is free (the face is gone).
        vertex_slots: ``int32 [u]`` vertex slots changed.
        vertex_ids: ``int32 [u]`` their PM vertex ids (-1: the slot is free).
        vertex_positions: ``float32 [u, 3]`` their positions, model units
            (zero in free slots).
        n_face_slots, n_vertex_slots: slots in use so far (the rows a
            buffer needs); every slot index is below them.
    """

    __slots__ = ("n_face_slots", "n_vertex_slots", "_packed", "_k", "_u", "_arrays")

    def __init__(self, face_slots, faces, vertex_slots, vertex_ids, vertex_positions, n_face_slots: int,
                 n_vertex_slots: int):
        self.n_face_slots, self.n_vertex_slots = n_face_slots, n_vertex_slots
        self._arrays = [face_slots, faces, vertex_slots, vertex_ids, vertex_positions]

    @classmethod
    def _of_packed(cls, packed, k: int, u: int, n_face_slots: int, n_vertex_slots: int) -> "MeshChange":
        """The change the core packed in ``packed`` (``int32`` face slots
        ``[k]``, faces ``[k, 3]``, vertex slots ``[u]``, ids ``[u]``, then
        ``float32`` positions ``[u, 3]``), its arrays made when read."""
        change = object.__new__(cls)
        change.n_face_slots, change.n_vertex_slots = n_face_slots, n_vertex_slots
        change._packed, change._k, change._u, change._arrays = packed, k, u, None
        return change

    def _array(self, which: int) -> np.ndarray:
        arrays = self._arrays
        if arrays is None:
            arrays = self._arrays = [None] * 5
        a = arrays[which]
        if a is None:
            # An array over its bytes of the packed buffer (it keeps the
            # buffer alive): (shape, dtype, byte offset) of each field.
            k, u = self._k, self._u
            shape, dtype, offset = (((k,), _INT32, 0), ((k, 3), _INT32, 4 * k), ((u,), _INT32, 16 * k),
                                    ((u,), _INT32, 16 * k + 4 * u), ((u, 3), _FLOAT32, 16 * k + 8 * u))[which]
            a = arrays[which] = _array(shape, dtype, self._packed, offset)
        return a

    face_slots = property(lambda self: self._array(0), doc="``int32 [k]`` face slots changed.")
    faces = property(lambda self: self._array(1), doc="``int32 [k, 3]`` their vertex slots (-1 rows: freed).")
    vertex_slots = property(lambda self: self._array(2), doc="``int32 [u]`` vertex slots changed.")
    vertex_ids = property(lambda self: self._array(3), doc="``int32 [u]`` their PM vertex ids (-1: freed).")
    vertex_positions = property(lambda self: self._array(4), doc="``float32 [u, 3]`` their positions.")

    # The seven fields in order, with a tuple's protocol: unpacking, indexing,
    # pickling and JAX's tree functions see the same fields as a NamedTuple's.
    _fields = ("face_slots", "faces", "vertex_slots", "vertex_ids", "vertex_positions", "n_face_slots",
               "n_vertex_slots")

    def __iter__(self):
        return (getattr(self, name) for name in self._fields)

    def __len__(self) -> int:
        return len(self._fields)

    def __getitem__(self, i):
        return getattr(self, self._fields[i]) if isinstance(i, int) else tuple(self)[i]

    def _asdict(self) -> dict:
        return dict(zip(self._fields, self))

    def _replace(self, **fields) -> "MeshChange":
        return MeshChange(**{**self._asdict(), **fields})

    def __reduce__(self):
        return MeshChange, tuple(self)

    def __repr__(self) -> str:
        return (f"MeshChange({len(self.face_slots)} face slots, {len(self.vertex_slots)} vertex slots; "
                f"n_face_slots={self.n_face_slots}, n_vertex_slots={self.n_vertex_slots})")


jax.tree_util.register_pytree_with_keys(
    MeshChange, lambda change: (tuple((jax.tree_util.GetAttrKey(k), x) for k, x in change._asdict().items()), None),
    lambda _, fields: MeshChange(*fields), flatten_func=lambda change: (tuple(change), None))


class MeshStream:
    """The drawable mesh of the last frame given, kept in stable slots, and
    each new frame as a :class:`MeshChange` against it.

    A face slot holds one face drawn (its three vertex slots), a vertex slot
    one vertex of the front (a ``vref`` representative: its id and
    position). After :meth:`update` with a refinement, the faces held (rows
    of :attr:`faces` that are not -1, over :attr:`vertex_positions`) are
    ``refinement.mesh()``'s faces as a set, each with its corners in the same
    order and at the same positions; :meth:`mesh` compacts them into exactly
    ``refinement.mesh()``'s arrays.

    With the C core (``pmjax/engines/core/mesh_stream.c``) a frame costs
    what changed: the pcols whose executed bit flipped since the last frame
    (found from the two refinements' visited lists) are applied one by one, a
    split handing its vertex slot to its first child and re-pointing the
    corners that move to the second, a collapse the reverse, each drawing or
    removing its kill list. Freed slots are reused first, so memory is one
    frame's mesh plus the change (and maps over the hierarchy), whatever the
    path's length. Any sequence of refinements of the mesh may be given (a
    cut, a teleport, a new tolerance or image size): the change is always to
    the new frame's mesh. Without the core, each frame's mesh is compared
    with the last by ids (same results, cost of the whole mesh).

    A host-side object: :meth:`update` takes concrete refinements (not
    under ``jax.jit``), as a viewer or a renderer holds them. One thread at a
    time: the C core's calls release the GIL and a stream has no lock, so
    threads that share a stream must take turns (a lock of their own).

    Args:
        pm: the :class:`ProgressiveMesh` whose refinements it is given.
    """

    def __init__(self, pm: ProgressiveMesh):
        check_mesh(pm, "MeshStream")
        self.pm = pm
        self._last = None
        # The lists of a step that failed (the core may hold them), kept alive.
        self._kept = None
        self._block = (None,)  # the last block's lists: (its object, positions, ran on the host, key)
        d = derived(pm)
        if _core.enabled() and pm.n_pcols > 0:
            from .engines._front_mesh import stream_tables

            tables = d.memo("mesh_stream_tables", lambda: stream_tables(
                d.depth_first, np.asarray(pm.parent), d.layout["order"], d.core_mesh))
            self._at = d.memo("mesh_stream_at", lambda: _positions_of(d.layout["order"]))
            self._stream = _core._pmx.mesh_stream_new(*tables, pm.n_original_vertices, pm.n_faces)
            self._generation = -1
            self._step = _core._pmx.mesh_stream_step  # bound once: the per-frame calls
            self._lane = _core._pmx.mesh_stream_lane
            self._counts = (0,) * 8
        else:
            self._stream = None
            self._numpy = _NumpyStream(pm)

    def _held(self, which: int) -> np.ndarray:
        """A view of the core's slots (0: faces' vertex slots, 1: face ids, 2:
        vertex ids, 3: positions), made again whenever it has grown them."""
        generation = self._counts[7]
        if generation != self._generation:
            fv, fid, vid, vpos = _core._pmx.mesh_stream_arrays(self._stream)
            self._arrays = (np.frombuffer(fv, np.int32).reshape(-1, 3), np.frombuffer(fid, np.int32),
                            np.frombuffer(vid, np.int32), np.frombuffer(vpos, np.float32).reshape(-1, 3))
            self._generation = generation
        return self._arrays[which]

    def _corner_searches(self) -> dict | None:
        """How many corners of faces the stream drew found their vertex each
        way since it was made: ``split`` (at the split's two vertices),
        ``had`` (from the vertex the face's third corner had when last
        removed), ``around`` (among the split's neighbours), ``up`` (up from
        the corner's original vertex: the base faces and any corner the
        others miss). None without the core (NumPy stream)."""
        if self._stream is None:
            return None
        return dict(zip(("split", "had", "around", "up"), _core._pmx.mesh_stream_searches(self._stream)))

    def _frame(self, r: Refinement):
        """The refinement's visited slots as the core's stream reads them:
        ``(positions, ran, frame bit, slots, key)``, ``key`` naming a word's
        lists (its frames share them) or -1."""
        if r.core_ran is not None:
            ran = r.core_ran
            if ran is not self._block[0]:  # a new block of words (its frames come one after another)
                self._block = (ran, np.asarray(r.front_positions), np.asarray(ran), next(_BLOCK_KEYS) << 20)
            positions, bits = self._block[1], self._block[2]
            if bits.ndim == 2:
                word, bit = divmod(int(r.core_item), _core.FRAMES)
                return positions[word], bits[word], bit, int(r.n_slots), self._block[3] | word
            return positions, bits, 0, int(r.n_slots if r.n_slots is not None else len(bits)), -1
        # Other engines: every pcol that did not run, in breadth-first order.
        not_run = np.flatnonzero(~np.asarray(r.executed))
        positions = np.sort(self._at[not_run]).astype(np.int32)
        return positions, np.zeros(len(positions), np.uint8), 0, len(positions), -1

    def update(self, refinement: Refinement) -> MeshChange:
        """Moves the stream to a refinement's mesh.

        Args:
            refinement: a concrete :class:`Refinement` of :attr:`pm` (any
                engine; a path's frames or single views, in any order).

        Returns:
            :class:`MeshChange` from the mesh held before (the first update:
            from nothing, every slot written).

        Raises:
            ValueError: a refinement of another mesh, or one being traced.
        """
        r = refinement
        if r.pm is not self.pm and (r.pm.n_pcols, r.pm.n_faces, r.pm.n_original_vertices) != (
                self.pm.n_pcols, self.pm.n_faces, self.pm.n_original_vertices):
            raise ValueError(f"MeshStream.update: the refinement is of another mesh ({r.pm.n_pcols} pcols, "
                             f"{r.pm.n_faces} faces; the stream's: {self.pm.n_pcols}, {self.pm.n_faces})")
        if is_traced(r.n_faces, r.visited, r.dense):
            raise ValueError("MeshStream.update: the refinement is being traced; a stream holds host arrays, "
                             "give it concrete refinements (outside jax.jit)")
        if self._stream is None:
            return self._numpy.update(r)
        return self._step_frame(self._frame(r))

    def _step_frame(self, frame) -> MeshChange:
        """The core's step to a frame's lists (``(positions, ran, bit, slots,
        key)``, :meth:`_frame`), its change in the bytearray the core packs
        it in (:meth:`MeshChange._of_packed`)."""
        last = self._last
        if last is not None and frame[4] >= 0 and frame[4] == last[4]:  # the word held: lists not passed again
            return self._stepped(frame, self._lane, frame[2])
        return self._stepped(frame, self._step, *frame)

    def _step_lane(self, word, bit: int) -> MeshChange:
        """The core's step to frame ``bit`` of a word whose lists are ``word``
        (``(positions, ran, 0, slots, key)``, one tuple for all its frames):
        the lists passed once, at the first of its frames stepped to."""
        if self._last is word:
            return self._stepped(word, self._lane, bit)
        return self._stepped(word, self._step, word[0], word[1], bit, word[3], word[4])

    def _stepped(self, lists, call, *args) -> MeshChange:
        """``call(stream, *args)``, the core's step to the frame whose lists
        are ``lists``, and its change. The core reads the last frame's lists
        at the next step, so they are kept; after a failed step the core may
        hold either frame's, so both stay and the stream takes no more steps."""
        if self._kept:
            raise ValueError("MeshStream: an earlier step failed; make a new MeshStream")
        try:
            counts = call(self._stream, *args)
        except BaseException:
            self._kept = [lists]
            raise
        self._last, self._counts = lists, counts
        return _of_packed(counts[8], counts[2], counts[3], counts[0], counts[1])

    @property
    def faces(self) -> np.ndarray:
        """``int32 [n_face_slots, 3]`` every face slot's vertex slots (-1 rows: free)."""
        if self._stream is None:
            return self._numpy.faces[:self._numpy.n_face_slots].copy()
        return self._held(0)[:self._counts[0]].copy() if self._last is not None else np.zeros((0, 3), np.int32)

    @property
    def face_ids(self) -> np.ndarray:
        """``int32 [n_face_slots]`` the original face in each slot (-1: free)."""
        if self._stream is None:
            return self._numpy.face_ids[:self._numpy.n_face_slots].copy()
        return self._held(1)[:self._counts[0]].copy() if self._last is not None else np.zeros(0, np.int32)

    @property
    def vertex_ids(self) -> np.ndarray:
        """``int32 [n_vertex_slots]`` the PM vertex in each slot (-1: free)."""
        if self._stream is None:
            return self._numpy.vertex_ids[:self._numpy.n_vertex_slots].copy()
        return self._held(2)[:self._counts[1]].copy() if self._last is not None else np.zeros(0, np.int32)

    @property
    def vertex_positions(self) -> np.ndarray:
        """``float32 [n_vertex_slots, 3]`` each vertex slot's position (zero where free)."""
        if self._stream is None:
            return self._numpy.positions[:self._numpy.n_vertex_slots].copy()
        return self._held(3)[:self._counts[1]].copy() if self._last is not None else np.zeros((0, 3), np.float32)

    def mesh(self):
        """The mesh held, compacted as :meth:`pmjax.Refinement.mesh` gives it.

        Returns:
            ``(vertices float32[n, 3], faces int32[m, 3], vertex_ids int32[n])``:
            faces in increasing original face order, ``vertex_ids`` sorted;
            new arrays, the caller's (later updates do not change them).
        """
        if self._stream is not None:  # the core's kept rows, merged with the changes since
            n_faces, n_used = self._counts[4], self._counts[6]
            packed = _core._pmx.mesh_stream_compact(self._stream)  # a new buffer: faces, ids, positions
            return (_array((n_used, 3), _FLOAT32, packed, 12 * n_faces + 4 * n_used),
                    _array((n_faces, 3), _INT32, packed), _array((n_used,), _INT32, packed, 12 * n_faces))
        slots, ids, vids, positions = self.faces, self.face_ids, self.vertex_ids, self.vertex_positions
        live = np.flatnonzero(ids >= 0)
        faces = slots[live[np.argsort(ids[live])]]
        used = np.unique(faces)
        by_id = used[np.argsort(vids[used])]
        rank = np.zeros(len(vids), np.int32)
        rank[by_id] = np.arange(len(by_id), dtype=np.int32)
        return positions[by_id], rank[faces], vids[by_id]


# Arrays over a buffer the core packed (shape, dtype, buffer, byte offset).
_array, _INT32, _FLOAT32 = np.ndarray, np.dtype(np.int32), np.dtype(np.float32)
_of_packed = MeshChange._of_packed


def _positions_of(order: np.ndarray) -> np.ndarray:
    """Each pcol's breadth-first position (the inverse of ``order``)."""
    at = np.empty(len(order), np.int32)
    at[order] = np.arange(len(order), dtype=np.int32)
    return at


class _NumpyStream:
    """:class:`MeshStream` without the C core: each frame's mesh compared
    with the last by face and vertex ids (the same meshes; slots of its own)."""

    def __init__(self, pm):
        self.pm = pm
        F, V = pm.n_faces, pm.n_original_vertices + pm.n_pcols
        self.face_slot, self.vertex_slot = np.full(F, -1, np.int32), np.full(V, -1, np.int32)
        self.faces, self.face_ids = np.zeros((0, 3), np.int32), np.zeros(0, np.int32)
        self.vertex_ids, self.positions = np.zeros(0, np.int32), np.zeros((0, 3), np.float32)
        self.free_faces, self.free_vertices = [], []
        self.n_face_slots = self.n_vertex_slots = 0
        self.all_positions = np.asarray(pm.vertices, np.float32)

    def _take(self, free: list, n: int, kind: str) -> np.ndarray:
        reuse = [free.pop() for _ in range(min(n, len(free)))]
        count = getattr(self, f"n_{kind}_slots")
        fresh = np.arange(count, count + n - len(reuse), dtype=np.int32)
        setattr(self, f"n_{kind}_slots", count + len(fresh))
        if kind == "face" and self.n_face_slots > len(self.face_ids):
            grow = max(self.n_face_slots, 2 * len(self.face_ids)) - len(self.face_ids)
            self.faces = np.concatenate([self.faces, np.full((grow, 3), -1, np.int32)])
            self.face_ids = np.concatenate([self.face_ids, np.full(grow, -1, np.int32)])
        if kind == "vertex" and self.n_vertex_slots > len(self.vertex_ids):
            grow = max(self.n_vertex_slots, 2 * len(self.vertex_ids)) - len(self.vertex_ids)
            self.vertex_ids = np.concatenate([self.vertex_ids, np.full(grow, -1, np.int32)])
            self.positions = np.concatenate([self.positions, np.zeros((grow, 3), np.float32)])
        return np.concatenate([np.asarray(reuse, np.int32), fresh])

    def update(self, r) -> MeshChange:
        _, faces, ids = r.mesh()
        face_ids = np.flatnonzero(np.asarray(r.active)).astype(np.int32)
        # Vertices: the slots of vertices gone are freed, new vertices get slots.
        live_v = np.flatnonzero(self.vertex_slot >= 0)
        gone_v = np.setdiff1d(live_v, ids)
        freed_v = self.vertex_slot[gone_v]
        self.vertex_slot[gone_v] = -1
        self.vertex_ids[freed_v] = -1
        self.positions[freed_v] = 0
        self.free_vertices.extend(freed_v.tolist())
        new_v = ids[self.vertex_slot[ids] < 0]
        slots_v = self._take(self.free_vertices, len(new_v), "vertex")
        self.vertex_slot[new_v] = slots_v
        self.vertex_ids[slots_v] = new_v
        self.positions[slots_v] = self.all_positions[new_v]
        # Faces: gone ones freed, new ones placed, kept ones whose corners moved rewritten.
        live_f = np.flatnonzero(self.face_slot >= 0)
        gone_f = np.setdiff1d(live_f, face_ids)
        freed_f = self.face_slot[gone_f]
        self.face_slot[gone_f] = -1
        self.faces[freed_f] = -1
        self.face_ids[freed_f] = -1
        self.free_faces.extend(freed_f.tolist())
        new_f = face_ids[self.face_slot[face_ids] < 0]
        self.face_slot[new_f] = self._take(self.free_faces, len(new_f), "face")
        slots_f = self.face_slot[face_ids]
        corners = self.vertex_slot[ids[faces]]
        changed = np.any(self.faces[slots_f] != corners, axis=1)
        self.faces[slots_f] = corners
        self.face_ids[slots_f] = face_ids
        face_slots = np.unique(np.concatenate([freed_f, slots_f[changed]])).astype(np.int32)
        vertex_slots = np.unique(np.concatenate([freed_v, slots_v])).astype(np.int32)
        return MeshChange(face_slots, self.faces[face_slots], vertex_slots, self.vertex_ids[vertex_slots],
                          self.positions[vertex_slots], self.n_face_slots, self.n_vertex_slots)
