"""The optional compiled extensions that are called through ctypes."""

from __future__ import annotations

import ctypes
import importlib.util
import os


def open_library(module: str):
    """The compiled extension ``module`` (a dotted name) as a ctypes library,
    or ``None`` where it is not built or ``PMJAX_NATIVE=0`` is set (the
    NumPy steps then run: the same results, bit for bit)."""
    if os.environ.get("PMJAX_NATIVE", "1") == "0":
        return None
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin:
        return None
    return ctypes.CDLL(spec.origin)
