"""Row-independent builder steps split over the CPU cores.

NumPy runs one core per call but releases the GIL inside its loops, so two
threads working on two halves of the rows run in parallel. Every split here is of work whose
rows are independent, so results are bit-identical to one call.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

# Below this many rows a split costs more than it saves.
MIN_ROWS = 20_000
_POOL: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pmjax-build")
    return _POOL


def _two_cores() -> bool:
    return (os.cpu_count() or 1) >= 2


def split_rows(fn, *arrays):
    """``fn(*arrays)`` with every array cut in two row halves, one half on a
    worker thread; outputs (an array or a tuple of arrays) are concatenated."""
    n = len(arrays[0])
    if n < MIN_ROWS or not _two_cores():
        return fn(*arrays)
    h = n // 2
    first = _pool().submit(fn, *(x[:h] for x in arrays))
    second = fn(*(x[h:] for x in arrays))
    first = first.result()
    if isinstance(first, tuple):
        return tuple(np.concatenate([u, v]) for u, v in zip(first, second))
    return np.concatenate([first, second])


def split_pairs(check, ids: np.ndarray, pair: np.ndarray, face: np.ndarray) -> np.ndarray:
    """``check(ids, pair, face)`` (one value per id, from that id's incidence
    rows ``pair == i``) computed as two halves of the ids in parallel."""
    if len(pair) < MIN_ROWS or not _two_cores():
        return check(ids, pair, face)
    h = len(ids) // 2
    low = pair < h
    first = _pool().submit(check, ids[:h], pair[low], face[low])
    second = check(ids[h:], pair[~low] - h, face[~low])
    return np.concatenate([first.result(), second])


def split_items(fn, items: list) -> None:
    """``fn(items)`` as two halves of the list, one on the worker thread (for
    work that writes its own disjoint outputs and returns nothing)."""
    if len(items) < 2 or not _two_cores():
        if items:
            fn(items)
        return
    h = len(items) // 2
    first = _pool().submit(fn, items[:h])
    fn(items[h:])
    first.result()


def split_range(fn, n: int) -> None:
    """``fn(0, n)`` as ``fn(0, h)`` on the worker thread and ``fn(h, n)``
    here (for row ranges written in place, disjoint between the halves)."""
    if n < MIN_ROWS or not _two_cores():
        fn(0, n)
        return
    h = n // 2
    first = _pool().submit(fn, 0, h)
    fn(h, n)
    first.result()
