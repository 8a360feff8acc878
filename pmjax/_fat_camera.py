"""The fat camera of a word: one set of view constants that covers every frame.

The frames of a word of a camera path (consecutive cameras) are decided
together by the C word traversal. Where all frames decide a pcol alike, one
vectorized pass over 16 pcols under a "fat" camera replaces one pass over the
16 frames per pcol. The fat camera bounds how far the frames are from a
reference (``_front_native.c`` explains how each test uses it):

- ``eye``, ``rho``: every frame's eye lies within ``rho`` of ``eye``;
- ``start``, ``step``, ``capsule``: every frame's eye lies within ``capsule``
  of the segment ``start + [0, 1] step`` (the chord from the first frame's eye
  to the last's; distances along a path move much less than ``rho``);
- ``pivot``, ``rotation``, ``t``, ``eps``, ``tau``: a point ``c`` in frame
  ``f``'s camera coordinates is ``R_f (c - pivot) + t_f``, with
  ``|R_f - rotation| <= eps`` (spectral norm, bounded by Gershgorin's
  circles) and ``|t_f - t| <= tau``. The pivot is the point the frames' view
  axes pass closest to (an orbit's centre), so that turning the camera moves
  the points near it little.

Every bound is computed in float64 from the frames' float32 constants and
rounded up to float32 with room for the float64 rounding, so it holds for the
exact values. Only the bounds' soundness matters for exactness; the pivot and
reference are free choices that only make the bounds tighter or looser.
"""

from __future__ import annotations

import numpy as np

# Layout of the fat camera (FAT_* in _front_native.c): eye 3, rho, pivot 3,
# rotation rows 9 (right, up, forward), t 3, eps, tau, start 3, step 3,
# 1 / |step|^2, capsule.
FAT_VALUES = 29

# Relative room above a float64 bound before rounding up to float32: covers
# the float64 arithmetic (about 2^-50 relative) many times over.
_ROOM = 2.0 ** -16


def _up(x: np.ndarray) -> np.ndarray:
    """Float32 values at least ``x * (1 + _ROOM)``."""
    return np.nextafter(np.asarray(x * (1 + _ROOM)).astype(np.float32), np.float32(np.inf))


def _to_f32(x: np.ndarray) -> np.ndarray:
    """Rounded to float32, held in float64 (exactly)."""
    return np.asarray(x).astype(np.float32).astype(np.float64)


def _pivots(eyes: np.ndarray, forward: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Per word ``[W, F, 3]``, the point closest to every view axis (least
    squares), or ``fallback`` where the axes are too near parallel to meet
    (a camera moving forward)."""
    n = eyes.shape[1]
    across = np.eye(3) - forward[..., :, None] * forward[..., None, :]  # projections across each axis
    a, b = across.sum(1), np.einsum("wfij,wfj->wi", across, eyes)
    meet = np.linalg.eigvalsh(a)[:, 0] > 1e-3 * n
    point = np.linalg.solve(np.where(meet[:, None, None], a, np.eye(3)), b[..., None])[..., 0]
    meet &= np.all(np.isfinite(point), axis=1)
    return np.where(meet[:, None], point, fallback)


def fat_cameras(views: np.ndarray) -> np.ndarray:
    """The fat cameras of words of frames.

    Args:
        views: ``float32 [W, F, 22]``, the view constants
            (:func:`pmjax._native.host_views`) of ``W`` words of ``F >= 1``
            frames each.

    Returns:
        ``float32 [W, FAT_VALUES]``; a word whose bounds are not finite has
        NaN ones (under which nothing is decided at once).
    """
    v = np.asarray(views, np.float64)
    eyes, rotations = v[..., 0:3], v[..., 3:12].reshape(v.shape[:2] + (3, 3))
    eye = _to_f32(0.5 * (eyes.min(1) + eyes.max(1)))
    rho = _up(np.max(np.linalg.norm(eyes - eye[:, None], axis=2), axis=1))
    reference = rotations[:, v.shape[1] // 2]
    # |D|_2^2 is the largest eigenvalue of D^T D, at most its largest absolute
    # row sum (Gershgorin; exact for a turn about one axis).
    d = rotations - reference[:, None]
    gram = np.einsum("wfki,wfkj->wfij", d, d)
    eps = _up(np.sqrt(np.max(np.abs(gram).sum(3), axis=(1, 2))))
    pivot = _to_f32(_pivots(eyes, rotations[..., 2, :], eye))
    t = np.einsum("wfij,wfj->wfi", rotations, pivot[:, None] - eyes)
    centre = _to_f32(0.5 * (t.min(1) + t.max(1)))
    # The float64 products and sums of t round by at most 2^-50 of |pivot - eye|_1.
    rounding = 2.0 ** -48 * np.max(np.abs(pivot[:, None] - eyes).sum(2), axis=1)
    tau = _up(np.max(np.linalg.norm(t - centre[:, None], axis=2), axis=1) + rounding)
    # The capsule about the chord: each eye's distance from its nearest
    # point of the segment (the float32 segment the C loops use).
    start = eyes[:, 0]
    step = _to_f32(eyes[:, -1] - start)
    length2 = np.einsum("wi,wi->w", step, step)
    along = np.einsum("wfi,wi->wf", eyes - start[:, None], step) / np.where(length2 > 0, length2, 1.0)[:, None]
    foot = start[:, None] + np.clip(along, 0, 1)[..., None] * step[:, None]
    capsule = _up(np.max(np.linalg.norm(eyes - foot, axis=2), axis=1) + 2.0 ** -48 * np.abs(eyes).sum(2).max(1))
    # Any step inverse will do (the C loops allow for the projection's error); 0 for one point.
    step_inv = np.where(length2 > 2.0 ** -100, 1.0 / np.where(length2 > 2.0 ** -100, length2, 1.0), 0.0)
    out = np.concatenate([eye, rho[:, None], pivot, reference.reshape(-1, 9), centre, eps[:, None], tau[:, None],
                          start, step, step_inv[:, None], capsule[:, None]], axis=1).astype(np.float32)
    out[~np.all(np.isfinite(out), axis=1)] = np.nan
    return out
