"""NVIDIA's FLIP in the fidelity measures: zero for identical images, growing
with a perturbation, over the model's pixels, and a clear error without the
package."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import pmjax


def _render(data, renderer, normals=None):
    from pmjax.render import original_arrays

    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = pmjax.index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4,
                                                  width=renderer.width, height=renderer.height), 1)
    v, f, n = original_arrays(pm)
    return renderer.render_mesh(v, f, cam, normals=n if normals is None else normals), n


def test_flip_is_zero_for_identical_images_and_grows_with_a_perturbation(built):
    from pmjax.render import Renderer, flip_difference

    data = built("cow.ply")
    with Renderer(160, 120, 2, True) as r:
        (rgb, depth), n = _render(data, r)
        same = flip_difference(rgb, depth, rgb, depth)
        assert same == dict(flip_mean=0.0, flip_model_mean=0.0)
        rng = np.random.default_rng(0)
        errors = []
        for noise in (0.05, 0.3):
            bent = n + rng.normal(0.0, noise, n.shape).astype(np.float32)
            bent /= np.linalg.norm(bent, axis=1, keepdims=True)
            (other, other_depth), _ = _render(data, r, bent)
            errors.append(flip_difference(rgb, depth, other, other_depth))
    assert 0 < errors[0]["flip_model_mean"] < errors[1]["flip_model_mean"]
    # Only the model's pixels change: FLIP's filters spread a little error onto
    # the background next to them, so the image mean lies between the model
    # mean times the model's share and the model mean.
    share = ((depth > 0) | (other_depth > 0)).mean()
    model_part = errors[1]["flip_model_mean"] * share
    assert model_part <= errors[1]["flip_mean"] < min(1.2 * model_part, errors[1]["flip_model_mean"])


def test_flip_refuses_different_shapes():
    from pmjax.render import flip_difference

    a = np.zeros((4, 5, 3), np.uint8)
    with pytest.raises(ValueError, match=r"image shapes differ: \(4, 5, 3\) vs \(5, 4, 3\)"):
        flip_difference(a, a[..., 0], np.zeros((5, 4, 3), np.uint8), a[..., 0])


def test_missing_package_is_named(monkeypatch, built):
    from pmjax.render import path_fidelity

    monkeypatch.setitem(sys.modules, "flip_evaluator", None)
    data = built("cow.ply")
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 2, width=64, height=48)
    with pytest.raises(RuntimeError, match=r"FLIP needs the flip-evaluator package .*pip install flip-evaluator"):
        path_fidelity(pmjax.ProgressiveMesh.from_data(data), cams, 1.0)
    # Without FLIP the other columns are measured.
    rows = path_fidelity(pmjax.ProgressiveMesh.from_data(data), cams, 1.0, flip=False)
    assert len(rows) == 2 and "flip_mean" not in rows[0] and rows[0]["differing_share"] >= 0


def test_flip_of_the_model_box_equals_flip_of_the_whole_image(built):
    """The crop to the model's box plus the margin changes no pixel's FLIP."""
    import flip_evaluator

    from pmjax.render import Renderer, flip_difference

    data = built("cow.ply")
    with Renderer(400, 300, 1, True) as r:
        (rgb, depth), n = _render(data, r)
        bent = n + np.random.default_rng(1).normal(0.0, 0.2, n.shape).astype(np.float32)
        bent /= np.linalg.norm(bent, axis=1, keepdims=True)
        (other, other_depth), _ = _render(data, r, bent)
    from pmjax.render._fidelity import FLIP_MARGIN

    rows, cols = np.flatnonzero((depth > 0).any(axis=1)), np.flatnonzero((depth > 0).any(axis=0))
    box = (rows[-1] - rows[0] + 1 + 2 * FLIP_MARGIN) * (cols[-1] - cols[0] + 1 + 2 * FLIP_MARGIN)
    assert box < 0.8 * depth.size and rows[0] > FLIP_MARGIN and cols[0] > FLIP_MARGIN  # a real crop
    full = flip_evaluator.evaluate(rgb / 255.0, other / 255.0, "LDR", applyMagma=False)[0][..., 0]
    model = (depth > 0) | (other_depth > 0)
    got = flip_difference(rgb, depth, other, other_depth)
    assert got["flip_mean"] == pytest.approx(float(full.mean(dtype=np.float64)), rel=1e-6)
    assert got["flip_model_mean"] == pytest.approx(float(full[model].mean(dtype=np.float64)), rel=1e-6)
