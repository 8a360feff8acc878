"""SIGTERM as an exit that a long loop does not lose.

While a command runs, SIGTERM raises ``SystemExit(128 + signal)`` where the
main thread is, so that writers remove their temporary files on the way
out. Python swallows an exception raised inside a finalizer or a garbage
collector's callback ("Exception ignored in ..."), and a signal handled
there would be lost; so the signal is also recorded, and loops that write
many outputs (frames) call :func:`check_terminated` once per item, which
raises the exit again.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading

_received: int | None = None


def check_terminated() -> None:
    """Raise ``SystemExit(128 + signal)`` if SIGTERM came while a command
    runs (see :func:`sigterm_exits`); nothing otherwise."""
    if _received is not None:
        raise SystemExit(128 + _received)


def _exit(signum, frame):
    global _received
    _received = signum
    sys.exit(128 + signum)


@contextlib.contextmanager
def sigterm_exits():
    """While a command runs, SIGTERM ends it as an exception would (status
    143), recorded for :func:`check_terminated`; the previous handler is
    restored after. Outside the main thread it does nothing."""
    global _received
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _exit)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        _received = None
