"""Soft face budgets: the ``tau`` whose soft face count equals a budget.

The exact answer for the hard engine is :func:`pmjax.faces_for_budget` (one
sort of the critical tolerances). This is its differentiable counterpart: a
root find with optimistix on the soft face count, vmapped over cameras.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, Int

from ._camera import Camera, camera_count, index_camera
from ._model import ProgressiveMesh
from ._predicate import ALL_TESTS, Tests
from ._soft import soft_refine_unchecked


class BudgetSolution(eqx.Module):
    """Per camera: the soft-budget tolerance and how the solve went.

    Attributes:
        tau: ``[K]`` tolerance in pixels.
        soft_faces: ``[K]`` soft face count at ``tau``.
        steps: ``[K]`` Newton iterations taken.
        converged: ``[K]`` whether the solve met its tolerance within ``max_steps``.
    """

    tau: Float[Array, " K"]
    soft_faces: Float[Array, " K"]
    steps: Int[Array, " K"]
    converged: Array


def _soft_faces(log_tau, pm, camera, temperature, tests):
    tau = jnp.exp(log_tau)
    return soft_refine_unchecked(pm, camera, tau, temperature * tau, None, tests).faces


def _logit_excess(log_tau, args):
    """Budget residual in coordinates where Newton behaves.

    The soft face count falls from ``hi`` (finest, at the lower end of the
    range) to ``lo`` (coarsest) in an S-shaped curve of ``log tau``, flat at
    both ends; its logit ``log((f − lo)/(hi − f))`` is close to a line, so a
    Newton step from anywhere in the range lands near the root.
    """
    pm, camera, temperature, tests, lo, hi, target, active, y0 = args
    f = _soft_faces(log_tau, pm, camera, temperature, tests)
    tiny = 1e-6 * (hi - lo)
    residual = jnp.log(jnp.maximum(f - lo, tiny)) - jnp.log(jnp.maximum(hi - f, tiny)) - target
    # A camera whose answer is already known (budget outside the range)
    # solves a trivial equation, so it cannot stall its batch's solve.
    return jnp.where(active, residual, log_tau - y0)


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
    chunk: int = 16,
) -> BudgetSolution:
    """Solve ``soft_faces(tau) = budget`` per camera (Newton, optimistix).

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
        max_steps: Newton iteration cap.
        rtol: tolerance on ``log tau`` steps (relative change of ``tau``) and
            on ``log faces`` (relative face-count error).
        tests: :class:`Tests`.
        chunk: cameras solved per vmapped call (memory grows with it).

    Returns:
        :class:`BudgetSolution` (device arrays, shape ``[K]``).
    """
    K = camera_count(cameras)
    if K == 0:
        raise ValueError("soft_tau_for_budget needs a camera batch (leading axis)")
    dtype = pm.attributes.radius.dtype
    budget = jnp.broadcast_to(jnp.asarray(budget, dtype), (K,))
    # Chunks of cameras keep memory bounded (each camera holds ~GRID soft
    # refinements at once); the last chunk is padded so one compile serves all.
    chunk = max(1, min(int(chunk), K))
    parts = []
    for start in range(0, K, chunk):
        idx = jnp.minimum(jnp.arange(start, start + chunk), K - 1)
        part = _solve(pm, index_camera(cameras, idx), budget[idx], jnp.asarray(temperature, dtype),
                      jnp.asarray(tau_range, dtype), max_steps, rtol, tests)
        parts.append(jax.tree.map(lambda x: x[: min(chunk, K - start)], part))
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)


# Log-spaced tolerances evaluated first to bracket the root (cells of ~2.9x).
GRID = 16


@eqx.filter_jit
def _solve(pm, cameras, budget, temperature, tau_range, max_steps, rtol, tests):
    solver = optx.Newton(rtol=rtol, atol=rtol)
    grid = jnp.linspace(jnp.log(tau_range[0]), jnp.log(tau_range[1]), GRID)

    def one(camera, b):
        # Bracket: the soft count falls along the grid; find the cell where it
        # crosses the budget. Its ends clip the Newton steps, so the flat
        # stretches of the curve outside the cell cannot trap the solve.
        counts = jax.vmap(lambda s: _soft_faces(s, pm, camera, temperature, tests))(grid)
        hi, lo = counts[0], counts[-1]
        fits = b >= hi  # met at the finest tolerance of the range
        reachable = b > lo  # else not met even at the coarsest
        cell = jnp.clip(jnp.sum(counts > b) - 1, 0, GRID - 2)
        c_hi, c_lo = counts[cell], counts[cell + 1]
        lower, upper = grid[cell], grid[cell + 1]
        inner = jnp.clip(b, c_lo + 1e-3 * (c_hi - c_lo), c_hi - 1e-3 * (c_hi - c_lo))
        target = jnp.log(inner - lo) - jnp.log(hi - inner)
        # Start where the count, linear in log tau across the cell, meets the budget.
        y0 = lower + (upper - lower) * (c_hi - inner) / jnp.maximum(c_hi - c_lo, 1e-30)
        args = (pm, camera, temperature, tests, lo, hi, target, ~fits & reachable, y0)
        sol = optx.root_find(_logit_excess, solver, y0, args, options=dict(lower=lower, upper=upper),
                             max_steps=max_steps, throw=False)
        log_tau = jnp.where(fits, grid[0], jnp.where(reachable, sol.value, grid[-1]))
        faces = _soft_faces(log_tau, pm, camera, temperature, tests)
        steps = jnp.where(fits | ~reachable, 0, sol.stats["num_steps"])
        ok = fits | (reachable & (sol.result == optx.RESULTS.successful))
        return jnp.exp(log_tau), faces, steps, ok

    tau, faces, steps, ok = jax.vmap(one)(cameras, budget)
    return BudgetSolution(tau=tau, soft_faces=faces, steps=steps, converged=ok)
