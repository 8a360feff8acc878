"""Row-wise helpers for ``(N, 3)`` arrays (triangles, vectors).

NumPy reduces over a length-3 axis through its generic reduction loop, whose
per-row overhead outweighs three elementwise operations on the columns; the
builder does these per face and per candidate every batch, so they are
spelled out.
"""

from __future__ import annotations

import numpy as np


def any3(m: np.ndarray) -> np.ndarray:
    """``m.any(axis=1)`` for a ``bool[N, 3]``."""
    return m[:, 0] | m[:, 1] | m[:, 2]


def min3(x: np.ndarray) -> np.ndarray:
    """``x.min(axis=1)`` for an ``[N, 3]`` array."""
    return np.minimum(np.minimum(x[:, 0], x[:, 1]), x[:, 2])


def max3(x: np.ndarray) -> np.ndarray:
    """``x.max(axis=1)`` for an ``[N, 3]`` array."""
    return np.maximum(np.maximum(x[:, 0], x[:, 1]), x[:, 2])


def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``[N, 3]`` arrays."""
    out = np.empty(np.broadcast_shapes(u.shape, v.shape), np.result_type(u, v))
    out[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    out[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    out[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    return out


def dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise dot product of ``[N, 3]`` arrays."""
    return u[:, 0] * v[:, 0] + u[:, 1] * v[:, 1] + u[:, 2] * v[:, 2]


def norm(u: np.ndarray) -> np.ndarray:
    """Row-wise Euclidean length of an ``[N, 3]`` array (``np.linalg.norm(u,
    axis=1)``, the same sums in the same order)."""
    return np.sqrt(dot(u, u))


def unit(u: np.ndarray) -> np.ndarray:
    """Rows of ``u`` scaled to unit length; zero rows stay zero."""
    length = norm(u)
    return u / np.where(length > 0, length, 1.0)[:, None]
