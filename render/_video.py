"""MP4 encoding: raw RGB frames piped to ffmpeg (the binary imageio-ffmpeg ships).

The encoder is started with ``posix_spawn`` rather than ``fork``: forking a
process that runs JAX's threads can deadlock (JAX warns about it on every
fork). ``subprocess`` spawns that way when the executable is an absolute
path and no file descriptors are closed or passed, so the pipe keeps to those
conditions.
"""

from __future__ import annotations

import subprocess

import numpy as np


class Mp4Writer:
    """Write ``uint8[H, W, 3]`` frames to an H.264 ``.mp4`` (yuv420p).

    Use as a context manager; frames must all have the first frame's size.
    On an error inside the block the encoder is killed (the caller removes
    the half-written file).
    """

    def __init__(self, path: str, fps: int):
        self.path, self.fps = path, fps
        self.process = None
        self.shape = None

    def _start(self, shape) -> None:
        import imageio_ffmpeg

        h, w = shape[:2]
        command = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo",
                   "-pix_fmt", "rgb24", "-s", f"{w}x{h}", "-r", str(self.fps), "-i", "-",
                   "-an", "-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", "18", "-f", "mp4", self.path]
        # close_fds=False (and an absolute executable): subprocess uses posix_spawn, no fork.
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stderr=subprocess.PIPE, close_fds=False)
        self.shape = shape

    def append(self, frame) -> None:
        frame = np.ascontiguousarray(frame, np.uint8)
        if frame.ndim != 3 or frame.shape[2] != 3:
            raise ValueError(f"{self.path}: frames must be RGB [H, W, 3], got {frame.shape}")
        if self.process is None:
            self._start(frame.shape)
        elif frame.shape != self.shape:
            raise ValueError(f"{self.path}: frame of size {frame.shape[:2]} after frames of {self.shape[:2]}")
        try:
            self.process.stdin.write(frame.tobytes())
        except BrokenPipeError:
            raise OSError(f"{self.path}: the video encoder stopped: {self._error()}") from None

    def _error(self) -> str:
        self.process.wait()
        return self.process.stderr.read().decode(errors="replace").strip() or f"exit {self.process.returncode}"

    def __enter__(self) -> "Mp4Writer":
        return self

    def __exit__(self, kind, value, tb) -> None:
        if self.process is None:
            if kind is None:
                raise ValueError(f"{self.path}: no frames to write")
            return
        if kind is not None:
            self.process.kill()
            self.process.wait()
            return
        self.process.stdin.close()
        if self.process.wait() != 0:
            raise OSError(f"{self.path}: the video encoder failed: {self._error()}")
