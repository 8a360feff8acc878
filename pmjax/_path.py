"""Coherent camera paths: every frame refined exactly as alone, consecutive frames together.

Consecutive cameras of a path see nearly the same front. The output-sensitive
traversal carries one bit per frame: a pcol is visited when any frame of a
word visits it, and each frame's tests and subtree bounds are evaluated as one
lane of the word. Run on consecutive frames, the union of their fronts is
little larger than one frame's, so each pcol near the front is fetched once for
the word and tested for all its frames in one vectorized pass: the coherence of
the path is what makes the word cheap. A word is 16 frames in the C loops
(:func:`pmjax._native.refine_word`) and 32 as JAX kernels (where the loops are
not built; :mod:`pmjax._front`). In the C loops most pcols are decided for all
of a word's frames at once, under a fat camera that covers them
(:func:`pmjax._native.fat_cameras`).

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

import collections
import itertools
import time
from typing import Iterator

import jax
import numpy as np

from . import _native
from ._bitsets import WORD
from ._camera import Camera, check_camera_values
from ._model import ProgressiveMesh
from ._predicate import ALL_TESTS, Tests
from ._refine import Refinement, _front_counts, check_budget, check_tau, faces_for_budget, refine

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
        out = _front_counts(pm, part, taus[idx], tests, False, want_front=want_front)
        yield np.where(real[start:start + n], idx, -1), out


def frames_per_word() -> int:
    """Consecutive frames traversed together: 16 in the C loops, 32 as JAX kernels."""
    return _native.FRAMES if _native.available() else WORD


def _word_order(n_frames: int, path_length: int):
    """Frame index per lane of the C loops' words (each path padded to whole
    words) and whether each lane is a real frame (not padding)."""
    order = _word_padded(n_frames, path_length, _native.FRAMES)
    real = np.ones(len(order), bool)
    real[1:] = order[1:] != order[:-1]
    return order, real


def _word_block(host, taus, order, real, w0: int, w1: int):
    """Words ``w0..w1`` of the padded frames: ``(frame index per lane, -1
    for padding), cameras, taus, views, fat cameras``, the views and fat
    cameras computed in one host pass."""
    F = _native.FRAMES
    idx = order[w0 * F:w1 * F]
    cams, word_taus = jax.tree.map(lambda a: a[idx], host), taus[idx]
    values = _native.host_views(cams, word_taus)
    return (np.where(real[w0 * F:w1 * F], idx, -1), cams, word_taus, values,
            _native.fat_cameras(values.reshape(w1 - w0, F, -1)))


def _native_words(pm, host, taus, tests, path_length, frames: bool):
    """The C word traversal over the frames, in order: yields ``(frame index
    per lane, -1 for padding), counts, lists`` per word
    (:func:`pmjax._native.refine_word`). The words are traversed by the
    cores, at most WORDS_AHEAD per core ahead of the consumer (memory: those
    words' lists), the constants of WORDS_AT_ONCE words computed together."""
    from concurrent.futures import ThreadPoolExecutor

    F = _native.FRAMES
    order, real = _word_order(len(taus), path_length)
    words = len(order) // F

    def jobs():
        for w0 in range(0, words, WORDS_AT_ONCE):
            lanes, cams, word_taus, values, fats = _word_block(host, taus, order, real, w0,
                                                               min(words, w0 + WORDS_AT_ONCE))
            for w in range(len(fats)):
                at = slice(w * F, (w + 1) * F)
                yield lanes[at], (jax.tree.map(lambda a: a[at], cams), word_taus[at], values[at], fats[w])

    def word(cams, word_taus, values, fat):
        counts, lists, _, _ = _native.refine_word(pm, cams, word_taus, tests, frames, values, fat)
        return counts, lists

    threads = _native._cores()
    pool = ThreadPoolExecutor(threads)
    pending = collections.deque()
    todo = jobs()
    try:
        for lanes, args in itertools.islice(todo, WORDS_AHEAD * threads):
            pending.append((lanes, pool.submit(word, *args)))
        while pending:
            lanes, done = pending.popleft()
            following = next(todo, None)
            if following is not None:
                pending.append((following[0], pool.submit(word, *following[1])))
            yield (lanes,) + done.result()
    finally:  # also when the consumer stops early
        for _, future in pending:
            future.cancel()
        pool.shutdown(wait=False)


# Words each core traverses ahead of the consumer of refine_path.
WORDS_AHEAD = 2


# Words whose camera constants are computed in one host pass (the C loops),
# and the most words counted by one C call.
WORDS_AT_ONCE = 16
# Records of unsure pairs (int32) held before they are decided together.
RECORDS_HELD = 1 << 20


def _native_path_counts(pm, host, taus, tests, path_length, cols, ms, bar):
    """:func:`path_counts` through the C word traversal: blocks of words
    (at least two per core, at most WORDS_AT_ONCE words) taken by the cores
    as they come free, each counted by one C call; the unsure pairs the
    blocks leave are decided in one call at the end (or whenever
    RECORDS_HELD of their records are held) and the counts corrected."""
    import queue
    import threading

    F = _native.FRAMES
    order, real = _word_order(len(taus), path_length)
    words = len(order) // F
    threads = _native._cores()
    size = max(1, min(WORDS_AT_ONCE, -(-words // (2 * threads))))
    blocks = iter([(w0, min(words, w0 + size)) for w0 in range(0, words, size)])
    n_blocks = -(-words // size)
    take, done = threading.Lock(), queue.Queue()
    # Per lane of the padded path: the pcols that did not run, the faces they keep.
    not_run, kept = np.zeros(len(order), np.int64), np.zeros(len(order), np.int64)

    def run():
        try:
            while True:
                with take:
                    span = next(blocks, None)
                if span is None:
                    return
                t = time.perf_counter()
                _, cams, word_taus, values, fats = _word_block(host, taus, order, real, *span)
                counted = _native.count_words(pm, cams, word_taus, tests, values, fats, span[0])
                done.put((span, counted, time.perf_counter() - t))
        except BaseException as e:  # handed to the caller's thread
            done.put(e)

    workers = [threading.Thread(target=run, daemon=True) for _ in range(threads)]
    for w in workers:
        w.start()
    held, n_held = [], 0
    for _ in bar(range(n_blocks), n_blocks, "block"):
        got = done.get()
        if isinstance(got, BaseException):
            raise got
        (w0, w1), (block_not_run, block_kept, records), seconds = got
        lanes = slice(w0 * F, w1 * F)
        not_run[lanes], kept[lanes] = block_not_run, block_kept
        held.append(records)
        n_held += len(records)
        if n_held >= RECORDS_HELD:
            _native.resolve_unsure(pm, np.concatenate(held), order, host, taus, tests, not_run, kept)
            held, n_held = [], 0
        # A block's wall time over its frames, over the cores that ran side by side.
        frames = order[lanes][real[lanes]]
        ms[frames] = 1e3 * seconds / max(1, len(frames)) / threads
    for w in workers:
        w.join()
    if held:
        _native.resolve_unsure(pm, np.concatenate(held), order, host, taus, tests, not_run, kept)
    counts = _native.native_mesh(pm).counts(not_run[real], kept[real])
    for col, v in zip(cols, counts):
        col[order[real]] = v


def refine_path(pm: ProgressiveMesh, cameras: Camera, tau=1.0, *, budget=None, tests: Tests = ALL_TESTS,
                coherent: bool = True) -> Iterator[Refinement]:
    """The refinements of an ordered camera path, one per frame, streamed.

    Each is exactly ``pmjax.refine(pm, camera_t, tau_t, tests)`` (executed
    set, faces, ``vref``, counts). With ``coherent`` (default) consecutive
    frames are traversed together, 16 per word in the C loops (32 as JAX
    kernels; module doc); memory stays that of one word (or chunk of words),
    whatever the path's length.

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
    host, taus, budgets, shape = check_path(cameras, tau, budget)
    if budgets is not None:
        taus = _budget_taus(pm, host, budgets, tests)
    if not coherent or pm.n_pcols == 0:
        for i in range(len(taus)):
            yield refine(pm, jax.tree.map(lambda a: a[i], host), taus[i], tests)
        return
    if _native.available():
        for frames, counts, lists in _native_words(pm, host, taus, tests, shape[-1], True):
            for lane, frame in enumerate(frames):
                if frame >= 0:
                    visited, ran, at = lists[lane]
                    yield Refinement(pm=pm, visited=visited, visited_executed=ran, dense=None,
                                     n_faces=np.int32(counts[0][lane]), n_vertices=np.int32(counts[1][lane]),
                                     n_executed=np.int32(counts[2][lane]), front_positions=at)
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
            the wall time of the frame's chunk over its frames, after the
            kernels of every chunk size were compiled on the path's first
            frames; else each frame's own ``refine`` (compiled beforehand).
        progress: a progress bar over the chunks (or frames).

    Returns:
        dict of NumPy arrays shaped like the leading axes: ``faces``,
        ``vertices``, ``executed_count`` (int32), ``tau`` (float32, the
        tolerance each frame was refined at) and, with ``timing``,
        ``milliseconds`` (float64).
    """
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
    if not coherent or pm.n_pcols == 0:
        frame = lambda i: jax.tree.map(lambda a: a[i], host)
        if timing:  # compile outside the timings
            jax.block_until_ready(refine(pm, frame(0), taus[0], tests, method=method))
        for i in bar(range(n), n, "frame"):
            t = time.perf_counter()
            r = jax.block_until_ready(refine(pm, frame(i), taus[i], tests, method=method))
            ms[i] = 1e3 * (time.perf_counter() - t)
            for col, v in zip(cols, (r.n_faces, r.n_vertices, r.n_executed)):
                col[i] = int(v)
    elif _native.available():
        _native_path_counts(pm, host, taus, tests, shape[-1], cols, ms, bar)
    else:
        padded = len(_word_padded(n, shape[-1]))
        if timing:  # one call per chunk size on the first frames: compiled, and buffers fitted
            for size in sorted({size for _, size in _chunk_spans(padded)}):
                idx = np.minimum(np.arange(size), n - 1)
                _front_counts(pm, jax.tree.map(lambda a: a[idx], host), taus[idx], tests, False)
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


def path_refinement_pairs(pm: ProgressiveMesh, cameras: Camera, tau, *, tests: Tests = ALL_TESTS,
                          coherent: bool = True) -> Iterator[tuple[Refinement, Refinement]]:
    """Per frame, ``(refinement at tau, refinement at tau 0)``: the executed
    set and the pcols a view hides (culled or facing away: what runs even at
    tau 0, :func:`pmjax.hidden_pcols`), as a geomorphed path needs them."""
    return zip(refine_path(pm, cameras, tau, tests=tests, coherent=coherent),
               refine_path(pm, cameras, 0.0, tests=tests, coherent=coherent))

