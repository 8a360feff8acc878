"""Geomorphs over time: blend a refinement change over a few frames.

When a pcol starts or stops executing between frames, the hard engine moves
vertices by the whole collapse at once (popping). Here each pcol keeps a
weight in [0, 1] that walks toward its target (1 executed, 0 not) by
``1 / frames`` per frame; positions (and normals) are
:func:`pmjax.geomorph_blend` of those weights, the same blend as the soft refinement's (docs/soft.md) driven by
time instead of temperature.

Only visible changes are blended. A pcol that the frustum or orientation
test culls, in this frame or the previous one, jumps to its target: its
geometry is out of sight, and blending it would keep coarse geometry around
while a region turns into view (that lag would pop; docs/soft.md).

A pcol's weight never exceeds its children's (the blend assumes it): after
each step the weights are clamped by their children's, up the batches.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._camera import Camera
from ._model import ProgressiveMesh
from ._predicate import ALL_TESTS, Tests
from .engines._dense import critical_tolerances, representatives, up_the_batches
from ._soft import geomorph_blend


class Geomorph(eqx.Module):
    """Per-pcol blend weights of a geomorph in progress.

    Attributes:
        weight: ``[P]`` float32 in [0, 1]: 0 not collapsed, 1 fully collapsed.
        hidden: ``[P]`` bool, the pcols culled in the last frame
            (:func:`hidden_pcols`); all False when unknown.
    """

    weight: Float[Array, " P"]
    hidden: Bool[Array, " P"]


@eqx.filter_jit
def hidden_pcols(pm: ProgressiveMesh, camera: Camera, tests: Tests = ALL_TESTS) -> Bool[Array, " P"]:
    """Pcols whose geometry is out of sight for ``camera``.

    A pcol is hidden when the frustum or orientation test collapses it and
    every pcol below it, whatever ``tau`` (critical tolerance < 0,
    :func:`pmjax.critical_tolerances`). Hidden pcols are always executed.

    Args:
        pm: the progressive mesh.
        camera: one :class:`Camera`.
        tests: :class:`Tests` (ablations), as given to ``refine``.

    Returns:
        ``bool[P]``.
    """
    return critical_tolerances(pm, camera, tests) < 0


def geomorph_start(executed: Bool[Array, " P"], hidden=None) -> Geomorph:
    """A geomorph at rest on an executed set (``Refinement.executed``);
    ``hidden``: this frame's :func:`hidden_pcols`, if known."""
    executed = jnp.asarray(executed)
    hidden = jnp.zeros(executed.shape, bool) if hidden is None else jnp.asarray(hidden, bool)
    return Geomorph(weight=executed.astype(jnp.float32), hidden=hidden)


@eqx.filter_jit
def geomorph_step(pm: ProgressiveMesh, state: Geomorph, executed: Bool[Array, " P"], frames, hidden=None) -> Geomorph:
    """One frame toward a new executed set.

    Args:
        pm: the progressive mesh.
        state: the current :class:`Geomorph`.
        executed: ``bool[P]`` this frame's hard refinement.
        frames: frames a full blend takes (``1`` = no geomorph: jump).
        hidden: ``bool[P]`` this frame's :func:`hidden_pcols`, or None
            (then every change is blended).

    Returns:
        the next :class:`Geomorph`.
    """
    rate = 1.0 / jnp.maximum(jnp.asarray(frames, jnp.float32), 1.0)
    target = jnp.asarray(executed, jnp.float32)
    hidden = jnp.zeros(target.shape, bool) if hidden is None else jnp.asarray(hidden, bool)
    # Out-of-sight changes (now or a frame ago) jump; visible ones walk.
    jump = hidden | state.hidden
    weight = jnp.where(jump, target, state.weight + jnp.clip(target - state.weight, -rate, rate))
    # A child that jumped open must not leave its parent more collapsed than itself.
    weight = up_the_batches(pm, weight, 1.0, lambda own, a, b: jnp.minimum(own, jnp.minimum(a, b)))
    return Geomorph(weight=weight, hidden=hidden)


@eqx.filter_jit
def _blend(pm: ProgressiveMesh, weight, normals):
    k = pm.killer
    drawn = (k < 0) if pm.n_pcols == 0 else (k < 0) | (weight[jnp.maximum(k, 0)] < 1.0)
    # Weld through the fully collapsed pcols, as the hard mesh does.
    rep = representatives(pm, weight >= 1.0)
    blended_normals = None if normals is None else geomorph_blend(pm, weight, normals)
    return geomorph_blend(pm, weight, pm.vertices), blended_normals, rep[pm.faces], drawn


def geomorph_mesh(pm: ProgressiveMesh, state: Geomorph, normals=None):
    """The blended mesh as plain arrays.

    Faces are the original faces whose killer is not fully collapsed; faces
    being refined grow from zero area, faces being collapsed shrink to it.
    At rest (weights 0 or 1) this is the hard refinement's mesh.

    Args:
        normals: optional ``[V0 + P, 3]`` per-vertex normals
            (:func:`pmjax.hierarchy_normals`) to blend the same way.

    Returns:
        ``(vertices float32[n, 3], faces int32[m, 3], vertex_ids int64[n])``
        (ids of the vertices used, as in ``Refinement.mesh``), plus the
        blended unit normals ``float32[n, 3]`` when ``normals`` is given.
    """
    positions, blended, corners, drawn = _blend(pm, state.weight, None if normals is None else jnp.asarray(normals))
    faces = np.asarray(corners)[np.asarray(drawn)]
    ids, inverse = np.unique(faces, return_inverse=True)
    out = (np.asarray(positions)[ids], inverse.reshape(-1, 3).astype(np.int32), ids)
    if normals is None:
        return out
    n = np.asarray(blended)[ids]
    return out + ((n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)).astype(np.float32),)
