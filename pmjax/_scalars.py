"""The checks of one camera's type and of scalar arguments (tolerances,
temperatures) that every public call shares.

Each says which call and which argument is wrong and what was expected. They
import no mesh module, so the view's own constants (:func:`pmjax.kappa`) use
them too; :mod:`pmjax._arguments` adds the checks of meshes and batches.
"""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np

from ._camera import Camera


def check_camera_type(camera, call: str, what: str = "camera") -> None:
    """``camera`` is a :class:`Camera` (``TypeError`` naming ``what`` otherwise)."""
    if not isinstance(camera, Camera):
        raise TypeError(f"{call}: {what} must be a pmjax.Camera (pmjax.look_at, pmjax.standard_orbit, "
                        f"pmjax.load_cameras, ...), got {type(camera).__name__}")


def host_scalar(value, name: str, call: str):
    """A tolerance-like argument: a JAX tracer or array is returned as it is;
    anything else must be one real number (``TypeError`` or ``ValueError``
    naming the argument otherwise), returned as float32."""
    if isinstance(value, jax.Array):
        return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating,
                                                                     np.ndarray)):
        raise TypeError(f"{call}: {name} must be a number, got {type(value).__name__} {_short(value)}")
    value = np.asarray(value)
    if value.shape != () or value.dtype.kind not in "iuf":
        raise ValueError(f"{call}: {name} must be one number, got {_short(value)} (shape {list(value.shape)})")
    return np.float32(value)


def host_number(value, name: str, call: str, ok, rule: str):
    """A scalar argument, checked where it is known: a tracer (shape checked,
    its value left to the compiled call's ``eqx.error_if``) and a concrete JAX
    array (value checked here) are returned as they are; anything else as
    :func:`host_scalar`'s float32. ``ok(value) -> bool`` is the rule,
    ``rule`` its words in the ``ValueError``."""
    if isinstance(value, jax.core.Tracer):
        if np.shape(value) != ():
            raise ValueError(f"{call}: {name} must be one number, got an array of shape {list(np.shape(value))}")
        return value
    host = host_scalar(np.asarray(value) if isinstance(value, jax.Array) else value, name, call)
    if not ok(host):
        raise ValueError(f"{call}: {name} must be {rule}, got {host:g}")
    return value if isinstance(value, jax.Array) else host


def host_tau(tau, call: str):
    """:func:`host_number` for a tolerance: >= 0 pixels, ``inf`` allowed
    (every collapsible pcol), NaN refused."""
    return host_number(tau, "tau", call, lambda t: t >= 0, ">= 0 pixels (not NaN)")


def checked_tau(tau, call: str):
    """A tolerance for a call that passes it on as given: :func:`host_tau` on
    the host; traced, refused where it is used if NaN or negative
    (``eqx.error_if``). Returns the caller's value (a traced one wrapped)."""
    host_tau(tau, call)
    if isinstance(tau, jax.core.Tracer):
        return eqx.error_if(tau, ~(tau >= 0), f"{call}: tau must be >= 0 (and not NaN)")
    return tau


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
