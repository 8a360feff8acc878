"""Model units: the refinement tests run on lengths divided by a power of two.

The screen-space test multiplies four lengths (``delta² · d²`` against
``kappa² · d⁴``), which in float32 overflows from about 1e9 world units up and
underflows from about 1e-9 down. So every test sees the pcol attributes and the
camera in *model units*: world lengths times ``2^-e``, with ``2^e`` the power of
two just above the largest bounding-sphere radius of the hierarchy (the size
of the model, or of its largest part). Multiplying by a power of two is exact
in floating point, so a model whose lengths already fit gets the same decisions,
bit for bit, as in world units, a model scaled by a power of two gets the same
decisions as the original, and any other uniform scale or translation changes
only float32 rounding. Angles, pixel sizes and tolerances are unitless and
stay as they are.

An eye farther than ``2^EYE_LIMIT`` model units from the origin is moved in
along its line to that distance, with its near and far planes scaled alike:
float32 cannot resolve the model from there (its offset from the eye rounds
to multiples of the model's size), and the model is far below a pixel for any
field of view above 1e-6 degrees; without the limit the squared distances
overflow and the coarsest answer turns into the finest.

Only the tests see model units: vertices, meshes and every result a user reads
stay in world units.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

# Eyes are kept within 2^EYE_LIMIT model units of the origin: d⁴ ≤ 2^124 stays
# finite in float32 (whose largest value is just below 2^128).
EYE_LIMIT = 30
# Exponents are clipped to float32's normal range, so 2^-e is a normal number.
_LOWEST, _HIGHEST = -126, 126

# The attributes that are lengths; the others (axes, angles) are unitless.
LENGTHS = ("center", "radius", "delta", "mu")


def _exponent(largest, xp):
    """``e`` with ``largest < 2^e`` (0 for 0), clipped to float32's normal range."""
    _, e = xp.frexp(largest)
    return xp.clip(e, _LOWEST, _HIGHEST).astype(xp.int32)


def unit_exponent(radius) -> int:
    """The model unit ``2^e`` of a hierarchy from its radii (host, ``float32 [P]``)."""
    radius = np.asarray(radius, np.float32)
    return int(_exponent(radius.max(initial=np.float32(0)), np))


def traced_unit_exponent(radius):
    """:func:`unit_exponent` as a JAX scalar (``int32``), for traced attributes."""
    largest = jnp.max(jax.lax.stop_gradient(radius), initial=0.0).astype(jnp.float32)
    return _exponent(largest, jnp)


def power_of_two(exponent, xp=jnp):
    """``2^exponent`` as float32, exact (``exponent`` within float32's normal range)."""
    return xp.ldexp(xp.float32(1.0), xp.asarray(exponent, xp.int32)).astype(xp.float32)


def host_lengths_in_model_units(arrays: dict, exponent: int) -> dict:
    """``arrays`` (attribute name -> host array) with the lengths (:data:`LENGTHS`)
    times ``2^-exponent``."""
    scale = np.float32(power_of_two(-exponent, np))
    return {k: (np.asarray(v) * scale).astype(np.asarray(v).dtype) if k in LENGTHS else v for k, v in arrays.items()}


def attributes_in_model_units(attrs, exponent=None):
    """``(attrs, exponent)``: :class:`pmjax.PcolAttributes` with its lengths in
    model units (traceable; ``exponent`` from the radii when not given)."""
    if exponent is None:
        exponent = traced_unit_exponent(attrs.radius)
    scale = power_of_two(-exponent).astype(attrs.radius.dtype)
    scaled = {k: getattr(attrs, k) * scale for k in LENGTHS}
    return type(attrs)(**{f: scaled.get(f, getattr(attrs, f)) for f in attrs.__dataclass_fields__}), exponent


def camera_lengths_in_model_units(eye, near, far, ortho_height, exponent, xp=jnp):
    """A camera's lengths in model units: ``(eye, near, far, ortho_height)``
    times ``2^-exponent``, the eye (with near and far) moved in to
    ``2^EYE_LIMIT`` model units from the origin where it is farther. Shapes
    ``[..., 3]`` and ``[...]``; ``xp`` is ``jax.numpy`` or ``numpy``."""
    eye = xp.asarray(eye)
    exponent = xp.asarray(exponent, xp.int32)
    # The eye's binary exponent, so the pull-in factor is found without
    # scaling (which could overflow) first.
    _, e_eye = xp.frexp(xp.max(xp.abs(eye), axis=-1))
    extra = xp.maximum(e_eye.astype(xp.int32) - exponent - EYE_LIMIT, 0)
    length = power_of_two(-exponent - extra, xp)
    size = power_of_two(-exponent, xp)
    return eye * length[..., None], xp.asarray(near) * length, xp.asarray(far) * length, xp.asarray(ortho_height) * size


def camera_in_model_units(camera, exponent):
    """A :class:`pmjax.Camera` with its lengths in model units (see
    :func:`camera_lengths_in_model_units`); host cameras stay host arrays.
    Not a camera a user would make (its lengths may be out of any sensible
    range), so it is not checked as one."""
    xp = np if isinstance(camera.fov_y, np.ndarray) else jnp
    lengths = camera_lengths_in_model_units(camera.eye, camera.near, camera.far, camera.ortho_height, exponent, xp)
    return eqx.tree_at(lambda c: (c.eye, c.near, c.far, c.ortho_height), camera, lengths)


def in_model_units(attrs, camera):
    """``(attrs, camera)`` both in model units, the unit from ``attrs``' radii (traceable)."""
    attrs, exponent = attributes_in_model_units(attrs)
    return attrs, camera_in_model_units(camera, exponent)
