"""Headless rendering of refinements to images, frames and videos."""

from __future__ import annotations

import os
from typing import Optional

import numpy as np

from pmjax import ALL_TESTS, Camera, ProgressiveMesh, Refinement, Tests, camera_count, index_camera, refine
from pmjax._atomic import atomic_path


from ._gl import RenderError, pyrender_module
from ._scene import batch_levels, build_scene, face_levels, frustum_past_model


_CONTEXTS: dict = {}


class Renderer:
    """An offscreen OpenGL context of a fixed size (EGL or OSMesa).

    Contexts are cached per size for the life of the process: pyrender's EGL
    teardown terminates the shared display, which breaks every other live
    context, so they are never deleted early. Usable as a context manager.
    """

    def __init__(self, width: int, height: int):
        pyrender = pyrender_module(offscreen=True)
        key = (int(width), int(height))
        if key not in _CONTEXTS:
            try:
                _CONTEXTS[key] = pyrender.OffscreenRenderer(*key)
            except Exception as exc:
                raise RenderError(
                    f"cannot create a {width}x{height} offscreen context with "
                    f"PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')!r}: {exc}"
                ) from exc
        self._gl = _CONTEXTS[key]
        self.width, self.height = key

    def render_scene(self, scene):
        """``(rgb uint8[H, W, 3], depth float32[H, W])``; depth 0 where empty."""
        color, depth = self._gl.render(scene)
        return np.ascontiguousarray(color[..., :3]), depth

    def render_mesh(self, vertices, faces, camera: Camera, *, levels=None, n_batches=1, wireframe=False,
                    lines=None):
        """Render plain arrays seen from ``camera`` (whose size must match).

        Args:
            levels, n_batches: optional per-face batch levels to colour by.
            wireframe: overlay the edges.
            lines: optional ``[2n, 3]`` line segments (drawn red).
        """
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError(f"camera is {camera.width}x{camera.height}, renderer {self.width}x{self.height}")
        scene, _ = build_scene(vertices, faces, camera, levels=levels, n_batches=n_batches, wireframe=wireframe,
                               extra_lines=lines)
        return self.render_scene(scene)

    def close(self):
        """Release this handle (the cached context stays for reuse)."""
        self._gl = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def refined_arrays(pm: ProgressiveMesh, refinement: Refinement, *, color_levels=False):
    """``(vertices, faces, face levels or None)`` of a refinement, ready to draw."""
    v, f, ids = refinement.mesh(pm)
    levels = face_levels(f, batch_levels(pm, ids)) if color_levels else None
    return v, f, levels


def original_arrays(pm: ProgressiveMesh):
    """``(vertices, faces)`` of the original (full-resolution) mesh."""
    V0 = pm.n_original_vertices
    return np.asarray(pm.vertices)[:V0], np.asarray(pm.faces)


def render_refinement(renderer: Renderer, pm: ProgressiveMesh, refinement: Refinement, camera: Camera, *,
                      wireframe=False, color_levels=False, phantom: Optional[Camera] = None):
    """Render ``refinement`` seen from ``camera``.

    Args:
        phantom: the camera the refinement was made for, when it differs from
            the viewing ``camera`` (the paper's phantom camera); its frustum is
            drawn as red lines.

    Returns:
        ``(rgb uint8[H, W, 3], depth float32[H, W])``.
    """
    v, f, levels = refined_arrays(pm, refinement, color_levels=color_levels)
    lines = frustum_past_model(pm, phantom) if phantom is not None else None
    return renderer.render_mesh(v, f, camera, levels=levels, n_batches=len(pm.batch_offsets) - 1,
                                wireframe=wireframe, lines=lines)


def write_frames(frames, path: str, fps: int = 30) -> None:
    """Write RGB frames as a video (``.mp4``: imageio-ffmpeg; ``.gif``) or, for a
    directory path or ``.png`` pattern, as numbered PNGs; atomically per file."""
    import imageio.v2 as imageio

    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext in (".mp4", ".gif"):
        with atomic_path(path, ext) as tmp:
            kw = dict(fps=fps, macro_block_size=1) if ext == ".mp4" else dict(duration=1.0 / fps, loop=0)
            with imageio.get_writer(tmp, format="FFMPEG" if ext == ".mp4" else "GIF", mode="I", **kw) as w:
                for frame in frames:
                    w.append_data(frame)
        return
    if ext not in ("", ".png"):
        raise ValueError(f"{path}: output must be .mp4, .gif or a directory for PNG frames")
    folder = path if ext == "" else os.path.dirname(path) or "."
    os.makedirs(folder, exist_ok=True)
    for i, frame in enumerate(frames):
        write_png(os.path.join(folder, f"frame_{i:05d}.png"), frame)


def write_png(path: str, image) -> None:
    """Write one PNG atomically."""
    import imageio.v2 as imageio

    with atomic_path(path, ".png") as tmp:
        imageio.imwrite(tmp, np.asarray(image), format="PNG")


def render_path(pm: ProgressiveMesh, cameras: Camera, tau: float, out: str, *, tests: Tests = ALL_TESTS,
                wireframe=False, color_levels=False, phantom: Optional[Camera] = None, fps: int = 30,
                progress: bool = True) -> dict:
    """Refine and render every camera of a path; write ``out`` (.mp4/.gif/PNG folder).

    Args:
        phantom: if given, every frame is refined for its path camera but seen
            from this fixed overview camera, with the path camera's frustum drawn.

    Returns:
        dict with ``faces`` (int per frame) and ``frames`` (count).
    """
    K = camera_count(cameras)
    first = index_camera(cameras, 0)
    view = phantom if phantom is not None else first
    faces = []

    def frames():
        with Renderer(view.width, view.height) as r:
            it = range(K)
            if progress:
                from tqdm import tqdm

                it = tqdm(it, unit="frame", desc="render")
            for i in it:
                cam = index_camera(cameras, i)
                ref = refine(pm, cam, tau, tests)
                faces.append(int(ref.n_faces))
                if phantom is None:
                    yield render_refinement(r, pm, ref, cam, wireframe=wireframe, color_levels=color_levels)[0]
                else:
                    yield render_refinement(r, pm, ref, phantom, wireframe=wireframe, color_levels=color_levels,
                                            phantom=cam)[0]

    write_frames(frames(), out, fps=fps)
    return dict(faces=np.asarray(faces), frames=len(faces))
