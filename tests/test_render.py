"""Headless rendering checked on real pixels: silhouette coverage, phantom
frustum lines, batch-level colours, videos, figures, fidelity, and the
interactive viewer in a real X window (Xvfb)."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from pmjax._atomic import TEMP_MARK

import pmjax


@pytest.fixture(scope="module")
def cow(built, tmp_path_factory):
    data = built("cow.ply")
    path = str(tmp_path_factory.mktemp("render") / "cow.pmz")
    pmjax.save_pm(data, path)
    return path, pmjax.load(path), data


@pytest.fixture(scope="module")
def renderer():
    from pmjax.render import Renderer

    with Renderer(320, 240) as r:
        yield r


def _camera(data, frame=0, n=8):
    return pmjax.index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], n, width=320,
                                                   height=240), frame)


def _red(rgb):
    return (rgb[..., 0] > 180) & (rgb[..., 1] < 110) & (rgb[..., 2] < 110)


def test_small_tau_covers_the_original_silhouette(cow, renderer):
    from pmjax.render import image_difference, original_arrays, render_refinement

    _, pm, data = cow
    cam = _camera(data)
    ov, of, on = original_arrays(pm)
    ref_rgb, ref_depth = renderer.render_mesh(ov, of, cam, normals=on)
    assert 0.05 < (ref_depth > 0).mean() < 0.9  # the model is in view
    fine = image_difference(ref_rgb, ref_depth, *render_refinement(renderer, pm, pmjax.refine(pm, cam, 0.25), cam))
    coarse = image_difference(ref_rgb, ref_depth, *render_refinement(renderer, pm, pmjax.refine(pm, cam, 8.0), cam))
    _, fine_depth = render_refinement(renderer, pm, pmjax.refine(pm, cam, 0.25), cam)
    iou = ((fine_depth > 0) & (ref_depth > 0)).sum() / ((fine_depth > 0) | (ref_depth > 0)).sum()
    assert iou > 0.98
    assert fine["differing_share"] < coarse["differing_share"]
    assert fine["psnr"] > coarse["psnr"]
    same = image_difference(ref_rgb, ref_depth, ref_rgb, ref_depth)
    assert same["differing"] == 0 and same["psnr"] == float("inf")


def test_silhouette_difference_sees_geometry_not_shading(cow, renderer):
    """Flat (unlit) renders separate geometry from shading: new normals on the
    original geometry change the lit image but not the flat one; a coarse
    refinement changes both, and its flat difference grows with tau."""
    from pmjax.render import image_difference, original_arrays, refined_arrays, silhouette_difference

    _, pm, data = cow
    cam = _camera(data)
    ov, of, on = original_arrays(pm)
    bent = on + np.random.default_rng(0).normal(0.0, 0.3, on.shape).astype(np.float32)
    bent /= np.linalg.norm(bent, axis=1, keepdims=True)
    lit = image_difference(*renderer.render_mesh(ov, of, cam, normals=on),
                           *renderer.render_mesh(ov, of, cam, normals=bent))
    assert lit["differing"] > 500
    flat = [renderer.render_mesh(ov, of, cam, normals=n, light=False)[0] for n in (on, bent)]
    assert np.array_equal(flat[0], flat[1])
    assert silhouette_difference(renderer, (ov, of), (ov, of), cam)["differing"] == 0

    shares = {}
    for tau in (0.25, 8.0):
        v, f, _, _ = refined_arrays(pm, pmjax.refine(pm, cam, tau))
        shares[tau] = silhouette_difference(renderer, (ov, of), (v, f), cam)["differing_share"]
    assert 0 < shares[0.25] < shares[8.0]


def test_phantom_shows_the_frustum_lines(cow, renderer):
    from pmjax.render import overview_camera, phantom, render_refinement

    _, pm, data = cow
    cam = _camera(data)
    view = overview_camera(data.vertices[: data.n_original_vertices], cam)
    v, f, lines = phantom(pm, cam, 1.0)
    assert lines.shape == (16, 3) and len(f) == int(pmjax.refine(pm, cam, 1.0).n_faces)
    ref = pmjax.refine(pm, cam, 1.0)
    with_lines, _ = render_refinement(renderer, pm, ref, view, phantom=cam)
    without, _ = render_refinement(renderer, pm, ref, view)
    assert _red(with_lines).sum() > 100
    assert _red(without).sum() == 0


def test_batch_level_colours_and_wireframe(cow, renderer):
    from pmjax.render import render_refinement

    _, pm, data = cow
    cam = _camera(data)
    ref = pmjax.refine(pm, cam, 2.0)
    plain, depth = render_refinement(renderer, pm, ref, cam)
    levels, _ = render_refinement(renderer, pm, ref, cam, color_levels=True)
    wire, _ = render_refinement(renderer, pm, ref, cam, wireframe=True)
    model = depth > 0
    # grey shading has equal channels; level colours are blue to red
    assert np.abs(plain[model].astype(int)[:, 2] - plain[model].astype(int)[:, 0]).mean() < 12
    assert np.abs(levels[model].astype(int)[:, 2] - levels[model].astype(int)[:, 0]).mean() > 20
    dark = lambda im: (im[model].astype(int).sum(-1) < 200).sum()
    assert dark(wire) > dark(plain) + 200


@pytest.mark.parametrize("ext", [".gif", ".mp4"])
@pytest.mark.slow
def test_video_has_one_frame_per_camera(cow, tmp_path, ext):
    path, _, _ = cow
    out = tmp_path / f"orbit{ext}"
    r = subprocess.run([sys.executable, "-m", "pmjax", "render", path, "--orbit", "7", "-o", str(out), "-q",
                        "--fps", "20"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "Warning" not in r.stderr and "fork" not in r.stderr  # the encoder is spawned, not forked
    # Decode in a process without JAX (imageio's reader forks ffmpeg).
    decoded = tmp_path / "frames.npy"
    code = ("import sys, numpy as np, imageio.v2 as imageio; r = imageio.get_reader(sys.argv[1]); "
            "np.save(sys.argv[2], np.stack([np.asarray(f)[..., :3] for f in r])); "
            "print(r.get_meta_data().get('fps', 0))")
    fps = subprocess.run([sys.executable, "-c", code, str(out), str(decoded)], capture_output=True, text=True,
                         check=True).stdout.strip()
    frames = np.load(decoded)
    assert len(frames) == 7
    assert frames[0].shape[:2] == (600, 800)
    assert not np.array_equal(frames[0], frames[3])  # the camera moves
    if ext == ".mp4":
        assert float(fps) == 20
    else:  # a GIF plays at the path's rate: 50 ms per frame at 20 fps, looping
        from PIL import Image

        gif = Image.open(out)
        assert gif.info["duration"] == 50 and gif.info["loop"] == 0


def test_figures_command(cow, tmp_path):
    import imageio.v2 as imageio

    from pmjax.render import paper_figures

    _, pm, _ = cow
    out = paper_figures(pm, str(tmp_path), width=320, height=240)
    assert set(out) == {"frustum", "orientation", "screen_tau1", "screen_tau4", "screen_tau16", "phantom"}
    faces = [out[f"screen_tau{t}"][1] for t in (1, 4, 16)]
    assert faces[0] > faces[1] > faces[2]
    for name, (path, _) in out.items():
        img = imageio.imread(path)[..., :3].astype(int)
        band, view = img[:-240], img[-240:]
        assert img.shape[1] == 320 and len(band) > 20, name
        assert (view.sum(-1) < 700).mean() > 0.01, name  # the model is drawn
        assert (band.sum(-1) < 200).mean() > 0.01, name  # the title and caption are written above it
        bluish = (band[..., 2] > band[..., 0] + 60).sum()  # the batch-level ramp in the legend
        assert (bluish > 10) == (not name.startswith("screen")), name
    assert _red(imageio.imread(out["phantom"][0])[-240:]).sum() > 50


@pytest.mark.slow
def test_path_fidelity_columns(cow, tmp_path):
    path, _, _ = cow
    out = tmp_path / "stats.csv"
    r = subprocess.run([sys.executable, "-m", "pmjax", "path", path, "--orbit", "4", "--fidelity", "--csv",
                        str(out), "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 4
    assert {"differing_share", "psnr", "silhouette_share", "popping_share", "render_ms", "flip_mean",
            "flip_model_mean", "fidelity_ms"} <= set(rows[0])
    assert float(rows[0]["popping_share"]) == 0.0
    # FLIP over the model's pixels exceeds FLIP over the image (the background matches).
    assert all(0 < float(r["flip_mean"]) < float(r["flip_model_mean"]) < 0.5 for r in rows)
    assert all(float(r["fidelity_ms"]) > float(r["render_ms"]) for r in rows)
    assert "FLIP over the model's pixels median" in r.stdout and "measuring cost median" in r.stdout
    assert all(0 <= float(r["differing_share"]) < 0.5 for r in rows)
    assert all(0 < float(r["silhouette_share"]) < 0.5 for r in rows)


@pytest.mark.skipif(not (shutil.which("Xvfb") and shutil.which("xdotool")), reason="needs Xvfb and xdotool")
@pytest.mark.slow
def test_viewer_in_a_real_window_reacts_to_keys(cow, tmp_path, xvfb_display):
    from PIL import ImageGrab

    path, _, _ = cow
    saved = tmp_path / "seen.json"
    display = xvfb_display
    env = dict(os.environ, DISPLAY=display)
    env.pop("PYOPENGL_PLATFORM", None)  # the viewer needs the X display, not EGL
    viewer = None
    try:
        viewer = subprocess.Popen([sys.executable, "-m", "pmjax", "view", path, "--size", "400", "300",
                                   "--close-after", "90", "--camera-file", str(saved)], env=env,
                                  stderr=subprocess.PIPE, text=True)

        def window():
            r = subprocess.run(["xdotool", "search", "--name", "pmjax view"], env=env, capture_output=True,
                               text=True)
            return r.stdout.split()

        def shot():
            return np.asarray(ImageGrab.grab(xdisplay=display)).astype(int)[:300, :400]

        start = time.time()
        while not window():
            assert viewer.poll() is None, viewer.stderr.read()
            assert time.time() - start < 60, "no viewer window"
            time.sleep(0.5)
        # wait until the model is drawn (white background, grey model)
        while (shot().sum(-1) < 700).mean() < 0.05:
            assert time.time() - start < 60, "model never appeared"
            time.sleep(0.5)
        time.sleep(1.0)
        before = shot()
        assert 0.05 < (before.sum(-1) < 700).mean() < 0.8
        subprocess.run(["xdotool", "key", "--window", window()[0], "e"], env=env, check=True)
        deadline = time.time() + 20
        while True:
            after = shot()
            changed = (np.abs(after - before).max(-1) > 40).sum()
            if changed > 1000 or time.time() > deadline:
                break
            time.sleep(0.5)
        # the wireframe overlay darkens the edges of the model
        assert changed > 1000
        assert (after.sum(-1) < 200).sum() > (before.sum(-1) < 200).sum() + 150
        # 'c' saves the current camera: the viewer's start view, 400 x 300
        subprocess.run(["xdotool", "key", "--window", window()[0], "c"], env=env, check=True)
        deadline = time.time() + 20
        while not saved.exists() and time.time() < deadline:
            time.sleep(0.3)
        cam = pmjax.load_cameras(saved)
        assert (int(cam.width[0]), int(cam.height[0])) == (400, 300)
    finally:
        if viewer is not None:
            viewer.terminate()
            viewer.wait(10)


@pytest.mark.slow
def test_render_refuses_an_unknown_video_format(cow, tmp_path):
    path, _, _ = cow
    out = tmp_path / "orbit.avi"
    r = subprocess.run([sys.executable, "-m", "pmjax", "render", path, "--orbit", "3", "-o", str(out), "-q"],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "must be .mp4, .gif or a directory" in r.stderr
    assert not out.exists() and not list(tmp_path.glob("*" + TEMP_MARK + "*"))


@pytest.mark.slow
def test_geomorph_spreads_a_refinement_change(cow, renderer):
    """At a fixed camera, a jump from tau 0.5 to tau 6 rendered at once vs blended
    over 4 frames: every blended step changes the image less than the jump, and
    the squared change summed over the steps is smaller too (the same change
    spread over frames)."""
    from pmjax.render import image_difference
    from pmjax.render._offscreen import refined_arrays, shading_normals

    _, pm, data = cow
    cam = _camera(data)
    fine, coarse = pmjax.refine(pm, cam, 0.5), pmjax.refine(pm, cam, 6.0)

    def draw(v, f, _, n):
        return renderer.render_mesh(v, f, cam, normals=n)

    jump = image_difference(*draw(*refined_arrays(pm, fine)), *draw(*refined_arrays(pm, coarse)))
    assert jump["differing"] > 100
    state, previous, steps = pmjax.geomorph_start(fine.executed), draw(*refined_arrays(pm, fine)), []
    for _ in range(4):
        state = pmjax.geomorph_step(pm, state, coarse.executed, 4)
        current = draw(*pmjax.geomorph_mesh(pm, state, shading_normals(pm)))
        steps.append(image_difference(*previous, *current))
        previous = current
    assert np.array_equal(previous[0], draw(*refined_arrays(pm, coarse))[0])  # arrived
    assert all(s["mse"] < jump["mse"] for s in steps)
    assert sum(s["mse"] for s in steps) < jump["mse"]


@pytest.mark.slow
def test_render_and_path_with_geomorphs(cow, tmp_path):
    path, _, _ = cow
    out = tmp_path / "stats.csv"
    r = subprocess.run([sys.executable, "-m", "pmjax", "path", path, "--orbit", "5", "--fidelity", "--geomorph", "4",
                        "--csv", str(out), "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 5 and float(rows[0]["popping_mse"]) == 0.0 and float(rows[1]["popping_mse"]) > 0.0
    r = subprocess.run([sys.executable, "-m", "pmjax", "path", path, "--orbit", "2", "--fidelity", "--supersample", "0",
                        "-q"], capture_output=True, text=True)
    assert r.returncode == 2 and "argument --supersample: 0 is out of range" in r.stderr
    gif = tmp_path / "g.gif"
    r = subprocess.run([sys.executable, "-m", "pmjax", "render", path, "--orbit", "5", "--geomorph", "4", "-o",
                        str(gif), "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    import imageio.v2 as imageio

    assert len(list(imageio.get_reader(str(gif)))) == 5


def test_float_color_is_the_unrounded_supersampled_render(cow):
    """``float_color`` keeps the box average of the samples: rounding it gives the
    8-bit render exactly, and it holds fractional levels (edge pixels partly
    covered), which is what lets popping see sub-level changes."""
    from pmjax.render import Renderer
    from pmjax.render._offscreen import original_arrays

    _, pm, data = cow
    cam = _camera(data)
    v, f, n = original_arrays(pm)
    with Renderer(320, 240, 2) as r8:
        rgb8, depth8 = r8.render_mesh(v, f, cam, normals=n)
    with Renderer(320, 240, 2, float_color=True) as rf:
        rgbf, depthf = rf.render_mesh(v, f, cam, normals=n)
    assert rgb8.dtype == np.uint8 and rgbf.dtype == np.float32
    assert np.array_equal(np.round(rgbf).astype(np.uint8), rgb8) and np.array_equal(depth8, depthf)
    assert 0.0 <= rgbf.min() and rgbf.max() <= 255.0
    assert np.any(rgbf != np.round(rgbf))  # some pixels are between levels


def test_path_geometry_refuses_a_bad_tau(cow):
    """With geomorphs the path skips refine (one critical-tolerance pass per
    frame), so it checks tau itself, before any frame."""
    from pmjax.render._offscreen import path_geometry

    _, pm, data = cow
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 3)
    for tau in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="tau must be >= 0"):
            next(path_geometry(pm, cams, tau, geomorph=4))


def test_refinements_drawn_with_an_eye_get_the_per_view_fit(cow, renderer):
    """With an eye a refinement's arrays are its own vertices and faces, shaded
    with :class:`pmjax.ViewNormals` of the stored normals seen from there
    (originals keep theirs); render_refinement draws them from its camera,
    or the stored normals when asked; the original is drawn as before."""
    from pmjax.render import original_arrays, refined_arrays, render_refinement
    from pmjax.render._offscreen import shading_normals

    _, pm, data = cow
    V0 = data.n_original_vertices
    cam = _camera(data, 3)
    refinement = pmjax.refine(pm, cam, 1.0)
    v, f, ids = refinement.mesh(pm)
    eye = np.asarray(cam.eye)
    stored = refined_arrays(pm, refinement)
    seen = refined_arrays(pm, refinement, eye=eye)
    for a, b in zip(stored[:2], seen[:2]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(stored[3], shading_normals(pm)[ids])
    expected = pmjax.ViewNormals(pm, shading_normals(pm))(ids, f, eye=eye)
    assert seen[3].tobytes() == expected.tobytes()
    created = np.asarray(ids) >= V0
    np.testing.assert_array_equal(seen[3][~created], stored[3][~created])
    assert np.abs(seen[3][created] - stored[3][created]).max() > 1e-2
    np.testing.assert_array_equal(original_arrays(pm)[2], shading_normals(pm)[:V0])
    by_view, _ = render_refinement(renderer, pm, refinement, cam)
    by_stored, _ = render_refinement(renderer, pm, refinement, cam, normals="stored")
    np.testing.assert_array_equal(by_view, renderer.render_mesh(v, f, cam, normals=seen[3])[0])
    np.testing.assert_array_equal(by_stored, renderer.render_mesh(v, f, cam, normals=stored[3])[0])
    assert (by_view != by_stored).any()


def test_a_bad_normals_choice_is_refused(cow, renderer, tmp_path):
    from pmjax.render import paper_figures, path_fidelity, render_path, render_refinement

    _, pm, data = cow
    cam = _camera(data)
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 2, width=64, height=48)
    with pytest.raises(ValueError, match="normals must be one of"):
        render_refinement(renderer, pm, pmjax.refine(pm, cam, 1.0), cam, normals="fitted")
    with pytest.raises(ValueError, match="normals must be one of"):
        path_fidelity(pm, cams, 1.0, normals="hierarchy", flip=False)
    with pytest.raises(ValueError, match="normals must be one of"):
        render_path(pm, cams, 1.0, str(tmp_path / "out.gif"), normals=None, progress=False)
    with pytest.raises(ValueError, match="normals must be one of"):
        paper_figures(pm, str(tmp_path / "figures"), normals="View")


def test_path_fidelity_with_stored_normals_draws_the_same_faces(cow, tmp_path):
    """``pmjax path --fidelity --stored-normals``: the same faces and
    silhouettes as with the normals fitted per view, other shading."""
    path, _, _ = cow
    rows = {}
    for flag in ([], ["--stored-normals"]):
        out = tmp_path / f"stats{len(flag)}.csv"
        r = subprocess.run([sys.executable, "-m", "pmjax", "path", path, "--orbit", "3", "--fidelity", "--csv",
                            str(out), "-q", *flag], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        rows[len(flag)] = list(csv.DictReader(open(out)))
    for view, stored in zip(rows[0], rows[1], strict=True):
        assert view["faces"] == stored["faces"] and view["silhouette_share"] == stored["silhouette_share"]
    assert any(v["differing_share"] != s["differing_share"] for v, s in zip(rows[0], rows[1]))
