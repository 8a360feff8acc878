"""Headless rendering of refinements to images, frames and videos."""

from __future__ import annotations

import collections
import os
import threading
from typing import Optional

import numpy as np

from pmjax import ALL_TESTS, Camera, ProgressiveMesh, Refinement, Tests, camera_count, index_camera
from pmjax import (MeshChange, MeshStream, ViewNormals, fitted_normals, geomorph_mesh, geomorph_start, geomorph_step,
                   refine_path)
from pmjax._path import path_refinement_pairs
from pmjax._atomic import atomic_folder, atomic_path, check_output_path
from pmjax._terminate import check_terminated


from ._gl import RenderError, pyrender_module
from ._scene import (BASE_COLOR, batch_levels, build_scene, face_levels, frustum_past_model, lines_mesh, new_scene,
                     place_view)
from ._video import Mp4Writer


_CONTEXTS: dict = {}


def block_average(color, depth, s: int):
    """Each ``s × s`` block of a render as one pixel: the mean colour,
    unrounded, and the nearest covered depth.

    The mean is ``color.reshape(H, s, W, s, 3).mean(axis=(1, 3),
    dtype=float32)`` bit for bit: a block's sum of 8-bit values is a whole
    number that float32 holds exactly in any order of addition, and that
    mean divides it by ``s²`` in float64 (its count is an integer scalar)
    and rounds to float32, as here. Summed block slice by block slice in
    integers, it costs a fraction of the strided reduction.

    Args:
        color: ``uint8[s·H, s·W, 3]``.
        depth: ``float32[s·H, s·W]``, 0 where empty.
        s: block size.

    Returns:
        ``(float32[H, W, 3]`` in [0, 255], ``float32[H, W])``: depth 0 where
        no sample of the block is covered.
    """
    H, W = depth.shape[0] // s, depth.shape[1] // s
    blocks = color.reshape(H, s, W, s, color.shape[-1])
    total = np.zeros((H, W, color.shape[-1]), np.uint32 if s > 16 else np.uint16)
    for i in range(s):
        for j in range(s):
            total += blocks[:, i, :, j]
    mean = (total / float(s * s)).astype(np.float32)
    near = np.where(depth > 0, depth, np.float32(np.inf)).reshape(H, s, W, s)
    nearest = near[:, 0, :, 0].copy()
    for i in range(s):
        for j in range(s):
            if i or j:
                np.minimum(nearest, near[:, i, :, j], out=nearest)
    nearest[np.isinf(nearest)] = 0.0
    return mean, nearest


def _read_depth_elementwise(renderer) -> None:
    """Make ``renderer`` (a ``pyrender.Renderer``) read its colour and depth
    images as pyrender does, bit for bit, with the depth made linear over the
    whole image and the empty pixels set to 0 after, instead of through
    boolean-indexed copies (which cost some 40 ms an image at 1600×1200).
    Reads with other flags (RGBA, depth only, segmentation) and macOS's
    resizing stay pyrender's."""
    import sys

    from OpenGL import GL
    from pyrender.constants import RenderFlags

    pyrender_read = renderer._read_main_framebuffer

    def read(scene, flags):
        if flags & (RenderFlags.RGBA | RenderFlags.DEPTH_ONLY | RenderFlags.SEG) or sys.platform == "darwin":
            return pyrender_read(scene, flags)
        width, height = renderer._main_fb_dims
        # Resolve the multisampled buffers, as pyrender does.
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, renderer._main_fb_ms)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, renderer._main_fb)
        GL.glBlitFramebuffer(0, 0, width, height, 0, 0, width, height, GL.GL_COLOR_BUFFER_BIT, GL.GL_LINEAR)
        GL.glBlitFramebuffer(0, 0, width, height, 0, 0, width, height, GL.GL_DEPTH_BUFFER_BIT, GL.GL_NEAREST)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, renderer._main_fb)
        raw = GL.glReadPixels(0, 0, width, height, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT)
        depth = np.flip(np.frombuffer(raw, dtype=np.float32).reshape(height, width), axis=0)
        # pyrender's formula, element by element: the same float32 operations.
        empty = depth == 1.0
        ndc = 2.0 * depth - 1.0
        near, far = scene.main_camera_node.camera.znear, scene.main_camera_node.camera.zfar
        if far is None:
            with np.errstate(divide="ignore"):  # the empty pixels, set to 0 below
                linear = 2 * near / (1.0 - ndc)
        else:
            linear = (2.0 * near * far) / (far + near - ndc * (far - near))
        depth = np.where(empty, np.float32(0.0), linear)
        raw = GL.glReadPixels(0, 0, width, height, GL.GL_RGB, GL.GL_UNSIGNED_BYTE)
        color = np.flip(np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3), axis=0)
        return color, depth

    renderer._read_main_framebuffer = read


class Renderer:
    """An offscreen OpenGL context of a fixed size (EGL or OSMesa).

    Contexts are cached per size for the life of the process: pyrender's EGL
    teardown terminates the shared display, which breaks every other live
    context, so they are never deleted early. Usable as a context manager.

    Args:
        width, height: output image size, pixels.
        supersample: draw ``s×`` larger and average each ``s × s`` block.
        float_color: return the averaged colour unrounded (float32 in
            [0, 255]) instead of uint8, for measurements (see
            :meth:`render_scene`).
    """

    def __init__(self, width: int, height: int, supersample: int = 1, float_color: bool = False):
        pyrender = pyrender_module(offscreen=True)
        if int(supersample) < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        self.supersample = int(supersample)
        key = (int(width) * self.supersample, int(height) * self.supersample)
        if key not in _CONTEXTS:
            try:
                _CONTEXTS[key] = pyrender.OffscreenRenderer(*key)
            except Exception as exc:
                raise RenderError(
                    f"cannot create a {width}x{height} offscreen context with "
                    f"PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')!r}: {exc}"
                ) from exc
            _read_depth_elementwise(_CONTEXTS[key]._renderer)
        self._gl = _CONTEXTS[key]
        self.width, self.height = int(width), int(height)
        self.float_color = bool(float_color)

    def render_scene(self, scene):
        """``(rgb uint8[H, W, 3], depth float32[H, W])``; depth 0 where empty.

        With ``supersample = s`` the scene is drawn at ``s×`` the size and each
        ``s × s`` block averaged (depth: nearest covered sample), so an edge
        moving by a fraction of a pixel changes the pixel by that fraction.
        With ``float_color`` the average is not rounded: rgb is float32 in
        [0, 255], so measurements see changes smaller than one 8-bit level
        (rounding turns a change of ``x < 1`` level into a 0-or-1 flip whose
        mean square is ``x``, not ``x²``).
        """
        color, depth = self._gl.render(scene)
        color = color[..., :3]
        s = self.supersample
        if s > 1 or self.float_color:
            color, depth = block_average(color, depth, s)
            if not self.float_color:
                color = color.round().astype(np.uint8)
        return np.ascontiguousarray(color), depth

    def render_mesh(self, vertices, faces, camera: Camera, *, levels=None, n_batches=1, wireframe=False,
                    lines=None, normals=None, light=True):
        """Render plain arrays seen from ``camera`` (whose size must match).

        Args:
            levels, n_batches: optional per-face batch levels to colour by.
            wireframe: overlay the edges.
            lines: optional ``[2n, 3]`` line segments (drawn red).
            normals: optional ``[V, 3]`` vertex normals (default: from the faces).
            light: False draws the mesh in its flat ambient colour, whatever
                its normals: the image then shows only where the surface lies.
        """
        if (int(camera.width), int(camera.height)) != (self.width, self.height):
            raise ValueError(f"camera is {int(camera.width)}x{int(camera.height)}, renderer {self.width}x{self.height}")
        scene, _ = build_scene(vertices, faces, camera, levels=levels, n_batches=n_batches, wireframe=wireframe,
                               extra_lines=lines, normals=normals, light=light)
        return self.render_scene(scene)

    def close(self):
        """Release this handle (the cached context stays for reuse)."""
        self._gl = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


_NORMALS: dict = {}


def shading_normals(pm: ProgressiveMesh) -> np.ndarray:
    """The vertex normals refinements of ``pm`` are drawn with: those stored
    in its file (``pm.shading_normals``), else :func:`pmjax.fitted_normals`
    computed once per mesh (a file written before they were stored)."""
    key = id(pm)
    if key not in _NORMALS or _NORMALS[key][0] is not pm:
        _NORMALS.clear()  # one mesh at a time; keeps the mesh alive while cached
        stored = getattr(pm, "shading_normals", None)
        _NORMALS[key] = (pm, fitted_normals(pm) if stored is None else np.asarray(stored, np.float32))
    return _NORMALS[key][1]


# How refinements are shaded: "view", their created vertices' normals fitted
# again on the mesh drawn, seen from the eye (pmjax.ViewNormals); "stored",
# the normals stored in the file (shading_normals).
NORMALS = ("view", "stored")


def check_normals(normals: str) -> str:
    """``normals`` if it is one of :data:`NORMALS`, else ``ValueError``."""
    if normals not in NORMALS:
        raise ValueError(f"normals must be one of {', '.join(map(repr, NORMALS))}, got {normals!r}")
    return normals


# The per-view fits of the meshes drawn last (a few, kept alive with their
# mesh: evaluation draws more than one model at a time, from threads).
_VIEW_NORMALS: "collections.OrderedDict[int, tuple]" = collections.OrderedDict()
_VIEW_NORMALS_KEPT = 4
_VIEW_NORMALS_LOCK = threading.Lock()


def view_normals(pm: ProgressiveMesh) -> ViewNormals:
    """The per-view fit of ``pm``'s refinements (:class:`pmjax.ViewNormals`
    from :func:`shading_normals`), made once per mesh (the last few kept;
    safe from several threads)."""
    key = id(pm)
    with _VIEW_NORMALS_LOCK:
        if key not in _VIEW_NORMALS or _VIEW_NORMALS[key][0] is not pm:
            _VIEW_NORMALS[key] = (pm, ViewNormals(pm, shading_normals(pm)))
            while len(_VIEW_NORMALS) > _VIEW_NORMALS_KEPT:
                _VIEW_NORMALS.popitem(last=False)
        _VIEW_NORMALS.move_to_end(key)
        return _VIEW_NORMALS[key][1]


def refined_arrays(pm: ProgressiveMesh, refinement: Refinement, *, color_levels=False, eye=None):
    """``(vertices, faces, face levels or None, normals)`` of a refinement,
    ready to draw.

    Args:
        eye: ``[3]`` the position it is seen from (world units): its created
            vertices are then shaded with normals fitted to the original
            surface in this very mesh, samples weighted by the area seen from
            there (:func:`view_normals`); ``None``: with the stored normals
            fitted to the original surface each vertex stands for
            (:func:`shading_normals`). Original vertices keep their stored
            normals either way, and the faces are the refinement's.
    """
    v, f, ids = refinement.mesh(pm)
    levels = face_levels(f, batch_levels(pm, ids)) if color_levels else None
    if eye is None:
        return v, f, levels, shading_normals(pm)[ids]
    return v, f, levels, view_normals(pm)(ids, f, eye=np.asarray(eye, np.float64))


def original_arrays(pm: ProgressiveMesh):
    """``(vertices, faces, normals)`` of the original (full-resolution) mesh."""
    V0 = pm.n_original_vertices
    return np.asarray(pm.vertices)[:V0], np.asarray(pm.faces), shading_normals(pm)[:V0]


def render_refinement(renderer: Renderer, pm: ProgressiveMesh, refinement: Refinement, camera: Camera, *,
                      wireframe=False, color_levels=False, phantom: Optional[Camera] = None, normals: str = "view"):
    """Render ``refinement`` seen from ``camera``.

    Args:
        phantom: the camera the refinement was made for, when it differs from
            the viewing ``camera`` (the paper's phantom camera); its frustum is
            drawn as red lines.
        normals: ``"view"``: shaded with normals fitted on the mesh drawn,
            seen from ``camera`` (:func:`refined_arrays`); ``"stored"``: with
            the stored ones.

    Returns:
        ``(rgb uint8[H, W, 3], depth float32[H, W])``.
    """
    eye = np.asarray(camera.eye) if check_normals(normals) == "view" else None
    v, f, levels, normals = refined_arrays(pm, refinement, color_levels=color_levels, eye=eye)
    lines = frustum_past_model(pm, phantom) if phantom is not None else None
    return renderer.render_mesh(v, f, camera, levels=levels, n_batches=len(pm.batch_offsets) - 1,
                                wireframe=wireframe, lines=lines, normals=normals)


class SlotMesh:
    """A :class:`pmjax.MeshStream`'s slots as one pyrender mesh node whose GPU
    buffers each frame's :class:`pmjax.MeshChange` updates in place, in any
    scene and OpenGL context (an offscreen renderer's, a viewer window's).

    The vertex buffer holds one row per vertex slot (position and shading
    normal, as pyrender lays them out), the index buffer one triangle per face
    slot (a free slot: a degenerate triangle, drawn as nothing). A frame
    writes the span of its changed rows (one call per buffer);
    the buffers are made again, with room for a quarter more, when the slots
    outgrow them; pyrender draws the slots in use.
    Drawn like :func:`render_refinement` without levels or wireframe: the
    same faces, vertices and normals.

    :meth:`update` (or :meth:`apply`) changes host arrays only; the drawing
    thread calls :meth:`before_draw` with the scene's context current, then
    draws, then :meth:`after_draw`. A caller drawing in another thread holds
    its lock over :meth:`apply`, :meth:`detach` and the draw.

    Args:
        pm: the mesh refined.
        scene: the ``pyrender.Scene`` the mesh node goes into.
    """

    def __init__(self, pm: ProgressiveMesh, scene):
        self.pm, self.scene = pm, scene
        self.stream = MeshStream(pm)
        self._normals = shading_normals(pm)
        self._pyrender = pyrender_module()
        self.node = self.primitive = None
        self._positions = np.zeros((0, 3), np.float32)
        self._vertex_normals = np.zeros((0, 3), np.float32)
        self._indices = np.zeros((0, 3), np.uint32)
        self._pending = None  # rows changed since the buffers were last written
        self._vaid, self._rows = None, 0  # the primitive's buffers last seen, and their triangles
        self._n_faces = 0  # face slots in use, as of the last change applied
        self.uploads = 0  # frames written into existing buffers

    def update(self, refinement: Refinement) -> MeshChange:
        """Moves the mesh to ``refinement``'s; returns the change."""
        return self.apply(self.stream.update(refinement))

    def apply(self, change: MeshChange) -> MeshChange:
        """Writes :attr:`stream`'s last ``change`` into the host arrays; returns it."""
        faces, vertices = change.face_slots, change.vertex_slots
        if change.n_face_slots > len(self._indices) or change.n_vertex_slots > len(self._positions):
            self._grow(change.n_face_slots, change.n_vertex_slots)
        self._n_faces = int(change.n_face_slots)
        self._indices[faces] = np.maximum(change.faces, 0)  # a free slot: the degenerate triangle (0, 0, 0)
        self._positions[vertices] = change.vertex_positions
        self._vertex_normals[vertices] = np.where(change.vertex_ids[:, None] >= 0,
                                                  self._normals[np.maximum(change.vertex_ids, 0)], 0)
        if self._pending is not None:
            self._pending = (np.concatenate([self._pending[0], faces]), np.concatenate([self._pending[1], vertices]))
        return change

    def shade(self, eye) -> None:
        """Shades the mesh held with normals fitted on it, seen from ``eye``
        (``[3]``, world units; :func:`view_normals`): every live vertex
        slot's normal row is rewritten (the stored normals' rows come back
        with the next :meth:`apply` only where that change writes them)."""
        ids, faces = self.stream.vertex_ids, self.stream.faces
        live = np.flatnonzero(ids >= 0)
        if not len(live):
            return
        # The live slots as one mesh: their ids, and the live face slots'
        # corners as indices into them.
        index = np.full(len(ids), -1, np.int64)
        index[live] = np.arange(len(live))
        corners = index[faces[faces[:, 0] >= 0]]
        self._vertex_normals[live] = view_normals(self.pm)(ids[live], corners, eye=np.asarray(eye, np.float64))
        if self._pending is not None:
            self._pending = (self._pending[0], np.concatenate([self._pending[1], live.astype(self._pending[1].dtype)]))

    def _grow(self, n_faces: int, n_vertices: int):
        """Host arrays and a new primitive with room for a quarter more slots."""
        F, V = max(n_faces + n_faces // 4, 64), max(n_vertices + n_vertices // 4, 64)
        indices, positions, normals = (np.zeros((F, 3), np.uint32), np.zeros((V, 3), np.float32),
                                       np.zeros((V, 3), np.float32))
        indices[:len(self._indices)] = self._indices
        positions[:len(self._positions)] = self._positions
        normals[:len(self._vertex_normals)] = self._vertex_normals
        self._indices, self._positions, self._vertex_normals = indices, positions, normals
        self.detach()

    def detach(self):
        """Takes the mesh node out of the scene (a view drawn otherwise
        meanwhile); the next draw makes it again from the host arrays."""
        if self.node is not None:
            self.scene.remove_node(self.node)
        self.node = self.primitive = None
        self._pending = None

    def _upload(self):
        """The changed rows into the primitive's buffers (pyrender's layout:
        buffer 0 the vertices' position and normal rows, the last the
        indices), in the context current."""
        from OpenGL import GL

        faces, vertices = self._pending
        self._pending = (np.zeros(0, np.int32), np.zeros(0, np.int32))
        if not (len(faces) or len(vertices)):
            return
        rows = np.concatenate([self._positions, self._vertex_normals], axis=1)
        # Written through the copy-write target: binding an element buffer
        # outside its vertex array object would change that object's binding.
        target = GL.GL_COPY_WRITE_BUFFER
        for buffer, data, slots in ((self.primitive._buffers[0], rows, vertices),
                                    (self.primitive._buffers[-1], self._indices, faces)):
            if not len(slots):
                continue
            GL.glBindBuffer(target, buffer)
            # One call over the span of the changed rows: a driver may copy the
            # whole buffer per call (a buffer still being drawn from), so one
            # longer write costs less than many short ones.
            lo, hi = int(slots.min()), int(slots.max()) + 1
            block = np.ascontiguousarray(data[lo:hi])
            GL.glBufferSubData(target, lo * block.strides[0], block.nbytes, block)
            GL.glBindBuffer(target, 0)
        self.uploads += 1

    def before_draw(self, make_current=None):
        """Readies the node for a draw of the scene: the changed rows written
        into its buffers (``make_current``: makes the drawing context current
        first, if it may not be), or a new node made from the host arrays."""
        # pyrender draws as many triangles as the primitive's index array
        # holds: after its first draw, the slots in use, not the buffers'
        # room. Buffers made again from that shorter array (pyrender drew
        # another scene meanwhile) may have fewer rows than the slots now in
        # use: the primitive is then made again.
        n_faces = max(self._n_faces, 1)
        if (self.node is not None and self.primitive._vaid is not None and self.primitive._vaid == self._vaid
                and n_faces > self._rows):
            self.detach()
        if self.node is None:  # a new primitive: its buffers are made from the host arrays when drawn
            material = self._pyrender.MetallicRoughnessMaterial(baseColorFactor=BASE_COLOR, metallicFactor=0.0,
                                                                roughnessFactor=0.9, doubleSided=True)
            self.primitive = self._pyrender.Primitive(positions=self._positions, normals=self._vertex_normals,
                                                      indices=self._indices, material=material,
                                                      mode=self._pyrender.GLTF.TRIANGLES)
            # The primitive reads the host arrays themselves (its setters copy):
            # whenever pyrender makes its buffers again (a renderer that drew
            # another scene meanwhile), they hold the current rows.
            self.primitive._positions, self.primitive._normals = self._positions, self._vertex_normals
            self.node = self.scene.add(self._pyrender.Mesh([self.primitive]), name="mesh")
            self._vaid = None
            self.primitive._indices = self._indices  # its buffers made at full room
            return
        if self._pending is not None and self.primitive._vaid is not None:
            if make_current is not None:
                make_current()
            self._upload()
        self.primitive._indices = self._indices[:n_faces]

    def after_draw(self):
        """Notes the buffers the draw used (made in it, or written before it)."""
        if self.primitive is None:
            return
        if self.primitive._vaid != self._vaid:  # buffers made in this draw: their rows
            self._vaid, self._rows = self.primitive._vaid, len(self.primitive._indices)
        if self._pending is None and self.primitive._vaid is not None:  # its buffers exist: changes go into them
            self._pending = (np.zeros(0, np.int32), np.zeros(0, np.int32))


class StreamScene:
    """A scene whose mesh is a :class:`pmjax.MeshStream`'s slots, drawn by
    an offscreen :class:`Renderer` from GPU buffers that each frame's
    :class:`pmjax.MeshChange` updates in place (:class:`SlotMesh`).

    Args:
        renderer: the :class:`Renderer` drawing it.
        pm: the mesh refined.
    """

    def __init__(self, renderer: "Renderer", pm: ProgressiveMesh):
        self.renderer, self.pm = renderer, pm
        self.scene = new_scene()
        self.mesh = SlotMesh(pm, self.scene)
        self.stream = self.mesh.stream
        self._camera = self._light = self._lines = None

    @property
    def _primitive(self):
        return self.mesh.primitive

    def update(self, refinement: Refinement) -> MeshChange:
        """Moves the mesh to ``refinement``'s; returns the change."""
        return self.mesh.update(refinement)

    def render(self, camera: Camera, *, view: Optional[Camera] = None, lines=None):
        """``(rgb, depth)`` of the mesh held, seen from ``view`` (default
        ``camera``); ``lines``: optional ``[2n, 3]`` segments drawn red."""
        view = camera if view is None else view
        self.mesh.before_draw(self.renderer._gl._platform.make_current)
        if self._lines is not None:
            self.scene.remove_node(self._lines)
        self._camera, self._light = place_view(self.scene, view, (self._camera, self._light))
        self._lines = self.scene.add(lines_mesh(lines), name="frustum") if lines is not None else None
        out = self.renderer.render_scene(self.scene)
        self.mesh.after_draw()
        return out


def check_frames_output(path: str, fps: int = 30) -> str:
    """Check a frames output and rate before any rendering; return the extension.

    Raises:
        ValueError: not ``.mp4``, ``.gif``, ``.png`` or a folder; ``fps`` not a
            whole number in ``[1, 1000]``.
        OSError: the folder it goes into does not exist (see
            :func:`pmjax._atomic.check_output_path`).
    """
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".mp4", ".gif", ".png", ""):
        raise ValueError(f"{path}: output must be .mp4, .gif or a directory for PNG frames")
    if isinstance(fps, bool) or not isinstance(fps, (int, np.integer)) or not 1 <= fps <= 1000:
        raise ValueError(f"fps must be a whole number in [1, 1000], got {fps!r}")
    if ext == ".png":
        check_output_path(os.path.dirname(path) or ".", folder=True)
    else:
        check_output_path(path, folder=ext == "")
    return ext


def _checked(frames):
    """The frames, each after :func:`pmjax._terminate.check_terminated`: an
    exit that SIGTERM raised where Python swallowed it (inside a finalizer)
    is raised again before the next frame."""
    for frame in frames:
        check_terminated()
        yield frame


def write_frames(frames, path: str, fps: int = 30) -> None:
    """Write RGB frames as a video (``.mp4``: H.264 through ffmpeg, started
    without forking; ``.gif``: looping, at ``fps``) or, for a directory path or
    ``.png`` pattern, as numbered PNGs, all moved into the folder at the end."""
    path = os.fspath(path)
    ext = check_frames_output(path, fps)
    frames = _checked(frames)
    if ext == ".mp4":
        with atomic_path(path, ext) as tmp, Mp4Writer(tmp, fps) as video:
            for frame in frames:
                video.append(frame)
        return
    if ext == ".gif":
        from PIL import Image

        images = [Image.fromarray(np.asarray(frame, np.uint8)) for frame in frames]
        if not images:
            raise ValueError(f"{path}: no frames to write")
        with atomic_path(path, ext) as tmp:
            # GIF delays are whole hundredths of a second: the nearest to 1/fps.
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], loop=0,
                           duration=10 * max(1, round(100 / fps)))
        return
    # The frames appear in the folder together, when all are written; the
    # temporary folder is private, so each frame goes straight into it.
    import imageio.v2 as imageio

    with atomic_folder(path if ext == "" else os.path.dirname(path) or ".") as tmp:
        for i, frame in enumerate(frames):
            imageio.imwrite(os.path.join(tmp, f"frame_{i:05d}.png"), np.asarray(frame), format="PNG")


def write_png(path: str, image) -> None:
    """Write one PNG atomically."""
    import imageio.v2 as imageio

    with atomic_path(path, ".png") as tmp:
        imageio.imwrite(tmp, np.asarray(image), format="PNG")


def path_geometry(pm: ProgressiveMesh, cameras: Camera, tau: float, *, tests: Tests = ALL_TESTS, geomorph: int = 0,
                  color_levels=False, coherent: bool = True, progress: bool = False, desc: str = "frames",
                  normals: str = "view", seen_from: Optional[Camera] = None):
    """Refine every camera of a path and yield what to draw, frame by frame.

    Args:
        geomorph: blend refinement changes over this many frames
            (:func:`pmjax.geomorph_step`); 0 or 1 draws each hard refinement.
            A blended mesh is shaded with the stored normals, blended along
            the ancestor chains like the positions.
        coherent: refine 32 consecutive frames at a time
            (:func:`pmjax.refine_path`, the same refinements as frame by frame).
        normals: ``"view"``: a hard refinement is shaded with normals fitted
            on the mesh drawn, seen from its camera (or ``seen_from``;
            :func:`refined_arrays`); ``"stored"``: with the stored ones.
        seen_from: the camera every frame is seen from, when not its own
            (a phantom view).

    Yields:
        ``(camera, vertices, faces, face levels or None, normals)``.
    """
    if not tau >= 0:
        raise ValueError(f"tau must be >= 0 (and not NaN), got {tau}")
    per_view = check_normals(normals) == "view"
    morph = None
    it = range(camera_count(cameras))
    if progress:
        from tqdm import tqdm

        it = tqdm(it, unit="frame", desc=desc)
    if geomorph > 1:
        # The executed set at tau and the hidden pcols (those that run even
        # at tau 0: culled or facing away, as hidden_pcols) of each frame.
        frames = path_refinement_pairs(pm, cameras, tau, tests=tests, coherent=coherent)
    else:
        frames = ((r, None) for r in refine_path(pm, cameras, tau, tests=tests, coherent=coherent))
    for i, (refined, at_zero) in zip(it, frames):
        cam = index_camera(cameras, i)
        if geomorph > 1:
            executed, hidden = np.asarray(refined.executed), np.asarray(at_zero.executed)
            if morph is None:
                morph = geomorph_start(executed, hidden)
            else:
                morph = geomorph_step(pm, morph, executed, geomorph, hidden)
            v, f, ids, shading = geomorph_mesh(pm, morph, shading_normals(pm))
            levels = face_levels(f, batch_levels(pm, ids)) if color_levels else None
        else:
            eye = np.asarray((seen_from if seen_from is not None else cam).eye) if per_view else None
            v, f, levels, shading = refined_arrays(pm, refined, color_levels=color_levels, eye=eye)
        yield cam, v, f, levels, shading


def render_path(pm: ProgressiveMesh, cameras: Camera, tau: float, out: str, *, tests: Tests = ALL_TESTS,
                wireframe=False, color_levels=False, phantom: Optional[Camera] = None, geomorph: int = 0,
                fps: int = 30, coherent: bool = True, progress: bool = True, normals: str = "view") -> dict:
    """Refine and render every camera of a path; write ``out`` (.mp4/.gif/PNG folder).

    Hard refinements in one colour (no geomorph, levels or wireframe) are
    drawn from GPU buffers that each frame's change updates in place
    (:class:`StreamScene`; normals fitted per view rewrite every live
    vertex's normal row each frame, :meth:`SlotMesh.shade`); the others
    build each frame's mesh.

    Args:
        phantom: if given, every frame is refined for its path camera but seen
            from this fixed overview camera, with the path camera's frustum drawn.
        geomorph: blend refinement changes over this many frames instead of
            popping (:func:`pmjax.geomorph_step`); 0 or 1: off.
        coherent, normals: see :func:`path_geometry` (``"view"``: seen from
            the camera each frame is drawn from).

    Returns:
        dict with ``faces`` (int per frame) and ``frames`` (count).
    """
    check_frames_output(os.fspath(out), fps)
    check_normals(normals)
    view = phantom if phantom is not None else index_camera(cameras, 0)
    n_batches = len(pm.batch_offsets) - 1
    faces = []

    def streamed():
        # Hard refinements in one colour: the GPU buffers follow each frame's change.
        with Renderer(view.width, view.height) as r:
            scene = StreamScene(r, pm)
            it = range(camera_count(cameras))
            if progress:
                from tqdm import tqdm

                it = tqdm(it, unit="frame", desc="render")
            for i, refined in zip(it, refine_path(pm, cameras, tau, tests=tests, coherent=coherent)):
                cam = index_camera(cameras, i)
                scene.update(refined)
                if normals == "view":
                    scene.mesh.shade((phantom if phantom is not None else cam).eye)
                faces.append(int(refined.n_faces))
                lines = frustum_past_model(pm, cam) if phantom is not None else None
                yield scene.render(cam, view=phantom, lines=lines)[0]

    if geomorph <= 1 and not color_levels and not wireframe:
        if not tau >= 0:
            raise ValueError(f"tau must be >= 0 (and not NaN), got {tau}")
        write_frames(streamed(), out, fps=fps)
        return dict(faces=np.asarray(faces), frames=len(faces))

    def frames():
        with Renderer(view.width, view.height) as r:
            for cam, v, f, levels, shading in path_geometry(pm, cameras, tau, tests=tests, geomorph=geomorph,
                                                            color_levels=color_levels, coherent=coherent,
                                                            progress=progress, desc="render", normals=normals,
                                                            seen_from=phantom):
                faces.append(len(f))
                lines = frustum_past_model(pm, cam) if phantom is not None else None
                yield r.render_mesh(v, f, view if phantom is not None else cam, levels=levels, n_batches=n_batches,
                                    wireframe=wireframe, lines=lines, normals=shading)[0]

    write_frames(frames(), out, fps=fps)
    return dict(faces=np.asarray(faces), frames=len(faces))
