"""Importing pyrender safely: headless platform choice and the numpy 2 shim."""

from __future__ import annotations

import os
import sys

import numpy as np


class RenderError(RuntimeError):
    """pyrender/OpenGL is unavailable or failed (names what to install)."""


def pyrender_module(offscreen: bool = True):
    """Import and return ``pyrender``.

    For offscreen rendering without a display, ``PYOPENGL_PLATFORM`` is set to
    ``egl`` unless already set (``osmesa`` works too: Debian ``libosmesa6``).
    It must be chosen before OpenGL is first imported. The interactive viewer
    needs a display and no ``PYOPENGL_PLATFORM``.
    """
    if offscreen and "OpenGL" not in sys.modules and not os.environ.get("PYOPENGL_PLATFORM"):
        os.environ["PYOPENGL_PLATFORM"] = "egl"
    # pyrender 0.1.45 uses np.infty, removed in numpy 2.
    if not hasattr(np, "infty"):
        np.infty = np.inf
    try:
        import pyrender
    except Exception as exc:  # ImportError, or OpenGL failing to find its library
        raise RenderError(
            f"cannot import pyrender ({exc}); headless rendering needs Debian packages "
            "libegl1 libegl-mesa0 libgl1-mesa-dri (PYOPENGL_PLATFORM=egl) or libosmesa6 "
            "(PYOPENGL_PLATFORM=osmesa), and PyOpenGL 3.1.10"
        ) from exc
    return pyrender
