"""Soft refinement: the three tests as smooth margins, differentiable (docs/soft.md).

Each hard test ``a > b`` becomes ``sigmoid((a − b) / (s · T))``: the margin
``a − b`` is the very difference the hard test compares (same float
expressions, so its sign is exact), ``s`` converts it to pixels and ``T`` is
the temperature in pixels. As ``T → 0`` every sigmoid becomes the hard
decision and the soft result equals :func:`pmjax.refine`'s.

The dtype follows the mesh: float32 for speed, float64 (``pm.astype``) for
gradient checks.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._arguments import check_camera, check_mesh
from ._camera import Camera
from ._model import PcolAttributes, ProgressiveMesh
from ._predicate import (ALL_TESTS, Tests, _eye_offset, frustum_margins, in_row_parts, join_row_parts, safe_sqrt,
                         view_screen_tolerance)
from ._scalars import host_number, host_tau
from ._units import in_model_units
from ._view import View
from .engines._dense import down_the_batches, up_the_batches


class SoftRefinement(eqx.Module):
    """A soft (differentiable) refinement for one view.

    Attributes:
        collapse: ``[P]`` soft collapse decision of each pcol's own tests.
        visible: ``[P]`` soft "neither outside the frustum nor facing away".
        weight: ``[P]`` soft executed: ``collapse`` times the weights of the
            pcols that made its two vertices (1 for original vertices).
        positions: ``[V0, 3]`` geomorphed position of every original vertex.
        face_weight: ``[F]`` soft "face is drawn": ``1 − weight[killer]``.
        faces: soft face count, ``Σ face_weight``.
        error: soft screen-space error in pixels: ``Σ_p weight·visible·t_p``,
            the summed deviation of the executed, visible collapses.
    """

    collapse: Float[Array, " P"]
    visible: Float[Array, " P"]
    weight: Float[Array, " P"]
    positions: Float[Array, "V0 3"]
    face_weight: Float[Array, " F"]
    faces: Float[Array, ""]
    error: Float[Array, ""]


def _above(margin, unit, temperature):
    """Soft ``margin > 0`` for a margin measured in ``unit`` per pixel."""
    return jax.nn.sigmoid(margin / (unit * temperature))


def soft_tests(attrs: PcolAttributes, camera: Camera, tau, temperature, scale=None, tests: Tests = ALL_TESTS):
    """Per pcol ``(collapse, visible, t_p)`` as smooth functions of the view.

    Margins are converted to pixels before the temperature applies: a world
    distance at the pcol by ``d·κ₁`` (one pixel at distance ``d``), an angle
    (cosine difference) by ``κ₁`` (one pixel's angle), so one temperature
    serves all three tests. ``κ₁ = 2 tan(φ/2) / H``.

    Args:
        attrs: :class:`PcolAttributes` (``[3, P]``, ``[P]`` rows; or row views).
        camera: one perspective :class:`Camera`.
        tau: tolerance, pixels.
        temperature: ``T`` in pixels (> 0).
        scale: ``[P]`` per-pcol factors on ``tau`` (per-region tolerances), or None.
        tests: :class:`Tests`.

    Returns:
        ``(collapse, visible, t_p)``, each shaped like ``attrs.radius``.

    Raises:
        TypeError, ValueError: a camera that is not one perspective camera,
            a ``tau`` or ``temperature`` that is not one number (``tau >= 0``,
            ``temperature > 0``; traced values: their shapes).
    """
    tau, temperature = _checked_view(camera, tau, temperature, "soft_tests")
    attrs, camera = in_model_units(attrs, camera)
    return soft_tests_in_model_units(attrs, camera, tau, temperature, scale, tests)


def _checked_view(camera, tau, temperature, call: str):
    """The view arguments of a soft call: one perspective camera, ``tau >= 0``
    and ``temperature > 0`` pixels (host values checked and returned as
    float32, traced ones shape-checked and passed on)."""
    check_camera(camera, call, batch=False)
    if camera.orthographic:
        raise ValueError(f"{call} supports perspective cameras only")
    tau = host_tau(tau, call)
    return tau, host_number(temperature, "temperature", call, lambda t: t > 0, "> 0 pixels (not NaN)")


def soft_tests_in_model_units(attrs, camera, tau, temperature, scale, tests):
    """:func:`soft_tests` with ``attrs`` and ``camera`` already in model units."""
    view = View.of(camera, 0.0)
    one_px = view.one_pixel
    d2, h = _eye_offset(attrs, view)
    d = safe_sqrt(d2)
    r = attrs.radius
    visible = jnp.ones_like(r)
    if tests.frustum:
        # The hard test's comparisons (pmjax.outside_frustum), each made soft;
        # inside all six planes is a product. Side margins are in units of l.
        x, y, z, sx, sy, lx, ly, near, far = frustum_margins(attrs, view)
        unit = d * one_px
        outside = [
            _above(near - (z + r), unit, temperature),
            _above((z - r) - far, unit, temperature),
            _above(-r * lx - (sx - x), unit * lx, temperature),
            _above(-r * lx - (sx + x), unit * lx, temperature),
            _above(-r * ly - (sy - y), unit * ly, temperature),
            _above(-r * ly - (sy + y), unit * ly, temperature),
        ]
        for o in outside:
            visible = visible * (1.0 - o)
    if tests.orientation:
        # The three conditions of pmjax.oriented_away (same expressions), ANDed.
        sa, ca = attrs.sin_alpha, attrs.cos_alpha
        tangent = safe_sqrt(jnp.maximum(d2 - r * r, 0.0))
        away = (
            _above(d2 - r * r, d2 * one_px, temperature)
            * _above(ca * tangent - sa * r, d * one_px, temperature)
            * _above(h - (sa * tangent + ca * r), d * one_px, temperature)
        )
        visible = visible * (1.0 - away)
    t = view_screen_tolerance(attrs, view, safe_sqrt)
    collapse = 1.0 - visible
    if tests.screen:
        limit = tau if scale is None else tau * scale
        collapse = 1.0 - visible * (1.0 - _above(limit - t, 1.0, temperature))
    return collapse, visible, t


def soft_weights(pm: ProgressiveMesh, collapse: Float[Array, " P"]) -> Float[Array, " P"]:
    """Soft executed: each pcol's collapse times its children's weights.

    Args:
        pm: :class:`ProgressiveMesh`.
        collapse: ``[P]`` soft collapse decision of each pcol's own tests in
            [0, 1] (:class:`SoftRefinement`'s ``collapse``); ``[P, K]`` for
            K cameras on the trailing axis.

    Returns:
        ``[P]`` (or ``[P, K]``) soft executed weights in [0, 1]: the product
        of the collapse values of the pcol and of every pcol below it in the
        hierarchy.
    """
    return up_the_batches(pm, collapse, 1.0, lambda own, a, b: own * a * b)


def soft_face_count(pm: ProgressiveMesh, weight: Float[Array, "P *K"]) -> Float[Array, "*K"]:
    """Soft face count from soft executed weights ``[P]`` (or ``[P, K]``, K
    cameras on the trailing axis): the faces no pcol kills plus each pcol's
    kills times ``1 − weight``."""
    # Sum the survivors, not F minus the collapsed: no cancellation in float32.
    kills = pm.kills.reshape(pm.kills.shape + (1,) * (weight.ndim - 1))
    return (pm.n_faces - jnp.sum(pm.kills)) + jnp.sum(kills * (1.0 - weight), axis=0)


def geomorph_blend(pm: ProgressiveMesh, weight: Float[Array, " P"], values: Float[Array, "V k"]):
    """Blend a per-vertex attribute along every vertex's ancestor chain.

    ``value(v) + Σ_k w(a_k)·(value(a_k) − value(a_{k−1}))`` over the chain
    ``a_0 = v, a_1, …`` of vertices made by the pcols consuming them (docs/soft.md).
    With the 0/1 weights of an executed set this is the value of ``v``'s
    representative; in between, a straight blend toward it.

    Args:
        weight: ``[P]`` per-pcol weights in [0, 1].
        values: ``[V0 + P, k]`` per-vertex values (positions, normals, ...).

    Returns:
        ``[V0 + P, k]`` blended values of every vertex.
    """
    V0 = pm.n_original_vertices
    if pm.n_pcols == 0:  # nothing to blend toward
        return values

    # offset(u) = w(p)·(value(p) − value(u)) + offset(p) for p = the pcol
    # consuming u: the step to the parent for all vertices at once, then its
    # sum down the hierarchy.
    parent = pm.parent
    up = jnp.maximum(parent, 0)
    step = weight[up][:, None] * (values[V0 + up] - values)
    offset = down_the_batches(pm, step, lambda own, t, has_parent: jnp.where(has_parent, own + t, 0.0))
    return values + offset


def geomorph_positions(pm: ProgressiveMesh, weight: Float[Array, " P"]) -> Float[Array, "V0 3"]:
    """Blended positions of the original vertices (:func:`geomorph_blend` of
    the vertex positions): with the 0/1 weights of an executed set, the
    position of each vertex's representative.

    Args:
        pm: :class:`ProgressiveMesh`.
        weight: ``[P]`` per-pcol weights in [0, 1] (:class:`SoftRefinement`'s
            ``weight``, or an executed set as 0/1 values).

    Returns:
        ``[V0, 3]`` positions of the original vertices, world units (the
        dtype of ``pm.vertices``).
    """
    return geomorph_blend(pm, weight, pm.vertices)[: pm.n_original_vertices]


def soft_refine(
    pm: ProgressiveMesh,
    camera: Camera,
    tau=1.0,
    temperature=0.1,
    scale: Optional[Float[Array, " P"]] = None,
    tests: Tests = ALL_TESTS,
) -> SoftRefinement:
    """Refine ``pm`` softly for one view; differentiable in every array input.

    Pure JAX: compose with ``jax.grad`` (eye, rotation, fov, ``tau``,
    ``scale``, ``temperature``), ``jax.vmap`` (cameras) and ``jax.jit``.

    Args:
        pm: :class:`ProgressiveMesh`; its dtype is the computation's.
        camera: one perspective :class:`Camera`.
        tau: tolerance, pixels of the image height.
        temperature: softness ``T`` in pixels (``→ 0``: the hard refinement).
        scale: optional ``[P]`` finite factors on ``tau`` per pcol (per region:
            gather a per-region array by each pcol's region id).
        tests: :class:`Tests` (ablations).

    Returns:
        :class:`SoftRefinement`.
    """
    check_mesh(pm, "soft_refine")
    tau, temperature = _checked_view(camera, tau, temperature, "soft_refine")
    scale = _checked_scale(pm, scale)
    # Arrays, not Python floats, so a new value does not recompile.
    dtype = pm.attributes.radius.dtype
    tau, temperature = jnp.asarray(tau, dtype), jnp.asarray(temperature, dtype)
    return _soft_refine_checked(pm, camera, tau, temperature, scale, tests)


def _checked_scale(pm, scale):
    """``scale`` is None or ``[P]`` finite numbers: checked on the host, or,
    traced, inside the compiled call (``eqx.error_if``)."""
    if scale is None:
        return None
    P = pm.n_pcols
    if np.shape(scale) != (P,):
        raise ValueError(f"soft_refine: scale must be [P] = [{P}] factors on tau, one per pcol, "
                         f"got shape {list(np.shape(scale))}")
    if isinstance(scale, jax.core.Tracer):
        return eqx.error_if(scale, ~jnp.all(jnp.isfinite(scale)), "soft_refine: scale must be finite")
    host = np.asarray(scale)
    if host.dtype.kind not in "iuf":
        raise TypeError(f"soft_refine: scale must be numbers, got dtype {host.dtype}")
    bad = np.flatnonzero(~np.isfinite(host))
    if bad.size:
        raise ValueError(f"soft_refine: scale must be finite, got {host[bad[0]]} at pcol {bad[0]} "
                         f"({bad.size} of {P} not finite)")
    return scale


def _soft_refine_checked(pm, camera, tau, temperature, scale, tests):
    # Two programs: the tests' row-shaped outputs are joined in the second, so
    # XLA cannot fuse the tests into the joins (1-D, not vectorized). Under a
    # caller's jit both are inlined; what the caller keeps decides then.
    parts = _soft_test_parts(pm, camera, tau, temperature, scale, tests)
    return _soft_refine_from_parts(pm, parts)


@eqx.filter_jit
def _soft_test_parts(pm, camera, tau, temperature, scale, tests):
    temperature = eqx.error_if(temperature, ~(temperature > 0), "temperature must be > 0")
    tau = eqx.error_if(tau, ~(tau >= 0), "tau must be >= 0 (and not NaN)")
    return _test_parts(pm, camera, tau, temperature, scale, tests)


@eqx.filter_jit
def _soft_refine_from_parts(pm, parts):
    return _from_tests(pm, *join_row_parts(parts))


def _test_parts(pm, camera, tau, temperature, scale, tests):
    dtype = pm.attributes.radius.dtype
    tau = jnp.asarray(tau, dtype)
    temperature = jnp.asarray(temperature, dtype)
    attrs, camera = in_model_units(pm.attributes, camera)
    if scale is None:
        return in_row_parts(lambda a: soft_tests_in_model_units(a, camera, tau, temperature, None, tests), attrs)
    return None, soft_tests_in_model_units(attrs, camera, tau, temperature, jnp.asarray(scale, dtype), tests)


def soft_refine_unchecked(pm, camera, tau, temperature, scale=None, tests: Tests = ALL_TESTS) -> SoftRefinement:
    """:func:`soft_refine` without the argument checks (for solvers, whose
    trial points may be anything; a bad one gives NaN in its own lane instead
    of an error for the whole batch)."""
    return _from_tests(pm, *join_row_parts(_test_parts(pm, camera, tau, temperature, scale, tests)))


def _from_tests(pm, collapse, visible, t) -> SoftRefinement:
    """The soft refinement from the per-pcol soft tests."""
    weight = soft_weights(pm, collapse)
    killer = pm.killer
    if pm.n_pcols == 0:  # every face drawn, fully
        face_weight = jnp.ones(killer.shape, weight.dtype)
    else:
        face_weight = jnp.where(killer < 0, 1.0, 1.0 - weight[jnp.maximum(killer, 0)])
    return SoftRefinement(
        collapse=collapse,
        visible=visible,
        weight=weight,
        positions=geomorph_positions(pm, weight),
        face_weight=face_weight,
        faces=soft_face_count(pm, weight),
        error=jnp.sum(weight * visible * t),
    )
