"""The paper's figures as functions: the effect of each test, seen from a
phantom (overview) camera with the refining camera's frustum drawn."""

from __future__ import annotations

import os

import numpy as np

from pmjax import ALL_TESTS, Camera, ProgressiveMesh, Tests, index_camera, look_at, refine, standard_orbit

from ._annotate import FRUSTUM_SWATCH, LEVELS, annotate
from ._offscreen import Renderer, check_normals, render_refinement, write_png
from ._scene import frustum_past_model


def overview_camera(vertices, camera: Camera, *, distance_scale: float = 2.5, lift: float = 0.6) -> Camera:
    """A camera behind and above ``camera`` that sees both the model and
    ``camera``'s eye (same image size and fov)."""
    v = np.asarray(vertices, np.float64)
    centre = 0.5 * (v.min(0) + v.max(0))
    eye = np.asarray(camera.eye, np.float64)
    back = eye - centre
    radius = 0.5 * np.linalg.norm(v.max(0) - v.min(0))
    up = np.asarray(camera.rotation, np.float64)[:, 1]
    new_eye = centre + distance_scale * back + lift * np.linalg.norm(back) * up + 0.5 * radius * up
    target = 0.5 * (centre + eye)
    far = 2.0 * np.linalg.norm(new_eye - centre) + 2 * radius
    return look_at(new_eye, target, up=up, fov_y_deg=float(np.degrees(camera.fov_y)), width=int(camera.width),
                   height=int(camera.height), near=far * 1e-4, far=far)


def phantom(pm: ProgressiveMesh, refine_for: Camera, tau=1.0, tests: Tests = ALL_TESTS):
    """Refine for one camera; return geometry to be seen from another.

    Returns:
        ``(vertices float32[n, 3], faces int32[m, 3], frustum float32[16, 3])``:
        the refined mesh and ``refine_for``'s view pyramid as 8 line segments
        reaching past the model.
    """
    v, f, _ = refine(pm, refine_for, tau, tests).mesh(pm)
    return v, f, frustum_past_model(pm, refine_for)


FIGURES = ("frustum", "orientation", "screen", "phantom")


def paper_figures(pm: ProgressiveMesh, out_dir: str, *, width=800, height=600, taus=(1.0, 4.0, 16.0),
                  normals: str = "view") -> dict:
    """Write the paper's figures as PNGs into ``out_dir``; returns ``{name: (path, faces)}``.

    Each PNG has a title, a caption (what is shown, tau, faces drawn) and a
    legend in a band above the rendering (:func:`annotate`); faces are
    coloured by batch level (blue fine, red coarse) where the point is where
    the mesh stays fine.

    - ``frustum.png``: only the frustum test, for a close camera, seen from an
      overview: fine inside the frustum, coarse outside.
    - ``orientation.png``: only the orientation test, for the orbit's first
      camera, seen from its side: the fine front beside the coarse back.
    - ``screen_tau{t}.png``: only the screen test at three tolerances (wireframe).
    - ``phantom.png``: all tests, for the close camera, seen from the overview.

    ``normals``: ``"view"`` shades each refinement with normals fitted on the
    mesh drawn, seen from the camera it is drawn from; ``"stored"`` with the
    stored ones (:func:`render_refinement`).
    """
    check_normals(normals)
    os.makedirs(out_dir, exist_ok=True)
    verts = np.asarray(pm.vertices)[: pm.n_original_vertices]
    F = len(pm.faces)
    orbit = index_camera(standard_orbit(verts, 240, width=width, height=height), 0)
    centre = 0.5 * (verts.min(0) + verts.max(0))
    close = look_at(centre + 0.45 * (np.asarray(orbit.eye) - centre), centre, fov_y_deg=30.0, width=width,
                    height=height)
    overview = overview_camera(verts, close)
    # From the orbit camera's right: its view direction crosses the image, so
    # the front it sees and the back it does not are side by side.
    rotation = np.asarray(orbit.rotation, np.float64)
    reach = np.linalg.norm(np.asarray(orbit.eye, np.float64) - centre)
    side = look_at(centre + reach * rotation[:, 0], centre, up=rotation[:, 1], width=width, height=height,
                   near=1e-3 * reach, far=4 * reach)
    only = dict(
        frustum=Tests(frustum=True, orientation=False, screen=False),
        orientation=Tests(frustum=False, orientation=True, screen=False),
        screen=Tests(frustum=False, orientation=False, screen=True),
    )
    frustum = (FRUSTUM_SWATCH, "refining camera's view frustum")
    levels = (LEVELS, "batch level: fine (original) to coarse")
    out = {}
    with Renderer(width, height) as r:

        def save(name, refined_for, seen_from, tau, tests, title, caption, *, phantom_lines=True, colour=True):
            ref = refine(pm, refined_for, tau, tests)
            rgb, _ = render_refinement(r, pm, ref, seen_from, wireframe=True, color_levels=colour,
                                       phantom=refined_for if phantom_lines else None, normals=normals)
            faces = int(ref.n_faces)
            legend = ((levels,) if colour else ()) + ((frustum,) if phantom_lines else ())
            path = os.path.join(out_dir, name + ".png")
            write_png(path, annotate(rgb, title, f"{caption} tau = {tau:g} px; {faces:,} of {F:,} faces drawn.",
                                     legend))
            out[name] = (path, faces)

        save("frustum", close, overview, 0.0, only["frustum"], "View-frustum test",
             "Refined for a close camera (red lines: its frustum), seen from behind it; only the frustum test: "
             "fine inside the frustum, coarse outside.")
        save("orientation", orbit, side, 0.0, only["orientation"], "Surface-orientation test",
             "Refined for a camera off to the left, seen from the side; only the orientation test: the front it "
             "sees stays fine, the back facing away is coarse.")
        for tau in taus:
            save(f"screen_tau{tau:g}", orbit, orbit, tau, only["screen"], f"Screen-space error test, tau {tau:g} px",
                 "Seen from the refining camera; only the screen-space test: a collapse is made while its error "
                 "on screen stays below tau.", phantom_lines=False, colour=False)
        save("phantom", close, overview, 1.0, ALL_TESTS, "Phantom camera: all three tests",
             "Refined for a close camera (red lines: its frustum), seen from behind it with every test on.")
    return out
