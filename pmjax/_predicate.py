"""The three refinement tests of docs/design.md, one vectorized predicate over pcols.

``collapse_mask`` (``view_collapse_mask`` for a :class:`View`) is THE
definition of "this pcol may be collapsed for this view": the engine and the
sequential oracle both call it, so they cannot disagree on float ties.
Everything is float32 (the speed path). The tests see lengths in model units
(:mod:`pmjax._units`): every function here that takes attributes and a camera
brings both to them, so results do not depend on the model's scale.
"""

from __future__ import annotations

from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._arguments import check_camera
from ._camera import Camera
from ._model import PcolAttributes
from ._scalars import checked_tau
from ._units import in_model_units
from ._view import View, kappa_squared


class Tests(eqx.Module):
    """Which tests may collapse a pcol (ablations switch them off).

    Attributes:
        frustum: sphere entirely outside one of the six frustum planes.
        orientation: whole normal cone faces away from the eye.
        screen: screen-space deviation below ``tau`` pixels.
    """

    frustum: bool = eqx.field(static=True, default=True)
    orientation: bool = eqx.field(static=True, default=True)
    screen: bool = eqx.field(static=True, default=True)


ALL_TESTS = Tests()

# A user predicate: (attributes, context) -> bool[P]; True = may collapse.
UserPredicate = Callable[[PcolAttributes, object], Bool[Array, " P"]]


def _rows_dot(a, b):
    """Per column dot product of ``[3, P]`` rows with ``[3, P]`` rows or three scalars."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _eye_vector(attrs: PcolAttributes, view: View):
    """The rows of ``centre − eye``."""
    eye = view.eye
    return [attrs.center[i] - eye[i] for i in range(3)]


def _eye_offset(attrs: PcolAttributes, view: View):
    """``(d², h)``: squared distance eye→centre and its component along the axis."""
    v = _eye_vector(attrs, view)
    return _rows_dot(v, v), _rows_dot(v, attrs.axis)


def frustum_margins(attrs: PcolAttributes, view: View):
    """Per pcol, what the frustum test compares (:meth:`Camera.frustum_frame`).

    Returns:
        ``(x, y, z, sx, sy, lx, ly, near, far)``: the centre in camera
        coordinates (``z`` the depth along the view direction); ``sx = z·a_x +
        b_x`` and ``sy`` (a sphere is outside a side plane when ``s − |x| <
        −r·l``); ``lx``, ``ly`` the plane scales. The sphere is outside the
        near or far plane when ``z + r < near`` or ``z − r > far``.
    """
    k = view.frustum
    # The offset from the eye first: no cancellation between right·centre and
    # right·eye far from the origin, and the offset is shared with the other tests.
    v = _eye_vector(attrs, view)
    x, y, z = (_rows_dot(v, view.axis(i)) for i in range(3))
    return x, y, z, z * k(0) + k(2), z * k(1) + k(3), k(4), k(5), k(6), k(7)


def _outside_frustum(attrs: PcolAttributes, view: View):
    x, y, z, sx, sy, lx, ly, near, far = frustum_margins(attrs, view)
    r = attrs.radius
    out = (z + r < near) | (z - r > far)
    return out | (sx - jnp.abs(x) < -r * lx) | (sy - jnp.abs(y) < -r * ly)


def outside_frustum(attrs: PcolAttributes, camera: Camera) -> Bool[Array, " P"]:
    """Sphere entirely on the outer side of one of the six planes.

    Tested in camera coordinates (:meth:`Camera.frustum_frame`): a third fewer
    operations per pcol than six general plane tests (the batched predicate
    is bound by this test).

    Args:
        attrs: :class:`PcolAttributes` of the pcols (``center [3, P]``,
            ``radius [P]``, world units).
        camera: one :class:`Camera` (eye ``[3]``).

    Returns:
        ``bool[P]``: True where the pcol's bounding sphere is outside the view.
    """
    check_camera(camera, "outside_frustum", batch=False)
    attrs, camera = in_model_units(attrs, camera)
    return _outside_frustum(attrs, View.of(camera, 0.0))


def _oriented_away(attrs: PcolAttributes, view: View):
    sa, ca = attrs.sin_alpha, attrs.cos_alpha
    if view.orthographic:
        h = _rows_dot(attrs.axis, view.forward)
        return (ca > 0) & (h > sa)
    d2, h = _eye_offset(attrs, view)
    r = attrs.radius
    t2 = d2 - r * r  # t² = (d·cos(beta))², > 0 when the eye is outside the sphere
    sr, g = sa * r, h - ca * r
    return (t2 > 0) & (ca > 0) & (ca * ca * t2 > sr * sr) & (g > 0) & (g * g > sa * sa * t2)


def oriented_away(attrs: PcolAttributes, camera: Camera) -> Bool[Array, " P"]:
    """Every normal in the cone faces away from every eye ray into the sphere.

    With ``theta`` the angle between the axis and ``x − e`` (length ``d``) and
    ``beta = asin(r / d)`` the sphere's angular radius, all such dot products
    are positive iff ``theta + alpha + beta < π/2``. Without trigonometry, with
    ``t = √(d² − r²) = d·cos β`` and ``h = d cos θ``:
    ``alpha + beta < π/2 ⇔ cos α·t > sin α·r`` and then
    ``cos θ > sin(α + β) ⇔ h − cos α·r > sin α·t``. Both sides of each are
    compared squared, with their signs, so no root is taken either: the
    square root would be the costliest operation of the batched predicate.
    Orthographic views are the limit ``d = 1, r = 0`` along the view direction.

    Args:
        attrs: :class:`PcolAttributes` of the pcols (``center``, ``axis``
            ``[3, P]``; ``radius`` ``[P]`` world units; ``sin_alpha``,
            ``cos_alpha`` ``[P]`` of the normal cone's half angle).
        camera: one :class:`Camera` (eye ``[3]``).

    Returns:
        ``bool[P]``: True where the whole normal cone faces away from the eye.
    """
    check_camera(camera, "oriented_away", batch=False)
    attrs, camera = in_model_units(attrs, camera)
    return _oriented_away(attrs, View.of(camera, 0.0))


def safe_sqrt(x):
    """``sqrt(x)`` for ``x >= 0`` (bit for bit) whose gradient at 0 is 0, not NaN."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def _screen_terms(attrs: PcolAttributes, view: View):
    """``(mu², normal², s)``: the pcol is small on screen for ``κ`` when
    ``mu² < κ²·s`` and ``normal² < κ²·s·s``: Hoppe 1997's test
    ``NOT(mu² ≥ κ²d² or delta²(d² − h²) ≥ κ²d⁴)`` with ``s = d²``,
    ``normal² = delta²(d² − h²)`` (perspective); orthographic: ``s = 1``,
    ``normal² = delta²(1 − h²)``, ``h`` along the view direction."""
    mu2 = attrs.mu * attrs.mu
    delta2 = attrs.delta * attrs.delta
    if view.orthographic:
        h = _rows_dot(attrs.axis, view.forward)
        return mu2, delta2 * (1.0 - h * h), jnp.ones_like(mu2)
    d2, h = _eye_offset(attrs, view)
    return mu2, delta2 * (d2 - h * h), d2


def _small(mu2, normal2, s, kappa2):
    """The screen-space comparison, with no division or root (the batched
    predicate's costliest operations)."""
    limit = kappa2 * s
    return (mu2 < limit) & (normal2 < limit * s)


def screen_tolerance(attrs: PcolAttributes, camera: Camera, sqrt=jnp.sqrt) -> Float[Array, " P"]:
    """Per pcol, the pixel tolerance ``t_p`` of the screen-space test in closed
    form, ``sqrt(max(mu²/s, normal²/s²)) / one_pixel``: the test holds for
    ``tau > t_p`` up to float rounding (:func:`critical_tau` gives the exact
    threshold). ``sqrt``: :func:`safe_sqrt` where gradients are needed.
    """
    attrs, camera = in_model_units(attrs, camera)
    return view_screen_tolerance(attrs, View.of(camera, 0.0), sqrt)


def view_screen_tolerance(attrs: PcolAttributes, view: View, sqrt=jnp.sqrt) -> Float[Array, " P"]:
    """:func:`screen_tolerance` for a :class:`View`, ``attrs`` and ``view`` in
    the same units."""
    mu2, normal2, s = _screen_terms(attrs, view)
    # 1e-30 model units²: an eye on the pcol's centre.
    s = jnp.maximum(s, 1e-30)
    return sqrt(jnp.maximum(mu2 / s, normal2 / (s * s))) / view.one_pixel


def small_on_screen(attrs: PcolAttributes, camera: Camera, tau) -> Bool[Array, " P"]:
    """Screen-space deviation below ``tau`` pixels (Hoppe 1997's test, docs/design.md).

    Args:
        attrs: :class:`PcolAttributes` of the pcols (rows ``[3, P]``, ``[P]``;
            world units).
        camera: one :class:`Camera` (eye ``[3]``).
        tau: tolerance, pixels of the image height: one number >= 0.

    Returns:
        ``bool[P]``.
    """
    check_camera(camera, "small_on_screen", batch=False)
    tau = checked_tau(tau, "small_on_screen")
    attrs, camera = in_model_units(attrs, camera)
    view = View.of(camera, tau)
    return _small(*_screen_terms(attrs, view), view.kappa2)


def collapse_mask(
    attrs: PcolAttributes,
    camera: Camera,
    tau,
    tests: Tests = ALL_TESTS,
    predicate: Optional[UserPredicate] = None,
    context=None,
    combine: str = "or",
) -> Bool[Array, " P"]:
    """Per pcol: may it be collapsed for this view? (one camera)

    Args:
        attrs: :class:`PcolAttributes` of the pcols.
        camera: one :class:`Camera`.
        tau: screen-space tolerance, pixels of the image height: one number
            >= 0 (``inf``: every pcol the screen test can collapse; NaN refused).
        tests: which of the three tests apply.
        predicate: optional user test ``predicate(attrs, context) -> bool[P]``.
        context: passed to ``predicate`` (any pytree).
        combine: ``"or"`` (OR-ed with the tests) or ``"replace"``.

    Returns:
        ``bool[P]``.
    """
    check_camera(camera, "collapse_mask", batch=False)
    tau = checked_tau(tau, "collapse_mask")
    return _collapse_mask(attrs, camera, jnp.asarray(tau, jnp.float32), tests, predicate, context, combine)



# Compiled even when called eagerly: XLA's CPU code contracts a·b + c into one
# fused multiply-add inside compiled kernels, which eager op-by-op evaluation
# does not, and the decisions must be the same bits wherever they are made.
@eqx.filter_jit
def _collapse_mask(attrs, camera, tau, tests, predicate, context, combine):
    model, camera = in_model_units(attrs, camera)
    return view_collapse_mask(model, View.of(camera, tau), tests, predicate, context, combine, world=attrs)


def view_collapse_mask(
    attrs: PcolAttributes,
    view: View,
    tests: Tests = ALL_TESTS,
    predicate: Optional[UserPredicate] = None,
    context=None,
    combine: str = "or",
    rows: bool = True,
    world: Optional[PcolAttributes] = None,
) -> Bool[Array, " P"]:
    """:func:`collapse_mask` for a :class:`View` (the camera's constants for one
    ``tau``), ``attrs`` and ``view`` in the same units (:mod:`pmjax._units`).

    Args:
        rows: evaluate the tests on ``[P/1024, 1024]`` views (faster for one
            camera on CPU); mapped over cameras (:meth:`View.map`) the flat
            layout is faster. Both give the same bits.
        world: the attributes a user predicate sees, in world units
            (default ``attrs``).
    """
    out = jnp.zeros(attrs.radius.shape, bool)
    if predicate is None or combine == "or":

        def builtin(a):
            hit = _culled(a, view, tests)
            if tests.screen:
                hit = hit | _small(*_screen_terms(a, view), view.kappa2)
            return hit

        out = _in_rows(builtin, attrs) if rows else builtin(attrs)
    if predicate is not None:
        if combine not in ("or", "replace"):
            raise ValueError(f"combine must be 'or' or 'replace', got {combine!r}")
        out = out | jnp.asarray(predicate(attrs if world is None else world, context), bool)
    return out


def critical_tau(attrs: PcolAttributes, camera: Camera, tests: Tests = ALL_TESTS) -> Float[Array, " P"]:
    """Per pcol, the tolerance above which it collapses: ``collapse ⇔ tau > t_p``
    exactly, for every float32 ``tau >= 0`` (same comparisons as
    :func:`collapse_mask`).

    ``-1`` where the frustum or orientation test already collapses it (any
    ``tau >= 0``), ``+inf`` where nothing can (screen test off, or never small).

    Args:
        attrs: :class:`PcolAttributes` of the pcols (rows ``[3, P]``, ``[P]``;
            world units).
        camera: one :class:`Camera` (eye ``[3]``).
        tests: which of the three tests apply.

    Returns:
        ``float32[P]``: the tolerance of each pcol in pixels of the image
        height, ``-1`` or ``+inf`` as above.
    """
    check_camera(camera, "critical_tau", batch=False)
    return _critical_tau(attrs, camera, tests)


@eqx.filter_jit  # compiled like _collapse_mask, so both see the same bits
def _critical_tau(attrs, camera, tests):
    attrs, camera = in_model_units(attrs, camera)
    view = View.of(camera, 0.0)

    def per_pcol(a):
        if tests.screen:
            t = _screen_threshold(*_screen_terms(a, view), view.one_pixel)
        else:
            t = jnp.full(a.radius.shape, jnp.inf)
        return jnp.where(_culled(a, view, tests), -1.0, t)

    return _in_rows(per_pcol, attrs)


_FLOAT32_INF_BITS = 0x7F800000


def _screen_threshold(mu2, normal2, s, unit):
    """The largest float32 ``tau`` at which :func:`_small` is still false, so
    that it holds exactly for ``tau > t`` (``+inf`` if it never holds).

    ``kappa² =`` :func:`kappa_squared` ``(unit, tau)``, the expression the
    :class:`View` holds, is monotone in ``tau`` through every rounding,
    and so is the test; non-negative float32 values are ordered as their bit
    patterns, so a bisection over the patterns from 0 to +inf (31 halvings)
    finds the switch exactly, where the closed form (:func:`screen_tolerance`)
    can be a few ulps off.
    """

    def small_at(bits):
        return _small(mu2, normal2, s, kappa_squared(unit, jax.lax.bitcast_convert_type(bits, jnp.float32)))

    # Invariant: not small at lo (tau = 0 never is), small at hi.
    lo = jnp.zeros(mu2.shape, jnp.int32)
    hi = jnp.full(mu2.shape, _FLOAT32_INF_BITS, jnp.int32)
    for _ in range(31):
        mid = lo + (hi - lo) // 2
        small = small_at(mid)
        lo, hi = jnp.where(small, lo, mid), jnp.where(small, mid, hi)
    t = jax.lax.bitcast_convert_type(lo, jnp.float32)
    return jnp.where(small_at(jnp.full(mu2.shape, _FLOAT32_INF_BITS, jnp.int32)), t, jnp.inf)


def _culled(attrs: PcolAttributes, view: View, tests: Tests) -> Bool[Array, " P"]:
    """The tests that collapse a pcol whatever ``tau``: frustum or orientation."""
    out = jnp.zeros(attrs.radius.shape, bool)
    if tests.frustum:
        out = out | _outside_frustum(attrs, view)
    if tests.orientation:
        out = out | _oriented_away(attrs, view)
    return out


ROW = 1024


def _in_rows(per_pcol, attrs: PcolAttributes):
    """Evaluate an elementwise per-pcol function on ``[P // ROW, ROW]`` views.

    XLA's CPU backend splits 2-D loops over both cores and vectorizes the rows;
    the same kernel over a 1-D ``[P]`` array runs on one core, unvectorized.
    The ``P % ROW`` remainder is evaluated as a short 1-D tail. ``per_pcol``
    may return a pytree of per-pcol arrays.
    """
    return join_row_parts(in_row_parts(per_pcol, attrs))


def in_row_parts(per_pcol, attrs: PcolAttributes):
    """:func:`_in_rows` before its outputs are joined: ``(rows, tail)``, the
    ``[P // ROW, ROW]`` body and the ``[P % ROW]`` tail (either may be None).

    Joining is a 1-D concatenation, and XLA fuses the per-pcol computation
    into it (1-D, not vectorized) unless the join happens in another program:
    an eager caller returns the parts from one jitted call and joins them in
    the next (:func:`join_row_parts`).
    """
    P = attrs.radius.shape[0]
    body = (P // ROW) * ROW
    if body == 0:
        return None, per_pcol(attrs)
    rows = jax.tree.map(lambda x: x[..., :body].reshape(x.shape[:-1] + (body // ROW, ROW)), attrs)
    out = per_pcol(rows)
    tail = None if body == P else per_pcol(jax.tree.map(lambda x: x[..., body:], attrs))
    return out, tail


def join_row_parts(parts):
    """The ``[P]`` arrays of :func:`in_row_parts`'s ``(rows, tail)``."""
    rows, tail = parts
    if rows is None:
        return tail
    flat = jax.tree.map(lambda y: y.reshape(y.shape[:-2] + (-1,)), rows)
    if tail is None:
        return flat
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b], axis=-1), flat, tail)
