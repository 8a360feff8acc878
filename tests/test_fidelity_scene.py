"""path_fidelity's renders from one scene whose meshes stay on the GPU, and the
block average of supersampled renders: every column equal, bit for bit, to the
same metrics from separate plain renders of the same arrays."""

from __future__ import annotations

import numpy as np
import pytest

import pmjax


def test_block_average_equals_the_strided_mean_and_nearest_depth():
    from pmjax.render._offscreen import block_average

    rng = np.random.default_rng(3)
    for s in (1, 2, 3, 4):
        H, W = 30, 40
        color = rng.integers(0, 256, (H * s, W * s, 3), dtype=np.uint8)
        depth = np.where(rng.random((H * s, W * s)) < 0.6, 0.0, rng.random((H * s, W * s)) * 9 + 0.1)
        depth = depth.astype(np.float32)
        depth[: 5 * s] = 0.0  # whole empty blocks
        mean, nearest = block_average(color, depth, s)
        reference = color.reshape(H, s, W, s, 3).mean(axis=(1, 3), dtype=np.float32)
        blocks = np.where(depth > 0, depth, np.inf).reshape(H, s, W, s).min(axis=(1, 3))
        assert mean.dtype == np.float32 and nearest.dtype == np.float32
        assert np.array_equal(mean.view(np.uint32), reference.view(np.uint32))
        assert np.array_equal(nearest, np.where(np.isfinite(blocks), blocks, 0.0).astype(np.float32))
        assert (nearest == 0).sum() > 0  # empty blocks are present and read 0


def _reference_rows(pm, cams, tau, normals="view"):
    """path_fidelity's columns from separate render_mesh calls per image
    (the refinements shaded with normals fitted on the mesh drawn, seen from
    its camera, or with the stored ones)."""
    from pmjax.render import Renderer, flip_difference, image_difference, original_arrays, refined_arrays
    from pmjax.render import silhouette_difference

    ov, of, on = original_arrays(pm)
    rows, previous = [], None
    first = pmjax.index_camera(cams, 0)
    with Renderer(int(first.width), int(first.height), 2, True) as r:
        for i, refined in enumerate(pmjax.refine_path(pm, cams, tau)):
            cam = pmjax.index_camera(cams, i)
            v, f, _, n = refined_arrays(pm, refined, eye=np.asarray(cam.eye) if normals == "view" else None)
            rgb, depth = r.render_mesh(v, f, cam, normals=n)
            reference = r.render_mesh(ov, of, cam, normals=on)
            row = image_difference(*reference, rgb, depth)
            row.update(flip_difference(*reference, rgb, depth))
            row["silhouette_share"] = silhouette_difference(r, (ov, of), (v, f), cam)["differing_share"]
            row.update(popping_share=0.0, popping_mse=0.0)
            if previous is not None:
                pop = image_difference(*r.render_mesh(*previous[:2], cam, normals=previous[2]), rgb, depth)
                row.update(popping_share=pop["differing_share"], popping_mse=pop["mse"])
            previous = (v, f, n)
            rows.append(row)
    return rows


@pytest.mark.parametrize("normals", ["view", "stored"])
def test_path_fidelity_equals_separate_renders(cow, normals):
    from pmjax.render import path_fidelity

    pm = pmjax.load(cow)
    cams = pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], 4, width=200, height=150)
    got = path_fidelity(pm, cams, 1.0, normals=normals)
    want = _reference_rows(pm, cams, 1.0, normals)
    keys = ("model_pixels", "differing", "differing_share", "mse", "psnr", "flip_mean", "flip_model_mean",
            "silhouette_share", "popping_share", "popping_mse")
    for g, w in zip(got, want, strict=True):
        assert {k: g[k] for k in keys} == {k: w[k] for k in keys}
    # The frames differ from the original and from each other: the columns can tell.
    assert all(g["differing"] > 0 for g in got) and any(g["popping_share"] > 0 for g in got[1:])
    assert any(g["silhouette_share"] > 0 for g in got)


def test_camera_fidelity_keeps_the_original_across_calls_and_follows_a_new_one(cow):
    """A second original (another tuple) is drawn, not the first one's buffers."""
    from pmjax.render import Renderer, camera_fidelity, image_difference, original_arrays, refined_arrays

    pm = pmjax.load(cow)
    cam = pmjax.index_camera(pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], 3,
                                                  width=160, height=120), 1)
    ov, of, on = original_arrays(pm)
    v, f, _, n = refined_arrays(pm, pmjax.refine(pm, cam, 2.0))
    with Renderer(160, 120, 2, True) as r:
        first, _ = camera_fidelity(r, (ov, of, on), (v, f, n), cam, flip=False)
        again, _ = camera_fidelity(r, (ov, of, on), (v, f, n), cam, flip=False)
        moved = (ov + np.float32(0.05) * (ov.max(0) - ov.min(0)), of, on)
        other, _ = camera_fidelity(r, moved, (v, f, n), cam, flip=False)
        want = image_difference(*r.render_mesh(*moved[:2], cam, normals=on), *r.render_mesh(v, f, cam, normals=n))
    drop = ("render_ms",)
    assert {k: x for k, x in first.items() if k not in drop} == {k: x for k, x in again.items() if k not in drop}
    assert other["differing"] == want["differing"] != first["differing"]
    assert other["mse"] == want["mse"]


def test_image_difference_counts_as_the_channel_maximum():
    """Differing pixels: the largest channel difference over the threshold,
    on the model's pixels, for float and 8-bit renders."""
    from pmjax.render import image_difference

    rng = np.random.default_rng(5)
    a = rng.random((40, 50, 3), dtype=np.float32) * 255
    b = np.clip(a + rng.normal(0, 8, a.shape).astype(np.float32), 0, 255)
    depth_a = np.where(rng.random((40, 50)) < 0.4, 1.0, 0.0).astype(np.float32)
    depth_b = np.where(rng.random((40, 50)) < 0.4, 2.0, 0.0).astype(np.float32)
    for x, y in ((a, b), (a.round().astype(np.uint8), b.round().astype(np.uint8))):
        diff = np.abs(x.astype(np.float32) - y.astype(np.float32))
        model = (depth_a > 0) | (depth_b > 0)
        got = image_difference(x, depth_a, y, depth_b)
        assert got["differing"] == int(((diff.max(axis=-1) > 8) & model).sum()) > 0
        assert got["mse"] == float((diff[model].astype(np.float64) ** 2).mean())
        assert got["model_pixels"] == int(model.sum())


def test_renders_read_back_as_pyrender_reads_them(cow):
    """The renderer's read of colour and depth equals pyrender's own, bit for
    bit, for a perspective and an orthographic view with empty pixels."""
    from pmjax.render import Renderer, original_arrays
    from pmjax.render._scene import build_scene

    pm = pmjax.load(cow)
    ov, of, on = original_arrays(pm)
    cams = pmjax.standard_orbit(np.asarray(ov), 2, width=160, height=120)
    with Renderer(160, 120, 1) as r:
        gl = r._gl
        assert "_read_main_framebuffer" in vars(gl._renderer)  # the elementwise read is installed
        c = pmjax.index_camera(cams, 0)
        extent = float(np.ptp(np.asarray(ov), axis=0).max())
        ortho = pmjax.Camera(c.eye, c.rotation, c.fov_y, c.near, c.far, 1.5 * extent, 160, 120, orthographic=True)
        for cam in (pmjax.index_camera(cams, 1), ortho):
            scene, _ = build_scene(ov, of, cam, normals=on)
            color, depth = gl.render(scene)
            own = vars(gl._renderer).pop("_read_main_framebuffer")
            try:
                want_color, want_depth = gl.render(scene)
            finally:
                gl._renderer._read_main_framebuffer = own
            assert np.array_equal(color, want_color)
            assert depth.dtype == want_depth.dtype == np.float32
            assert np.array_equal(depth.view(np.uint32), want_depth.view(np.uint32))
            assert (depth == 0).any() and (depth > 0).any()


def test_fidelity_scene_outlives_a_closed_renderer_handle(cow):
    """Renderer handles of one size share a context: a new handle after the
    first is closed finds the same scene (the original is not uploaded
    again), and its rows equal the first handle's."""
    from pmjax.render import Renderer, camera_fidelity, original_arrays, refined_arrays
    from pmjax.render._fidelity import FidelityScene

    pm = pmjax.load(cow)
    cam = pmjax.index_camera(pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], 3,
                                                  width=96, height=72), 2)
    original = original_arrays(pm)
    v, f, _, n = refined_arrays(pm, pmjax.refine(pm, cam, 2.0))
    with Renderer(96, 72, 2, True) as r:
        first, _ = camera_fidelity(r, original, (v, f, n), cam, flip=False)
        scene = FidelityScene.of(r, original)
    with Renderer(96, 72, 2, True) as r2:
        again, _ = camera_fidelity(r2, original, (v, f, n), cam, flip=False, popping=True)
        assert FidelityScene.of(r2, original) is scene
    assert again.pop("popping_share") == 0.0 and again.pop("popping_mse") == 0.0  # the same mesh as before
    first.pop("render_ms"), again.pop("render_ms")
    assert first == again
