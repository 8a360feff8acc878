"""Image-space fidelity: refined vs original renders, and popping between frames."""

from __future__ import annotations

import time

import numpy as np

from pmjax import ALL_TESTS, Camera, ProgressiveMesh, Tests, index_camera


from ._offscreen import Renderer, original_arrays, path_geometry
from ._scene import mesh_node_geometry, new_scene, place_view

# A pixel "differs" when some 8-bit channel differs by more than this.
DIFF_THRESHOLD = 8


def image_difference(rgb_a, depth_a, rgb_b, depth_b, threshold: int = DIFF_THRESHOLD) -> dict:
    """Compare two renders of the same model from the same camera.

    The model's pixels are those covered in either render (``depth > 0``).

    Returns:
        dict: ``model_pixels``, ``differing`` (count), ``differing_share``
        (of the model's pixels), ``mse`` (mean squared 8-bit difference over
        the model's pixels and channels) and ``psnr`` (dB; ``inf`` if identical).
    """
    a = np.asarray(rgb_a, np.float32)
    b = np.asarray(rgb_b, np.float32)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    model = (np.asarray(depth_a) > 0) | (np.asarray(depth_b) > 0)
    n = int(model.sum())
    diff = np.abs(a - b)
    # The largest channel difference, channel by channel: a reduction over a
    # length-3 last axis costs some hundred times more.
    largest = diff[..., 0]
    for c in range(1, diff.shape[-1]):
        largest = np.maximum(largest, diff[..., c])
    differing = int(((largest > threshold) & model).sum())
    mse = float((diff[model].astype(np.float64) ** 2).mean()) if n else 0.0
    psnr = float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)
    return dict(model_pixels=n, differing=differing, differing_share=differing / n if n else 0.0, mse=mse, psnr=psnr)


# Pixels beyond the model's bounding box that FLIP is evaluated on: more than
# its filters' reach at the default 67 pixels per degree (the error of a change
# spreads about 10 pixels), so the cropped evaluation equals the full one.
FLIP_MARGIN = 32


def flip_module():
    """NVIDIA's FLIP (the ``flip_evaluator`` module), or a clear error naming the package."""
    try:
        import flip_evaluator
    except ImportError as exc:
        raise RuntimeError("FLIP needs the flip-evaluator package (NVIDIA's FLIP image metric): "
                           "pip install flip-evaluator") from exc
    return flip_evaluator


def flip_difference(rgb_ref, depth_ref, rgb_test, depth_test) -> dict:
    """NVIDIA's FLIP (LDR) between a reference render and a test render of the same view.

    Args:
        rgb_ref, rgb_test: ``[H, W, 3]`` sRGB colour in [0, 255] (uint8 or
            unrounded float32, :class:`Renderer`).
        depth_ref, depth_test: ``[H, W]``, 0 where empty; the model's pixels
            are those covered in either.

    Returns:
        dict: ``flip_mean`` (mean FLIP over the image, 0 for identical
        images, at most 1) and ``flip_model_mean`` (over the model's pixels;
        0 when there are none). FLIP is evaluated on the model's bounding box
        grown by :data:`FLIP_MARGIN` pixels: the background around it is the
        same in both renders.
    """
    a = np.clip(np.asarray(rgb_ref, np.float32) / 255.0, 0.0, 1.0)
    b = np.clip(np.asarray(rgb_test, np.float32) / 255.0, 0.0, 1.0)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    model = (np.asarray(depth_ref) > 0) | (np.asarray(depth_test) > 0)
    if not model.any():
        # Nothing drawn in either: two renders of the background alone.
        error = np.asarray(flip_module().evaluate(a, b, "LDR", applyMagma=False)[0], np.float64)
        return dict(flip_mean=float(error.mean()), flip_model_mean=0.0)
    # Away from the model both images are the same background, where FLIP is
    # 0; its filters reach FLIP_MARGIN pixels at most, so FLIP of the model's
    # box grown by the margin equals the full image's there.
    rows, cols = np.flatnonzero(model.any(axis=1)), np.flatnonzero(model.any(axis=0))
    y0, y1 = max(rows[0] - FLIP_MARGIN, 0), min(rows[-1] + 1 + FLIP_MARGIN, a.shape[0])
    x0, x1 = max(cols[0] - FLIP_MARGIN, 0), min(cols[-1] + 1 + FLIP_MARGIN, a.shape[1])
    error, _, _ = flip_module().evaluate(a[y0:y1, x0:x1], b[y0:y1, x0:x1], "LDR", applyMagma=False)
    error = np.asarray(error, np.float64).reshape(y1 - y0, x1 - x0)
    return dict(flip_mean=float(error.sum() / model.size), flip_model_mean=float(error[model[y0:y1, x0:x1]].mean()))


def silhouette_difference(renderer, mesh_a, mesh_b, camera: Camera) -> dict:
    """:func:`image_difference` of two meshes drawn unlit, in one flat colour.

    Shading plays no part, so what differs is where the surfaces lie on
    screen: coverage along the silhouettes and at holes. It estimates the part
    of a lit comparison that no normals or shading on ``mesh_b``'s geometry
    could remove: with ``s × s`` samples a coverage change moves a pixel by at
    least ``1/s²`` of the model-to-background contrast, which at 2×2 exceeds
    the threshold for any model colour below 223 of 255 (lit or flat; the
    flat colour is about 87). An estimate, not a bound: a lit edge brighter
    than that hides a one-sample change.

    Args:
        renderer: a :class:`Renderer` of ``camera``'s size.
        mesh_a, mesh_b: ``(vertices [V, 3], faces [F, 3])`` each.
        camera: the view.

    Returns:
        The dict of :func:`image_difference` for the two flat renders.
    """
    flat_a = renderer.render_mesh(*mesh_a, camera, light=False)
    flat_b = renderer.render_mesh(*mesh_b, camera, light=False)
    return image_difference(*flat_a, *flat_b)


def camera_fidelity(renderer, original, mesh, camera: Camera, *, flip: bool = True,
                    popping: bool = False) -> tuple[dict, tuple]:
    """One view's image metrics: ``mesh`` (a refinement's geometry) against
    the ``original`` mesh, both drawn lit and unlit from ``camera``.

    The renders are those of :meth:`Renderer.render_mesh` and
    :func:`silhouette_difference`, bit for bit; the original's GPU buffers
    stay in the renderer's context from one call to the next while
    ``original`` is the same tuple (:class:`FidelityScene`).

    Args:
        renderer: a :class:`Renderer` of ``camera``'s size.
        original, mesh: ``(vertices [V, 3], faces [F, 3], normals [V, 3])``
            each (:func:`original_arrays`, :func:`refined_arrays`).
        camera: one view.
        flip: also NVIDIA's FLIP against the original (:func:`flip_difference`).
        popping: also compare with the mesh of the previous call on this
            context and original, drawn from ``camera`` (0 when there is none).

    Returns:
        ``(row, (rgb, depth))``: ``row`` holds ``differing_share``, ``psnr``,
        ``silhouette_share`` (:func:`silhouette_difference`), ``flip_mean`` and
        ``flip_model_mean`` (with ``flip``), ``popping_share`` and
        ``popping_mse`` (with ``popping``: the ``differing_share`` and ``mse``
        of :func:`image_difference` of the previous mesh's render against
        this one's), ``render_ms`` (drawing ``mesh``,
        milliseconds) and the other keys of :func:`image_difference`;
        ``(rgb, depth)`` is ``mesh``'s lit render. No OpenGL context is left
        current in the calling thread, so another thread may call next.
    """
    scene = FidelityScene.of(renderer, original)
    try:
        scene.set_mesh(*mesh)
        t = time.perf_counter()
        rgb, depth = scene.render(scene.mesh, camera)
        render_ms = 1e3 * (time.perf_counter() - t)
        reference = scene.render(scene.original, camera)
        silhouette = image_difference(*scene.render(scene.original, camera, light=False),
                                      *scene.render(scene.mesh, camera, light=False))["differing_share"]
        before = scene.render(scene.previous, camera) if popping and scene.previous is not None else None
    finally:
        _release_context(renderer)
    row = image_difference(*reference, rgb, depth)
    if flip:
        row.update(flip_difference(*reference, rgb, depth))
    row.update(render_ms=render_ms, silhouette_share=silhouette)
    if popping:
        pop = image_difference(*before, rgb, depth) if before is not None else dict(differing_share=0.0, mse=0.0)
        row.update(popping_share=pop["differing_share"], popping_mse=pop["mse"])
    return row, (rgb, depth)


_SCENES: dict = {}


class FidelityScene:
    """One pyrender scene holding the original mesh, the refined mesh of the
    current view and that of the view before, of which each draw shows one,
    lit or unlit: the meshes' GPU buffers are made once and stay in the
    renderer's context (pyrender deletes the buffers of meshes missing from
    the scene it draws), so the original is uploaded once, not four times a
    frame. A draw equals :meth:`Renderer.render_mesh` of the same arrays bit
    for bit (same primitives, camera, light and background; a hidden mesh is
    not drawn; unlit, the shader reads no normal).

    Use :meth:`of`: one per OpenGL context, holding the last original drawn
    in it (kept, with its buffers, until another original is drawn there).

    Args:
        renderer: the :class:`Renderer` drawing it.
        original: ``(vertices [V, 3], faces [F, 3], normals [V, 3])``.
    """

    def __init__(self, renderer, original):
        self.renderer, self.original_arrays = renderer, original
        self.context = renderer._gl
        self.scene = new_scene()
        self.original = self._add(*original)
        self.mesh = self.previous = None
        self._camera = self._light = None

    @classmethod
    def of(cls, renderer, original) -> "FidelityScene":
        """The scene of ``renderer``'s context holding ``original`` (the same
        tuple object), made if there is none. Renderer handles of one size
        share a context (:class:`Renderer`), and so this scene."""
        key = id(renderer._gl)
        held = _SCENES.get(key)
        if held is None or held.original_arrays is not original or held.context is not renderer._gl:
            held = _SCENES[key] = cls(renderer, original)
        held.renderer = renderer
        return held

    def _add(self, vertices, faces, normals):
        """A hidden mesh node of these arrays (None for no faces)."""
        if not len(np.asarray(faces).reshape(-1, 3)):
            return None
        node = self.scene.add(mesh_node_geometry(vertices, faces, normals=normals), name="mesh")
        node.mesh.is_visible = False
        return node

    def set_mesh(self, vertices, faces, normals) -> None:
        """Make these arrays the current mesh; the current one becomes the
        previous (:meth:`render` of :attr:`previous`), the previous leaves."""
        if self.previous is not None:
            self.scene.remove_node(self.previous)
        self.previous, self.mesh = self.mesh, self._add(vertices, faces, normals)

    def render(self, node, camera: Camera, *, light: bool = True):
        """``(rgb, depth)`` of ``node`` alone (None: nothing) seen from
        ``camera``, as :meth:`Renderer.render_scene` returns them."""
        if (int(camera.width), int(camera.height)) != (self.renderer.width, self.renderer.height):
            raise ValueError(f"camera is {int(camera.width)}x{int(camera.height)}, renderer "
                             f"{self.renderer.width}x{self.renderer.height}")
        self._camera, self._light = place_view(self.scene, camera, (self._camera, self._light), light=light)
        shown = [n for n in (self.original, self.mesh, self.previous) if n is not None]
        for n in shown:
            n.mesh.is_visible = n is node
        try:
            return self.renderer.render_scene(self.scene)
        finally:
            for n in shown:
                n.mesh.is_visible = False


def _release_context(renderer) -> None:
    """Make ``renderer``'s EGL context current in no thread: EGL lets a
    context be current in one thread at a time, and pyrender leaves it
    current after drawing, so another thread could not draw with it. (OSMesa
    rebinds a context to whichever thread draws.)"""
    platform = getattr(getattr(renderer, "_gl", None), "_platform", None)
    display = getattr(platform, "_egl_display", None)
    if display is not None:
        from OpenGL import EGL

        EGL.eglMakeCurrent(display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)


def path_fidelity(pm: ProgressiveMesh, cameras: Camera, tau: float, *, tests: Tests = ALL_TESTS,
                  geomorph: int = 0, supersample: int = 2, float_color: bool = True, coherent: bool = True,
                  progress: bool = False, flip: bool = True, normals: str = "view") -> list[dict]:
    """Per frame: faces, share of the model's pixels that differ from the
    original mesh's render (and PSNR), the part of that share due to geometry
    alone (:func:`silhouette_difference`), and popping — the share of pixels
    that change at this frame's camera only because the refinement changed
    since the previous frame (render with the previous frame's geometry vs
    this one's).

    Args:
        geomorph: blend refinement changes over this many frames
            (:func:`pmjax.geomorph_step`); 0 or 1 draws each frame's hard
            refinement.
        supersample: render at this many times the size and average down
            (anti-aliasing: without it an edge moving by a fraction of a pixel
            flips whole pixels, and every small motion counts as popping).
            Popping measurements want 4 or more (docs/soft.md).
        float_color: compare the unrounded supersampled averages
            (:class:`Renderer`), so changes below one 8-bit level count as
            their size, not as a 0-or-1 rounding flip.
        coherent: refine 32 consecutive frames at a time (same refinements,
            :func:`pmjax.refine_path`).
        flip: also NVIDIA's FLIP against the original (:func:`flip_difference`;
            needs the flip-evaluator package).
        normals: ``"view"``: each hard refinement shaded with normals fitted
            on the mesh drawn, seen from its camera
            (:func:`pmjax.render.refined_arrays`); ``"stored"``: with the
            stored normals. The original is drawn with its stored normals.

    Returns:
        list of dicts (one per camera) with ``faces``, ``differing_share``,
        ``psnr``, ``silhouette_share``, ``popping_share`` (visibly changed pixels
        against the previous frame's mesh as it was drawn, see
        :data:`DIFF_THRESHOLD`; with ``normals="view"`` its normals are the
        previous eye's fit, so the share includes that reshading),
        ``popping_mse`` (mean squared change: a
        change spread over ``n`` frames counts ``1/n`` as much per frame),
        both 0 for the first frame, ``flip_mean`` and ``flip_model_mean``
        (with ``flip``), ``render_ms`` (drawing the refined frame) and
        ``fidelity_ms`` (all of this frame's measuring: renders and metrics).
        The original is drawn once per frame (lit, and unlit for the
        silhouette) for every column.
    """
    if flip:
        flip_module()  # a missing package is named before any rendering
    first = index_camera(cameras, 0)
    original = original_arrays(pm)
    rows = []
    with Renderer(int(first.width), int(first.height), supersample, float_color) as r:
        frames = path_geometry(pm, cameras, tau, tests=tests, geomorph=geomorph, coherent=coherent, progress=progress,
                               desc="fidelity", normals=normals)
        for i, (cam, v, f, _, n) in enumerate(frames):
            t = time.perf_counter()
            # Popping against the previous frame's mesh, still in the scene
            # camera_fidelity draws (none before the first frame).
            row, _ = camera_fidelity(r, original, (v, f, n), cam, flip=flip, popping=i > 0)
            row.update(frame=i, faces=int(len(f)))
            if not i:
                row.update(popping_share=0.0, popping_mse=0.0)
            row.update(fidelity_ms=1e3 * (time.perf_counter() - t))
            rows.append(row)
    return rows
