"""Content keys of arrays: what the engines' derived tables are cached by.

A table an engine derives from a :class:`pmjax.ProgressiveMesh` (the front
engine's breadth-first layout and bounds, the front mesh's records) is kept
under a digest of the arrays it was derived from, so an updated mesh (an
``eqx.tree_at`` of its attributes, new positions) finds no stale table: it
has other contents, hence another key. A JAX array is immutable, so its
digest is computed once per array object and remembered by identity, beside a
weak reference to the array: the memo keeps no array alive (a study that
updates a mesh's arrays thousands of times holds no old copies), and an
identity reused by a new array after the old one is gone is seen as new. A
NumPy array can change in place and is digested at every call.
"""

from __future__ import annotations

import collections
import hashlib
import threading
import weakref

import jax
import numpy as np

# Array objects whose digests are remembered (a 16-byte digest and a weak
# reference each).
MEMO_SIZE = 256

_memo: collections.OrderedDict = collections.OrderedDict()
_lock = threading.Lock()


def is_traced(x) -> bool:
    """Whether ``x`` is a tracer (an abstract value inside ``jit``, ``vmap``, ``grad``)."""
    return isinstance(x, jax.core.Tracer)


def _hash(x) -> bytes:
    a = np.ascontiguousarray(np.asarray(x))
    h = hashlib.blake2b(digest_size=16)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(memoryview(a).cast("B") if a.size else b"")
    return h.digest()


def digest(x) -> bytes:
    """16-byte digest of an array's dtype, shape and contents (``ValueError``
    for a tracer: an abstract array has no contents)."""
    if is_traced(x):
        raise ValueError("an array being traced has no contents to key a table by")
    if not isinstance(x, jax.Array):
        return _hash(x)
    with _lock:
        hit = _memo.get(id(x))
        if hit is not None and hit[0]() is x:
            _memo.move_to_end(id(x))
            return hit[1]
    d = _hash(x)
    with _lock:
        _memo[id(x)] = (weakref.ref(x), d)
        while len(_memo) > MEMO_SIZE:
            _memo.popitem(last=False)
    return d


def key(*arrays, static=()) -> bytes:
    """One digest of several arrays (in order) and hashable static values."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        h.update(digest(a))
    h.update(repr(static).encode())
    return h.digest()
