"""Subtree bounds: one test at a pcol that decides its whole subtree.

A pcol is executed exactly when every pcol of its subtree (itself and all the
pcols below it) may collapse, because ``executed(p) = collapse(p) ∧
executed(c1) ∧ executed(c2)``. So a test at ``p`` that implies "every pcol
below collapses" decides the whole subtree without looking into it. Each of
the three refinement tests has such a bound, from four numbers per pcol
computed at load (:func:`subtree_bounds`), all upper bounds over the subtree
``S(p)``:

- ``reach``: a sphere about the pcol's centre ``c_p`` holding every sphere of
  ``S(p)``: ``max |c_q − c_p| + r_q``;
- ``spread``: ``max |c_q − c_p|``, the centres alone (the screen test);
- ``cone``: a cone about the pcol's axis ``n_p`` holding every cone of ``S(p)``:
  ``max angle(n_p, n_q) + alpha_q``;
- ``error``: ``max(mu_q, delta_q)``.

Then the refinement tests, each on the outer sphere and cone:

- **outside**: the ``reach`` sphere is outside a frustum plane: so is every
  sphere inside it;
- **oriented away**: ``theta + cone + asin(reach / d) < π/2``: every cone of
  ``S(p)`` faces away from every eye ray into its sphere;
- **small**: ``error < κ (d − spread)``: every ``q`` has ``mu_q`` and
  ``delta_q`` below ``κ d_q`` since ``d_q ≥ d − spread``, which is Hoppe's
  test for ``q``.

The pcols' own tests run in float32; each bound holds with a margin that
dominates their rounding (``MARGIN``, ``SCREEN_MARGIN``, ``ANGLE_MARGIN``), so
a subtree the bound decides is decided identically by the exact tests, pcol by
pcol. Nothing here assumes the file's attributes nest: the bounds are computed
from what each pcol holds, bottom-up with the triangle inequality.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._view import View

# Relative margins, in units of the magnitudes a test adds up: 2^-16 is 128
# float32 ulps (the frustum test rounds in a dozen operations).
MARGIN = 2.0 ** -16
SCREEN_MARGIN = 2.0 ** -14
# Angle margin of the orientation bound (radians). The pcols' root-free
# comparisons then have a slack of at least ANGLE_MARGIN²/2 = 1.25e-3
# relative, while the eye stays far enough from every sphere below that
# d² − r² ≥ sin²(0.05)·d² keeps its rounding near 5e-5: a 25x margin.
ANGLE_MARGIN = 0.05
# Float32 rounding is relative only between underflow and overflow (XLA on the
# CPU flushes subnormals to zero): a bound decides nothing where a
# descendant's own comparison could leave [LOW, HIGH].
LOW = 2.0 ** -100
HIGH = 2.0 ** 100


class SubtreeBounds(eqx.Module):
    """Per-pcol bounds over its subtree (float32, rounded up; see module doc).

    Attributes:
        reach: ``[P]`` radius about the pcol centre holding every sphere below, model units.
        spread: ``[P]`` radius about the pcol centre holding every centre below, model units.
        cone: ``[P]`` half-angle about the pcol axis holding every cone below, radians.
        error: ``[P]`` largest ``mu`` or ``delta`` below, model units.
    """

    reach: Float[Array, " P"]
    spread: Float[Array, " P"]
    cone: Float[Array, " P"]
    error: Float[Array, " P"]


class FrontBounds(eqx.Module):
    """The subtree bounds as the traversal reads them, per-pcol factors
    precomputed so that no camera lane recomputes them (float32).

    Attributes:
        reach, spread, error: as :class:`SubtreeBounds`.
        facing: ``sin(cone + ANGLE_MARGIN)`` rounded up, or 2 (no bound) when
            ``cone + ANGLE_MARGIN >= π/2``.
        axis_scale: ``1 / |axis|`` (0 for a zero axis): the projection on
            the unit axis is ``(v · axis) · axis_scale``.
    """

    reach: Float[Array, " P"]
    spread: Float[Array, " P"]
    facing: Float[Array, " P"]
    error: Float[Array, " P"]
    axis_scale: Float[Array, " P"]


def front_bounds(bounds: dict, axis) -> dict:
    """:class:`FrontBounds` fields (host float32 arrays) from the
    :func:`subtree_bounds` of pcols with cone axes ``axis [3, P]``."""
    cone = np.asarray(bounds["cone"], np.float64) + ANGLE_MARGIN
    up = lambda x: np.nextafter(x.astype(np.float32), np.float32(np.inf))
    facing = np.where(cone < math.pi / 2, up(np.sin(np.minimum(cone, math.pi / 2))), np.float32(2.0))
    n = np.asarray(axis, np.float64)
    length = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    scale = np.where(length > 0, 1.0 / np.where(length > 0, length, 1.0), 0.0).astype(np.float32)
    return dict(reach=bounds["reach"], spread=bounds["spread"], facing=facing.astype(np.float32),
                error=bounds["error"], axis_scale=scale)


def subtree_bounds(center, axis, radius, sin_alpha, cos_alpha, delta, mu, child1, child2, batch_offsets,
                   nesting=None) -> dict:
    """The four subtree bounds of every pcol, bottom-up, batch by batch.

    Args:
        center, axis: ``[P, 3]`` the pcols' centres and cone axes, as the tests see them.
        radius, sin_alpha, cos_alpha, delta, mu: ``[P]`` the pcols' own attributes.
        child1, child2: ``[P]`` pcol making each endpoint, ``-1`` for an original vertex.
        batch_offsets: ``[B + 1]``.
        nesting: optional ``nesting(p, q, gap, turn, which)``, called for
            every parent ``p`` and created child ``q`` (pcol ids, arrays) with
            their centres' distance and their axes' angle, ``which`` being 1
            or 2: the load's check that attributes nest
            (:class:`pmjax._structure.NestingCheck`) reads the gathers made
            here instead of repeating them.

    Returns:
        dict ``reach, spread, cone, error`` of float32 ``[P]`` arrays, each
        an upper bound (computed in float64, rounded up).
    """
    c, norm, unit = _centres_and_axes(center, axis)
    # The cone angle the tests mean: they compare the stored sine squared and
    # need a positive cosine, so it is atan2(|sin|, cos) (at least π/2, never
    # facing away, when the cosine is not positive). An axis that is not unit
    # (a degenerate normal), or a sine and cosine that are not those of one
    # angle (an attribute updated alone), bounds nothing: its cone is π.
    sin64, cos64 = np.asarray(sin_alpha, np.float64), np.asarray(cos_alpha, np.float64)
    own_cone = np.arctan2(np.abs(sin64), cos64)
    one_angle = np.abs(np.sqrt(sin64 * sin64 + cos64 * cos64) - 1.0) < 1e-3
    own_cone = np.where((np.abs(norm - 1.0) < 1e-3) & one_angle, own_cone, math.pi)
    acc = dict(reach=np.asarray(radius, np.float64).copy(), spread=np.zeros(len(norm)), cone=own_cone.copy(),
               error=np.maximum(np.asarray(mu, np.float64), np.asarray(delta, np.float64)))
    child1 = np.asarray(child1).astype(np.intp)
    child2 = np.asarray(child2).astype(np.intp)
    # Children come from earlier batches, so their bounds are final when a
    # batch is reached (the same order as the engine's propagation).
    for lo, hi in zip(batch_offsets[:-1], batch_offsets[1:]):
        lo, hi = int(lo), int(hi)
        for which, child in ((1, child1[lo:hi]), (2, child2[lo:hi])):
            has = np.flatnonzero(child >= 0)
            if len(has) == 0:
                continue
            p, q = lo + has, child[has]
            gap, turn = _gap_and_turn(c, unit, p, q)
            if nesting is not None:
                nesting(p, q, gap, turn, which)
            _take_child(acc, acc, p, q, gap, turn)
    acc["cone"] = np.minimum(acc["cone"], 4.0)
    return {k: _rounded_up(v) for k, v in acc.items()}


def _centres_and_axes(center, axis):
    """Centres and axes ``[P, 3]`` as struct of arrays (one float64 row per
    coordinate: gathers of single rows are several times faster than gathers
    of [N, 3] rows), with the axes' lengths and the unit axes."""
    c = np.ascontiguousarray(np.asarray(center).T, np.float64)
    n = np.ascontiguousarray(np.asarray(axis).T, np.float64)
    norm = np.sqrt(_rows_dot(n, n))
    return c, norm, n / np.where(norm > 0, norm, 1.0)


def _gap_and_turn(c, unit, p, q):
    """Distance of the centres and angle of the unit axes of pcols ``p`` and ``q``."""
    d = [c[k][q] - c[k][p] for k in range(3)]
    dot = _rows_dot([u[p] for u in unit], [u[q] for u in unit])
    return np.sqrt(_rows_dot(d, d)), np.arccos(np.clip(dot, -1.0, 1.0))


def _take_child(acc, child, p, q, gap, turn):
    """Grow the bounds ``acc`` of pcols ``p`` (float64, in place) to hold the
    subtree bounds ``child`` of their children ``q``, seen from ``p``: farther
    by ``gap``, turned by ``turn``."""
    acc["reach"][p] = np.maximum(acc["reach"][p], gap + child["reach"][q])
    acc["spread"][p] = np.maximum(acc["spread"][p], gap + child["spread"][q])
    acc["cone"][p] = np.maximum(acc["cone"][p], turn + child["cone"][q])
    acc["error"][p] = np.maximum(acc["error"][p], child["error"][q])


def _rounded_up(x):
    """float32 upper bounds of float64 ``x``, whose sums rounded too: one
    relative step of 2^-40 covers them. A zero (nothing below, or a spread
    over one centre) is exact and stays zero: rounded up it would be the
    smallest subnormal float, which costs the CPU a microcode assist in every
    vector operation that reads it."""
    up = np.nextafter((x * (1 + 2.0 ** -40)).astype(np.float32), np.float32(np.inf))
    return np.where(x == 0, np.float32(0), up)



def below_bounds(center, axis, bounds, child1, child2) -> dict:
    """Bounds over the pcols strictly below each pcol (its subtree but itself),
    about its own centre and axis, from its created children's
    :func:`subtree_bounds`.

    Where such a bound says "every pcol below collapses", both children ran
    and the pcol runs exactly when it collapses itself: the traversal decides
    the pcol and need not visit its children. A pcol whose children are both
    original vertices has nothing below (zeros).

    Args:
        center, axis: ``[P, 3]`` as for :func:`subtree_bounds`.
        bounds: :func:`subtree_bounds` (``reach, spread, cone, error``).
        child1, child2: ``[P]`` pcol making each endpoint, ``-1`` for an original vertex.

    Returns:
        dict ``reach, spread, cone, error`` of float32 ``[P]`` upper bounds.
    """
    c, norm, unit = _centres_and_axes(center, axis)
    whole = {k: np.asarray(bounds[k], np.float64) for k in ("reach", "spread", "cone", "error")}
    out = {k: np.zeros(len(norm)) for k in whole}
    for child in (np.asarray(child1), np.asarray(child2)):
        p = np.flatnonzero(child >= 0)
        q = child[p].astype(np.intp)
        gap, turn = _gap_and_turn(c, unit, p, q)
        _take_child(out, whole, p, q, gap, turn)
    # About an axis that is not unit the cones bound nothing (π, as in
    # subtree_bounds).
    out["cone"] = np.where(np.abs(norm - 1.0) < 1e-3, np.minimum(out["cone"], 4.0), math.pi)
    return {k: _rounded_up(v) for k, v in out.items()}


def _rows_dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def subtree_collapses(center, axis, bounds: FrontBounds, view: View, tests) -> Bool[Array, " N"]:
    """Per pcol: does every pcol of its subtree collapse for this view?

    ``True`` is a guarantee (the tests of every pcol below would say
    "collapse"); ``False`` only means the bound cannot tell.

    Args:
        center, axis: ``[3, N]`` rows of the pcols' centres and axes.
        bounds: :class:`FrontBounds` of the same ``N`` pcols.
        view: one camera's :class:`View`.
        tests: :class:`pmjax.Tests`; a test switched off bounds nothing.
    """
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    reach, spread, error = bounds.reach, bounds.spread, bounds.error
    v = [center[i] - view.eye[i] for i in range(3)]
    out = jnp.zeros(reach.shape, bool)
    if tests.frustum:
        k = view.frustum
        x, y, z = (_rows_dot(v, view.axis(i)) for i in range(3))
        sx, sy, lx, ly, near, far = z * k(0) + k(2), z * k(1) + k(3), k(4), k(5), k(6), k(7)
        size = (jnp.abs(x) + jnp.abs(y) + jnp.abs(z) + reach) * (1 + jnp.abs(k(0)) + jnp.abs(k(1)) + lx + ly)
        m = f32(MARGIN) * (size + jnp.abs(k(2)) + jnp.abs(k(3)) + jnp.abs(near) + jnp.abs(far))
        outside = (z + reach < near - m) | (z - reach > far + m)
        outside = outside | (sx - jnp.abs(x) + reach * lx < -m) | (sy - jnp.abs(y) + reach * ly < -m)
        out = out | (outside & (m > f32(LOW)) & (m < f32(HIGH)))
    if view.orthographic:
        if tests.orientation:
            # theta + cone < π/2 − margin, as cos(theta) > sin(cone + margin).
            out = out | (_rows_dot(axis, view.forward) * bounds.axis_scale > bounds.facing)
        if tests.screen:
            e2 = error * error
            out = out | ((e2 < view.kappa2 * f32(1 - SCREEN_MARGIN)) & (view.kappa2 > f32(LOW)) & (e2 < f32(HIGH)))
        return out
    d2 = _rows_dot(v, v)
    if tests.orientation:
        # theta + beta < π/2 − cone − margin, without inverse trigonometry:
        # cos(theta + beta) > sin(cone + margin) = facing, with cos(theta) =
        # a / d (a the eye vector's projection on the unit axis) and
        # sin(beta) = reach / d; times d², two roots and no division.
        # Rounding moves the angle by far less than the margin.
        a = _rows_dot(v, axis) * bounds.axis_scale
        lhs = a * jnp.sqrt(jnp.maximum(d2 - reach * reach, 0.0)) - reach * jnp.sqrt(jnp.maximum(d2 - a * a, 0.0))
        d = jnp.sqrt(d2)
        in_range = ((d - reach) * (d - reach) > f32(2.0 ** -80)) & ((d + reach) * (d + reach) < f32(HIGH))
        out = out | ((d2 > reach * reach) & (a > 0) & (lhs > d2 * bounds.facing) & in_range)
    if tests.screen:
        d = jnp.sqrt(d2)
        room = d - spread - f32(SCREEN_MARGIN) * (d + spread)
        room2, far2, e2 = room * room, (d + spread) * (d + spread), error * error
        in_range = (view.kappa2 * jnp.minimum(room2, room2 * room2) > f32(LOW)) & \
            (view.kappa2 * far2 * far2 < f32(HIGH)) & (e2 * far2 < f32(HIGH))
        out = out | ((room > 0) & (e2 < view.kappa2 * room2 * f32(1 - SCREEN_MARGIN)) & in_range)
    return out
