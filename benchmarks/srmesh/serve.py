"""SrMesh's driver kept running beside a benchmark, one adapt pass along a path per request.

The driver (``srmesh_adapt ... --serve``, see ``srmesh_adapt.cpp``) reads the
SR mesh and the cameras once, then answers each ``pass`` line with one pass
along the path from the coarse mesh: per frame, the milliseconds of
``set_view_params`` + ``adapt_refinement`` and the active faces after it. The
benchmark alternates passes with its own variants; the process inherits the
benchmark's CPU affinity (``taskset -c 0``).
"""

from __future__ import annotations

import os
import subprocess
import tempfile

import numpy as np

from .cameras import write_cameras


class SrMeshServer:
    """A running driver for one SR mesh, cameras and tolerance.

    Args:
        driver: path of ``srmesh_adapt``.
        mesh: the SR progressive mesh (``.pm``) or ``.srm``.
        cams: ``pmjax.Camera`` batch ``[T]``, perspective.
        tau: screen-space tolerance, pixels of the image height.

    Use as a context manager; :meth:`one_pass` returns ``(ms [T], faces [T], cpu_ms)``.
    """

    def __init__(self, driver: str, mesh: str, cams, tau: float):
        for path, what in ((driver, "driver"), (mesh, "SR mesh")):
            if not os.path.exists(path):
                raise FileNotFoundError(f"SrMesh {what} {path} not found (benchmarks/srmesh/build.py makes it)")
        fd, self._cam_path = tempfile.mkstemp(suffix=".cameras.txt")
        os.close(fd)
        self.frames = write_cameras(cams, self._cam_path)
        self._proc = subprocess.Popen([driver, mesh, self._cam_path, repr(float(tau)), "--serve"],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        # MPL prints its own notes as '#' lines; the driver's first answer is "ready T".
        try:
            line = self._answer()
            if line.split() != ["ready", str(self.frames)]:
                raise RuntimeError(f"SrMesh driver did not start: {line!r}")
        except BaseException:
            self.close()
            raise

    def _answer(self) -> str:
        while True:
            line = self._proc.stdout.readline()
            if not line:
                raise RuntimeError(f"SrMesh driver ended (exit {self._proc.poll()})")
            if not line.startswith("#"):
                return line.strip()

    def one_pass(self):
        """One pass along the path: per-frame wall milliseconds ``[T]``, active
        faces ``[T]`` and the pass's CPU milliseconds (the thread's, over its frames)."""
        self._proc.stdin.write("pass\n")
        self._proc.stdin.flush()
        out = {}
        for _ in range(3):
            key, *values = self._answer().split()
            out[key] = values
        ms, faces = np.asarray(out["ms"], float), np.asarray(out["faces"], int)
        if len(ms) != self.frames or len(faces) != self.frames:
            raise RuntimeError(f"SrMesh driver answered {len(ms)} frames, expected {self.frames}")
        return ms, faces, float(out["cpu_ms"][0])

    def close(self):
        """Ends the driver (killed if it does not quit) and removes the camera file."""
        try:
            if self._proc.poll() is None:
                try:
                    self._proc.stdin.write("quit\n")
                    self._proc.stdin.close()
                    self._proc.wait(timeout=60)
                except (OSError, subprocess.TimeoutExpired):
                    self._proc.kill()
                    self._proc.wait()
        finally:
            if os.path.exists(self._cam_path):
                os.unlink(self._cam_path)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
