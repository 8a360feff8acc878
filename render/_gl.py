"""Importing pyrender safely: headless platform choice and the numpy 2 shim."""

from __future__ import annotations

import os
import sys

import numpy as np


class RenderError(RuntimeError):
    """pyrender/OpenGL is unavailable or failed (names what to install)."""


# pyrender 0.1.45 pins PyOpenGL 3.1.0, which cannot render headless through
# OSMesa; pmjax depends on 3.1.10 and pyrender is installed without its pins.
PYRENDER_INSTALL = "pip install --no-deps --no-warn-conflicts pyrender==0.1.45"
BROKEN_PYOPENGL = "3.1.0"


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
        import OpenGL
    except ImportError as exc:
        raise RenderError(f"PyOpenGL is not installed ({exc}): pip install PyOpenGL==3.1.10") from exc
    if OpenGL.__version__ == BROKEN_PYOPENGL:
        raise RenderError(f"PyOpenGL {BROKEN_PYOPENGL} is installed (pyrender's own pin, brought back by installing "
                          "pyrender with its dependencies); it cannot render headless: "
                          "pip install PyOpenGL==3.1.10")
    try:
        import pyrender
    except ModuleNotFoundError as exc:
        if exc.name != "pyrender":
            raise RenderError(f"cannot import pyrender ({exc})") from exc
        raise RenderError(f"pyrender is not installed: {PYRENDER_INSTALL} (without its dependencies, whose "
                          "PyOpenGL pin breaks headless rendering; pmjax installs the others)") from exc
    except Exception as exc:  # OpenGL failing to find its library
        raise RenderError(
            f"cannot import pyrender ({exc}); headless rendering needs Debian packages "
            "libegl1 libegl-mesa0 libgl1-mesa-dri (PYOPENGL_PLATFORM=egl) or libosmesa6 "
            "(PYOPENGL_PLATFORM=osmesa), and PyOpenGL 3.1.10"
        ) from exc
    return pyrender
