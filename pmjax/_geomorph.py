"""Geomorphs over time: blend a refinement change over a few frames.

When a pcol starts or stops executing between frames, the hard engine moves
vertices by the whole collapse at once (popping). Here each pcol keeps a
weight in [0, 1] that walks toward its target (1 executed, 0 not) by
``1 / frames`` per frame; positions (and normals) are
:func:`pmjax.geomorph_blend` of those weights, the same blend as the soft refinement's (DESIGN §4) driven by
time instead of temperature.

A pcol's weight never exceeds its children's: both start consistent (the
executed set contains the children of every member) and the step is monotone
in the weight and in the target.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._model import ProgressiveMesh
from ._refine import representatives
from ._soft import geomorph_blend


class Geomorph(eqx.Module):
    """Per-pcol blend weights of a geomorph in progress.

    Attributes:
        weight: ``[P]`` float32 in [0, 1]: 0 not collapsed, 1 fully collapsed.
    """

    weight: Float[Array, " P"]


def geomorph_start(executed: Bool[Array, " P"]) -> Geomorph:
    """A geomorph at rest on an executed set (``Refinement.executed``)."""
    return Geomorph(weight=jnp.asarray(executed, jnp.float32))


@eqx.filter_jit
def geomorph_step(state: Geomorph, executed: Bool[Array, " P"], frames) -> Geomorph:
    """One frame toward a new executed set.

    Args:
        state: the current :class:`Geomorph`.
        executed: ``bool[P]`` this frame's hard refinement.
        frames: frames a full blend takes (``1`` = no geomorph: jump).

    Returns:
        the next :class:`Geomorph`.
    """
    rate = 1.0 / jnp.maximum(jnp.asarray(frames, jnp.float32), 1.0)
    target = jnp.asarray(executed, jnp.float32)
    return Geomorph(weight=state.weight + jnp.clip(target - state.weight, -rate, rate))


@eqx.filter_jit
def _blend(pm: ProgressiveMesh, weight, normals):
    k = pm.killer
    drawn = (k < 0) | (weight[jnp.maximum(k, 0)] < 1.0)
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
