"""Soft face budgets: the ``tau`` whose soft face count equals a budget.

The exact answer for the hard engine is :func:`pmjax.faces_for_budget` (one
sort of the critical tolerances). This is its differentiable counterpart: a
root find on the soft face count, solved for many cameras at once by one
compiled program (a bracketed regula falsi, every camera a lane).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._arguments import check_camera, check_mesh
from ._camera import Camera, index_camera
from ._model import ProgressiveMesh
from ._predicate import ALL_TESTS, Tests, _in_rows
from ._scalars import host_number, host_scalar
from ._soft import soft_face_count, soft_tests_in_model_units, soft_weights
from ._units import attributes_in_model_units, camera_in_model_units


class BudgetSolution(eqx.Module):
    """Per camera: the soft-budget tolerance and how the solve went.

    Attributes:
        tau: ``[K]`` tolerance in pixels.
        soft_faces: ``[K]`` soft face count at ``tau``.
        steps: ``[K]`` evaluations after the bracketing grid.
        converged: ``[K]`` whether the solve met its tolerance within ``max_steps``.
    """

    tau: Float[Array, " K"]
    soft_faces: Float[Array, " K"]
    steps: Int[Array, " K"]
    converged: Array


def soft_faces_batch(pm: ProgressiveMesh, cameras: Camera, log_tau: Float[Array, " K"], temperature,
                     tests: Tests = ALL_TESTS) -> Float[Array, " K"]:
    """Soft face count of each camera at its own ``tau = exp(log_tau)``.

    The same count as ``soft_refine(pm, camera, tau, temperature · tau).faces``
    (to float32 rounding: the sums run in another order), for K cameras at
    once with the cameras on the trailing axis, so the hierarchy is walked
    once for all of them and each gather reads K neighbouring values.

    Args:
        cameras: a camera batch (leading axis K).
        log_tau: ``[K]`` natural log of each camera's tolerance (pixels).
        temperature: softness relative to the tolerance.

    Returns:
        ``[K]`` soft face counts.
    """
    tau = jnp.exp(log_tau)
    attrs, exponent = attributes_in_model_units(pm.attributes)

    def collapse(camera, t):
        camera = camera_in_model_units(camera, exponent)
        return _in_rows(lambda a: soft_tests_in_model_units(a, camera, t, temperature * t, None, tests)[0], attrs)

    return soft_face_count(pm, soft_weights(pm, jax.vmap(collapse, out_axes=1)(cameras, tau)))  # weights [P, K]


def soft_tau_for_budget(
    pm: ProgressiveMesh,
    cameras: Camera,
    budget,
    temperature=0.05,
    *,
    tau_range: tuple = (1e-3, 1e4),
    max_steps: int = 20,
    rtol: float = 1e-4,
    tests: Tests = ALL_TESTS,
    chunk: int | None = None,
) -> BudgetSolution:
    """Solve ``soft_faces(tau) = budget`` per camera.

    One compiled program solves every camera: chunk by chunk, the cameras
    of a chunk as lanes of one loop. A log-spaced grid of tolerances
    brackets each camera's root, then regula falsi (Anderson-Björck) on the
    logit of the soft count in ``log tau`` (close to a line) shrinks each
    bracket until each camera has converged. Every pass of the loop is one
    batched soft count of the chunk (:func:`soft_faces_batch`).

    Args:
        pm: :class:`ProgressiveMesh`.
        cameras: a camera batch (leading axis K).
        budget: face budget, scalar or ``[K]``; must lie strictly between the
            base mesh's and the original mesh's face counts to have a root.
        temperature: softness relative to the tolerance: the soft count at
            ``tau`` uses ``temperature · tau`` pixels, so the curve is equally
            smooth at every scale of ``tau`` (a fixed temperature in pixels
            leaves stairs at large ``tau``, where few pcols change).
        tau_range: ``(lowest, highest)`` tolerance searched, pixels. A budget
            already met at the lowest gives the lowest (``converged``); one not
            met at the highest gives the highest (not ``converged``).
        max_steps: cap on the evaluations after the grid.
        rtol: relative face-count error at which a camera has converged.
        tests: :class:`Tests`.
        chunk: cameras solved together (memory grows with it as ``P·chunk``);
            default: as many as keep one ``[P, chunk]`` float32 array near
            4 MB, at most 256.

    Returns:
        :class:`BudgetSolution` (device arrays, shape ``[K]``).

    Raises:
        ValueError: a temperature that is not > 0 and finite, a budget that is
            negative, NaN or of another shape than one number or ``[K]``, a
            ``tau_range`` that is not ``0 < lowest < highest``, finite (traced
            values: inside the compiled solve, ``eqx.error_if``).
    """
    check_mesh(pm, "soft_tau_for_budget")
    K = check_camera(cameras, "soft_tau_for_budget", batch=True)
    if cameras.orthographic:
        raise ValueError("soft_tau_for_budget supports perspective cameras only")
    _check_arguments(budget, temperature, tau_range, K)
    dtype = pm.attributes.radius.dtype
    budget = jnp.broadcast_to(jnp.asarray(budget, dtype), (K,))
    if chunk is None:
        chunk = max(1, min(256, (1 << 20) // max(pm.n_pcols, 1)))
    chunk = max(1, min(int(chunk), K))
    return _solve_chunks(pm, cameras, budget, jnp.asarray(temperature, dtype), jnp.asarray(tau_range, dtype),
                         max_steps, rtol, tests, chunk)


def _check_arguments(budget, temperature, tau_range, K: int) -> None:
    """The budget, temperature and searched range, checked on the host where
    they are known (``ValueError`` naming the argument); traced values are
    checked inside the compiled solve (:func:`_checked_traced`)."""
    call = "soft_tau_for_budget"
    host_number(temperature, "temperature", call, lambda t: 0 < t < np.inf, "> 0 and finite (a fraction of tau)")
    if np.ndim(budget) not in (0, 1) or (np.ndim(budget) == 1 and np.shape(budget)[0] != K):
        raise ValueError(f"{call}: budget must be one number or one per camera ([{K}]), "
                         f"got shape {list(np.shape(budget))}")
    if not isinstance(budget, jax.core.Tracer):
        faces = np.asarray(budget)
        if faces.dtype.kind not in "iuf":
            raise TypeError(f"{call}: budget must be numbers of faces, got {faces.dtype} {faces!r}"[:200])
        bad = np.flatnonzero(~(np.isfinite(faces) & (faces >= 0)))
        if bad.size:
            raise ValueError(f"{call}: budget must be >= 0 faces and finite, got {np.ravel(faces)[bad[0]]}"
                             + (f" for camera {bad[0]}" if faces.ndim else ""))
    shape = (len(tau_range),) if isinstance(tau_range, (tuple, list)) else np.shape(tau_range)
    if shape != (2,):
        raise ValueError(f"{call}: tau_range must be (lowest, highest) pixels, got shape {list(shape)}")
    if not any(isinstance(t, jax.core.Tracer) for t in tau_range):
        lo, hi = (host_scalar(np.asarray(t) if isinstance(t, jax.Array) else t, "tau_range", call) for t in tau_range)
        if not 0 < lo < hi < np.inf:
            raise ValueError(f"{call}: tau_range must be (lowest, highest) with 0 < lowest < highest, finite "
                             f"pixels, got ({lo:g}, {hi:g})")


def _checked_traced(budget, temperature, tau_range):
    """:func:`_check_arguments`'s value rules inside the compiled solve, for
    traced arguments (``eqx.error_if``; values the host checked pass)."""
    budget = eqx.error_if(budget, ~jnp.all(jnp.isfinite(budget) & (budget >= 0)),
                          "soft_tau_for_budget: budget must be >= 0 faces and finite")
    temperature = eqx.error_if(temperature, ~((temperature > 0) & jnp.isfinite(temperature)),
                               "soft_tau_for_budget: temperature must be > 0 and finite")
    lo, hi = tau_range[0], tau_range[1]
    tau_range = eqx.error_if(tau_range, ~((lo > 0) & (lo < hi) & jnp.isfinite(hi)),
                             "soft_tau_for_budget: tau_range must be (lowest, highest) with 0 < lowest < highest, "
                             "finite pixels")
    return budget, temperature, tau_range


@eqx.filter_jit
def _solve_chunks(pm, cameras, budget, temperature, tau_range, max_steps, rtol, tests, chunk):
    budget, temperature, tau_range = _checked_traced(budget, temperature, tau_range)
    # One program for all chunks, solved one after the other (lax.map): the
    # last chunk is padded with its last camera, and the padding dropped.
    K = budget.shape[0]
    n = -(-K // chunk)
    index = jnp.minimum(jnp.arange(n * chunk), K - 1).reshape(n, chunk)
    parts = jax.lax.map(lambda i: _solve(pm, index_camera(cameras, i), budget[i], temperature, tau_range,
                                         max_steps, rtol, tests), index)
    return jax.tree.map(lambda x: x.reshape((n * chunk,) + x.shape[2:])[:K], parts)


# Log-spaced tolerances evaluated first to bracket the root (cells of 215x over
# the default range): each costs one batched evaluation, as does each regula
# falsi step; the logit of the count is close enough to a line across a cell
# that three steps usually follow.
GRID = 4


def _solve(pm, cameras, budget, temperature, tau_range, max_steps, rtol, tests):
    K = budget.shape[0]
    grid = jnp.linspace(jnp.log(tau_range[0]), jnp.log(tau_range[1]), GRID)
    lanes = jnp.arange(K)

    def residual(ends, f):
        # The logit of the soft count: close to a line in log tau, so secants
        # through the bracket land near the root.
        hi, lo, inner, target = ends
        tiny = 1e-6 * (hi - lo)
        return jnp.log(jnp.maximum(f - lo, tiny)) - jnp.log(jnp.maximum(hi - f, tiny)) - target

    def bracket(counts):
        """The cell of the grid where each camera's count crosses its budget,
        as the regula falsi's start, from the grid's counts ``[GRID, K]``."""
        hi, lo = counts[0], counts[-1]
        fits = budget >= hi  # met at the finest tolerance of the range
        reachable = budget > lo  # else not met even at the coarsest
        cell = jnp.clip(jnp.sum(counts > budget, axis=0) - 1, 0, GRID - 2)
        c_hi, c_lo = counts[cell, lanes], counts[cell + 1, lanes]
        inner = jnp.clip(budget, c_lo + 1e-3 * (c_hi - c_lo), c_hi - 1e-3 * (c_hi - c_lo))
        ends = (hi, lo, inner, jnp.log(inner - lo) - jnp.log(hi - inner))
        # The residual falls with log tau: positive at the cell's lower end.
        a, b = grid[cell], grid[cell + 1]
        return ends, (a, residual(ends, c_hi), b, residual(ends, c_lo)), fits, reachable, c_hi

    # One loop, one evaluation of the soft count per pass (one copy of it in
    # the program): the grid's points first, then regula falsi with the
    # Anderson-Björck rule from each camera's cell, until every camera is done.
    def cond(state):
        i, steps, done = state[0], state[-2], state[-1]
        return (i < GRID) | (jnp.any(~done) & (jnp.max(steps) < max_steps))

    def step(state):
        i, counts, ends, (a, ra, b, rb), side, fits, reachable, y_done, f_done, steps, done = state
        secant = jnp.clip((a * rb - b * ra) / (rb - ra), a, b)
        secant = jnp.where(jnp.isfinite(secant), secant, 0.5 * (a + b))
        in_grid = i < GRID
        y = jnp.where(in_grid, grid[jnp.minimum(i, GRID - 1)], secant)
        f = soft_faces_batch(pm, cameras, y, temperature, tests)

        # The grid: record the count; after its last point, bracket.
        counts = jnp.where(in_grid, jax.lax.dynamic_update_index_in_dim(counts, f, jnp.minimum(i, GRID - 1), 0),
                           counts)
        g_ends, g_ab, g_fits, g_reachable, c_hi = bracket(counts)

        # A regula falsi step: keep the root bracketed; an end kept twice in
        # a row has its residual scaled down (by 1 - r/r_replaced, or a half),
        # so that the bracket shrinks from both ends.
        r = residual(ends, f)
        ok = jnp.abs(f - ends[2]) <= rtol * ends[2]
        above = r > 0  # the root lies above y
        scale_b = jnp.where(above & (side > 0), 1.0 - r / ra, 1.0)
        scale_a = jnp.where(~above & (side < 0), 1.0 - r / rb, 1.0)
        scale_a, scale_b = (jnp.where(s > 0, s, 0.5) for s in (scale_a, scale_b))
        s_ab = (jnp.where(above, y, a), jnp.where(above, r, scale_a * ra),
                jnp.where(above, b, y), jnp.where(above, scale_b * rb, r))
        live = ~done
        stepped = (ends, s_ab, jnp.where(above, 1, -1), fits, reachable, jnp.where(live, y, y_done),
                   jnp.where(live, f, f_done), steps + live, done | ok)

        last = i == GRID - 1
        bracketed = (g_ends, g_ab, jnp.zeros(K, jnp.int32), g_fits, g_reachable, g_ab[0], c_hi,
                     jnp.zeros(K, jnp.int32), g_fits | ~g_reachable)
        waiting = (ends, (a, ra, b, rb), side, fits, reachable, y_done, f_done, steps, done)
        pick = lambda x, y, z: jnp.where(last, x, jnp.where(in_grid, y, z))
        return (i + 1, counts) + jax.tree.map(pick, bracketed, waiting, stepped)

    zero, no = jnp.zeros(K, grid.dtype), jnp.zeros(K, bool)
    start = (jnp.int32(0), jnp.zeros((GRID, K), grid.dtype), (zero, zero, zero, zero), (zero, zero, zero, zero),
             jnp.zeros(K, jnp.int32), no, no, zero, zero, jnp.zeros(K, jnp.int32), no)
    _, counts, _, _, _, fits, reachable, y, f, steps, done = jax.lax.while_loop(cond, step, start)
    hi, lo = counts[0], counts[-1]
    log_tau = jnp.where(fits, grid[0], jnp.where(reachable, y, grid[-1]))
    soft = jnp.where(fits, hi, jnp.where(reachable, f, lo))
    return BudgetSolution(tau=jnp.exp(log_tau), soft_faces=soft, steps=steps, converged=fits | (reachable & done))
