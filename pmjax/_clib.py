"""The optional compiled extensions that are called through ctypes."""

from __future__ import annotations

import ctypes
import hashlib
import importlib.util
import os
import warnings


def open_library(module: str):
    """The compiled extension ``module`` (a dotted name) as a ctypes library,
    or ``None`` where it is not built, where ``PMJAX_NATIVE=0`` is set, or
    where it was built from another text than the C source beside it (a
    stale build: its functions may take other arguments; a warning says how
    to rebuild). The NumPy steps then run: the same results, bit for bit."""
    if os.environ.get("PMJAX_NATIVE", "1") == "0":
        return None
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin:
        return None
    lib = ctypes.CDLL(spec.origin)
    source = os.path.join(os.path.dirname(spec.origin), module.rsplit(".", 1)[-1] + ".c")
    if os.path.exists(source) and not built_from(lib, source):
        warnings.warn(f"{spec.origin} was built from another version of {source}: rebuild it (pip install again, "
                      "or python setup.py build_ext --inplace); its NumPy steps run meanwhile (the same results, "
                      "slower)", RuntimeWarning, stacklevel=2)
        return None
    return lib


def built_from(lib, source: str) -> bool:
    """Whether ``lib`` was built from the text of ``source`` (the SHA-256 the
    build put in it, ``pmjax_source_digest``)."""
    try:
        get = lib.pmjax_source_digest
    except AttributeError:  # built before the digest was put in
        return False
    get.restype, get.argtypes = ctypes.c_char_p, []
    with open(source, "rb") as fh:
        return get().decode() == hashlib.sha256(fh.read()).hexdigest()
