"""Interactive viewer: pyrender's Viewer, re-refined whenever the camera moves.

Each view's mesh is a change to a :class:`pmjax.MeshStream`'s slots, written
into the window's GPU buffers in place (:class:`SlotMesh`); with the wireframe
overlay each view's mesh is built and drawn anew."""

from __future__ import annotations

import dataclasses
import os
import sys
import time

import jax
import numpy as np

from pmjax import Camera, Tests, index_camera, load, refine, save_cameras, standard_orbit

from ._gl import RenderError, pyrender_module
from ._offscreen import SlotMesh, refined_arrays
from ._scene import add_mesh, build_scene, frustum_past_model, lines_mesh

KEYS = {
    "=": "raise tau (x2)",
    "-": "lower tau (/2)",
    "p": "freeze / release a phantom camera",
    "1": "toggle the frustum test",
    "2": "toggle the orientation test",
    "3": "toggle the screen-space test",
    "e": "toggle the wireframe overlay",
    "c": "save the current camera to the camera file (JSON)",
}


@dataclasses.dataclass
class ViewerState:
    """What the keys change; the refinement loop reads it."""

    tau: float = 1.0
    frustum: bool = True
    orientation: bool = True
    screen: bool = True
    wireframe: bool = False
    phantom: Camera | None = None
    freeze_requested: bool = False
    save_requested: bool = False
    camera_file: str = "view-camera.json"
    dirty: bool = True

    def tests(self) -> Tests:
        return Tests(frustum=self.frustum, orientation=self.orientation, screen=self.screen)


def _key_actions(state: ViewerState) -> dict:
    def change(**kw):
        def act(viewer):
            for k, v in kw.items():
                setattr(state, k, v(getattr(state, k)))
            state.dirty = True

        return act

    def freeze(viewer):
        state.freeze_requested = True
        state.dirty = True

    def save(viewer):
        state.save_requested = True
        state.dirty = True

    return {
        "=": (change(tau=lambda t: t * 2.0),),
        "-": (change(tau=lambda t: t / 2.0),),
        "p": (freeze,),
        "1": (change(frustum=lambda b: not b),),
        "2": (change(orientation=lambda b: not b),),
        "3": (change(screen=lambda b: not b),),
        "e": (change(wireframe=lambda b: not b),),
        "c": (save,),
    }


def camera_from_pose(pose, like: Camera, width: int, height: int) -> Camera:
    """A :class:`pmjax.Camera` at a 4×4 camera-to-world ``pose`` with ``like``'s fov and clip planes."""
    return Camera(
        eye=np.asarray(pose[:3, 3], np.float32), rotation=np.asarray(pose[:3, :3], np.float32),
        fov_y=like.fov_y, near=like.near, far=like.far, ortho_height=like.ortho_height,
        width=int(width), height=int(height),
    )


class ViewerMesh:
    """The mesh a viewer window draws, moved to each view's refinement.

    With ``stream`` (and no wireframe) a view's mesh is its change to a
    :class:`pmjax.MeshStream`, written into the window's GPU buffers in place
    before the next draw (:class:`SlotMesh`); otherwise the mesh nodes are
    built anew. The window's thread calls :meth:`before_draw` and
    :meth:`after_draw` round each draw, under the viewer's lock.

    Args:
        pm: the mesh refined.
        scene: the viewer's ``pyrender.Scene``.
        nodes: mesh nodes already in the scene (replaced by the first view).
        stream: draw from the stream's slots where no wireframe is asked.
    """

    def __init__(self, pm, scene, nodes=(), *, stream: bool = True):
        self.pm, self.scene, self.nodes = pm, scene, list(nodes)
        self.stream = bool(stream)
        self.slots = SlotMesh(pm, scene)
        self._streamed = False  # the slots' node is what is drawn

    def show(self, refinement, lock, *, wireframe: bool = False) -> None:
        """Moves the mesh drawn to ``refinement``'s: the costly part (the
        change, or the arrays) outside ``lock``, the scene's update under it."""
        if self.stream and not wireframe:
            change = self.slots.stream.update(refinement)
            with lock:
                self._drop_nodes()
                self.slots.apply(change)
                self._streamed = True
            return
        v, f, _, normals = refined_arrays(self.pm, refinement)
        with lock:
            # The stream is not moved meanwhile: its next change is from the
            # last mesh it held, and its node is made again from its rows.
            self.slots.detach()
            self._streamed = False
            self._drop_nodes()
            self.nodes = add_mesh(self.scene, v, f, wireframe=wireframe, normals=normals)

    def _drop_nodes(self):
        """The mesh nodes built anew out of the scene."""
        for n in self.nodes:
            self.scene.remove_node(n)
        self.nodes = []

    def before_draw(self):
        """In the drawing thread, its context current: the slots' changed rows into their buffers."""
        if self._streamed:
            self.slots.before_draw()

    def after_draw(self):
        """In the drawing thread, once drawn: notes the buffers the draw used."""
        if self._streamed:
            self.slots.after_draw()


def viewer_class(pyrender):
    """pyrender's ``Viewer`` drawing a :class:`ViewerMesh`: keyword
    ``mesh`` (the :class:`ViewerMesh`) and ``drawn`` (optional
    ``drawn(viewer)``, called in the window's thread once the scene is drawn,
    before the captions)."""

    class StreamViewer(pyrender.Viewer):
        def __init__(self, scene, *, mesh: ViewerMesh, drawn=None, **kwargs):
            # Set before pyrender's constructor: with run_in_thread its window
            # may draw before the constructor returns.
            self.mesh, self.drawn = mesh, drawn
            super().__init__(scene, **kwargs)

        def _render(self):
            self.mesh.before_draw()
            super()._render()
            self.mesh.after_draw()
            if self.drawn is not None:
                self.drawn(self)

    return StreamViewer


def open_viewer(pm, start: Camera, state: ViewerState, *, title: str = "pmjax view", stream: bool = True,
                drawn=None):
    """Open the viewer's window (in its own thread) on ``pm`` refined for ``start``.

    Args:
        pm: :class:`pmjax.ProgressiveMesh`.
        start: the first camera (its width and height: the window's size).
        state: the keys' :class:`ViewerState`.
        stream: draw each view's change in place (see :class:`ViewerMesh`).
        drawn: see :func:`viewer_class`.

    Returns:
        ``(viewer, mesh, caption)``: the pyrender viewer, its
        :class:`ViewerMesh` and the caption's style.
    """
    pyrender = pyrender_module(offscreen=False)
    W, H = int(start.width), int(start.height)
    first = refine(pm, start, state.tau)
    v, f, _, normals = refined_arrays(pm, first)
    scene, nodes = build_scene(v, f, start, light=False, normals=normals)
    mesh = ViewerMesh(pm, scene, nodes, stream=stream)
    caption = dict(location=pyrender.constants.TextAlign.TOP_LEFT, font_name="OpenSans-Regular", font_pt=16,
                   color=np.array([0.1, 0.1, 0.1, 1.0]), scale=1.0)
    viewer = viewer_class(pyrender)(
        scene, mesh=mesh, drawn=drawn, viewport_size=(W, H), run_in_thread=True,
        registered_keys=_key_actions(state), use_direct_lighting=True, window_title=title,
        caption=[dict(caption, text="pmjax")],
    )
    return viewer, mesh, caption


def run_viewer(path: str, *, tau: float = 1.0, size=(800, 600), close_after: float = 0.0,
               camera_file: str = "view-camera.json", stream: bool = True) -> None:
    """Open ``pmjax view``: an interactive window (needs a display, e.g. Xvfb).

    Args:
        path: ``.pmz`` file.
        tau: initial tolerance in pixels.
        size: window ``(width, height)``.
        close_after: close after this many seconds (0: when the user quits).
        camera_file: where the ``c`` key saves the current camera (JSON, as
            :func:`pmjax.save_cameras` writes and ``--camera`` reads).
        stream: draw each view's mesh as its change, written into the GPU
            buffers in place (False: each view's mesh built anew; the
            wireframe overlay always is).
    """
    check_display()
    pm = load(path)
    W, H = int(size[0]), int(size[1])
    verts = np.asarray(pm.vertices)[: pm.n_original_vertices]
    start = index_camera(standard_orbit(verts, 240, width=W, height=H), 0)
    state = ViewerState(tau=float(tau), camera_file=camera_file)
    viewer, mesh, caption = open_viewer(pm, start, state, title=f"pmjax view {path}", stream=stream)
    scene = viewer.scene
    # Re-refine whenever the camera moves, until the window closes (or its
    # thread dies: a window that failed to open ends the loop too).
    began, last_pose, frustum_node = time.time(), None, None
    try:
        while viewer.is_active and viewer._thread.is_alive():
            with viewer.render_lock:
                pose = np.array(scene.get_pose(viewer._camera_node))
            if state.dirty or last_pose is None or not np.allclose(pose, last_pose):
                last_pose = pose
                current = camera_from_pose(pose, start, W, H)
                if state.freeze_requested:
                    state.phantom = None if state.phantom is not None else current
                    state.freeze_requested = False
                saved = ""
                if state.save_requested:
                    save_cameras(current, state.camera_file)
                    state.save_requested = False
                    saved = f"  saved camera to {state.camera_file}"
                state.dirty = False
                target = state.phantom if state.phantom is not None else current
                t = time.perf_counter()
                ref = refine(pm, target, state.tau, state.tests())
                jax.block_until_ready(ref.n_faces)
                ms = 1e3 * (time.perf_counter() - t)
                text = (f"faces {int(ref.n_faces)}  refine {ms:.1f} ms  tau {state.tau:g} px  tests "
                        f"{'F' if state.frustum else '-'}{'O' if state.orientation else '-'}"
                        f"{'S' if state.screen else '-'}{'  phantom' if state.phantom is not None else ''}{saved}")
                mesh.show(ref, viewer.render_lock, wireframe=state.wireframe)
                with viewer.render_lock:
                    if frustum_node is not None:
                        scene.remove_node(frustum_node)
                        frustum_node = None
                    if state.phantom is not None:
                        frustum_node = scene.add(lines_mesh(frustum_past_model(pm, state.phantom)),
                                                 name="phantom-frustum")
                    viewer.viewer_flags["caption"] = [dict(caption, text=text)]
            if close_after and time.time() - began > close_after:
                viewer.close_external()
                break
            time.sleep(0.03)
    except KeyboardInterrupt:  # Ctrl-C: close the window, or its thread keeps the process alive
        viewer.close_external()
    if viewer.run_in_thread and viewer.is_active and not viewer._thread.is_alive():
        raise RenderError("the viewer window closed unexpectedly (see the messages above)")


def check_display() -> None:
    """Refuse to start the viewer where no window can open.

    Raises:
        RenderError: no ``DISPLAY``/``WAYLAND_DISPLAY`` on Linux, or the
            display cannot be opened; the message suggests ``xvfb-run``.
    """
    hint = "run it on a desktop, or under a virtual display: xvfb-run -a pmjax view ..."
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise RenderError(f"pmjax view needs a display and DISPLAY is not set; {hint}")
    try:
        import pyglet

        pyglet.display.get_display()
    except Exception as exc:  # pyglet raises its own types for an unreachable display
        raise RenderError(f"cannot open the display {os.environ.get('DISPLAY', '')!r} "
                          f"({type(exc).__name__}: {exc}); {hint}") from exc


