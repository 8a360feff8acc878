"""A switch for comparisons of the engines: the C core off in a block of code."""

from __future__ import annotations

import contextlib
import threading

_state = threading.local()


def core_allowed() -> bool:
    """False inside :func:`without_core` (in this thread)."""
    return getattr(_state, "core", True)


@contextlib.contextmanager
def without_core():
    """Calls in this block run as if the C core were not built (the front
    engine as JAX kernels): for comparisons of the engines."""
    was = core_allowed()
    _state.core = False
    try:
        yield
    finally:
        _state.core = was
