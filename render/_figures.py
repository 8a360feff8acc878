"""The paper's figures as functions: the effect of each test, seen from a
phantom (overview) camera with the refining camera's frustum drawn."""

from __future__ import annotations

import os

import numpy as np

from pmjax import ALL_TESTS, Camera, ProgressiveMesh, Tests, index_camera, look_at, refine, standard_orbit

from ._offscreen import Renderer, render_refinement, write_png
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


def paper_figures(pm: ProgressiveMesh, out_dir: str, *, width=800, height=600, taus=(1.0, 4.0, 16.0)) -> dict:
    """Write the paper's figures as PNGs into ``out_dir``; returns ``{name: (path, faces)}``.

    - ``frustum.png``: only the frustum test, a close camera, seen from an overview.
    - ``orientation.png``: only the orientation test, seen from the side.
    - ``screen_tau{t}.png``: only the screen test at three tolerances (wireframe).
    - ``phantom.png``: all tests, the refined mesh seen from the overview.
    """
    os.makedirs(out_dir, exist_ok=True)
    verts = np.asarray(pm.vertices)[: pm.n_original_vertices]
    orbit = index_camera(standard_orbit(verts, 240, width=width, height=height), 0)
    centre = 0.5 * (verts.min(0) + verts.max(0))
    close = look_at(centre + 0.45 * (np.asarray(orbit.eye) - centre), centre, fov_y_deg=30.0, width=width,
                    height=height)
    overview = overview_camera(verts, close)
    side = overview_camera(verts, orbit, distance_scale=-1.0, lift=0.3)
    only = dict(
        frustum=Tests(frustum=True, orientation=False, screen=False),
        orientation=Tests(frustum=False, orientation=True, screen=False),
        screen=Tests(frustum=False, orientation=False, screen=True),
    )
    out = {}
    with Renderer(width, height) as r:

        def save(name, refined_for, seen_from, tau, tests, phantom_lines=True):
            ref = refine(pm, refined_for, tau, tests)
            rgb, _ = render_refinement(r, pm, ref, seen_from, wireframe=True,
                                       phantom=refined_for if phantom_lines else None)
            path = os.path.join(out_dir, name + ".png")
            write_png(path, rgb)
            out[name] = (path, int(ref.n_faces))

        save("frustum", close, overview, 0.0, only["frustum"])
        save("orientation", orbit, side, 0.0, only["orientation"])
        for tau in taus:
            save(f"screen_tau{tau:g}", orbit, orbit, tau, only["screen"], phantom_lines=False)
        save("phantom", close, overview, 1.0, ALL_TESTS)
    return out
