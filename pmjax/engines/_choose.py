"""Which engine a call uses: the one place that decides.

Three engines give the same bits (docs/design.md):

- ``"dense"``: every pcol tested, the decisions propagated batch by batch
  (JAX kernels; the reference, and the engine of GPUs);
- ``"core"``: the front engine's C core as XLA FFI calls on the CPU (its
  cost follows the refined mesh);
- ``"jax"``: the front engine as JAX kernels, where the core is not built
  (eager calls only: its buffers adapt between calls).

The choice depends on the method asked for, the platform, whether the mesh
is being traced (a mesh passed as an argument of a compiled function has no
contents to derive the front engine's tables from; a closed-over mesh has),
whether the call is being traced, and what is built.
"""

from __future__ import annotations

import weakref

import jax
from jax._src.core import trace_state_clean

from ._switch import core_allowed, without_core  # noqa: F401 (re-exported)
from ._tables import has_contents
from . import _core

METHODS = ("auto", "front", "dense")

# "auto" picks the front engine where it is faster (docs/front.md): with the
# core, for one camera on every hierarchy, and for camera
# batches from FRONT_BATCH_FROM_PCOLS on (smaller batches run faster dense);
# as JAX kernels, for one camera only from FRONT_FROM_PCOLS on, and never for
# batches.
FRONT_FROM_PCOLS = 100_000
FRONT_BATCH_FROM_PCOLS = 30_000

def platform_of(pm) -> str:
    """Where ``pm``'s arrays live (the default backend for traced ones)."""
    x = pm.vertices
    if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer):
        return next(iter(x.devices())).platform
    return jax.default_backend()


def is_traced(*trees) -> bool:
    """Whether any leaf of ``trees`` is a tracer (none outside every ``jit``,
    ``vmap`` and ``grad``: then no leaf is looked at)."""
    if trace_state_clean():
        return False
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trees))


# What select reads of the last mesh asked about: whether its arrays are
# known, and where they live (fixed for a mesh object).
_facts_of = (None, None)


def _facts(pm) -> tuple:
    global _facts_of
    ref, facts = _facts_of
    if ref is not None and ref() is pm:
        return facts
    facts = (has_contents(pm), platform_of(pm) if has_contents(pm) else jax.default_backend())
    _facts_of = (weakref.ref(pm), facts)
    return facts


def select(pm, method: str = "auto", *, predicate=None, batch: bool = False, traced: bool = False) -> str:
    """The engine of a call: ``"dense"``, ``"core"`` or ``"jax"``.

    Args:
        pm: the :class:`pmjax.ProgressiveMesh` refined.
        method: ``"auto"``, ``"front"`` or ``"dense"``.
        predicate: a user predicate (only the dense engine applies one: it
            has no subtree bound).
        batch: a camera batch (else one camera).
        traced: the call's cameras or tolerance are being traced (``jit``,
            ``vmap``), so the engine must be a JAX function.

    Raises:
        ValueError: an unknown method; ``"front"`` with a user predicate.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "front" and predicate is not None:
        raise ValueError("method='front' cannot apply a user predicate (it has no subtree bound); "
                         "use method='dense' or 'auto'")
    if method == "dense" or predicate is not None or pm.n_pcols == 0:
        return "dense"
    contents, platform = _facts(pm)
    # The front engines derive tables from the mesh's contents.
    if not contents:
        return "dense"
    if _core.enabled() and platform == "cpu":
        if method == "front" or not batch or pm.n_pcols >= FRONT_BATCH_FROM_PCOLS:
            return "core"
        return "dense"
    # The JAX front engine adapts its buffers on the host between calls.
    if traced:
        return "dense"
    if method == "front" or (not batch and pm.n_pcols >= FRONT_FROM_PCOLS):
        return "jax"
    return "dense"


def info() -> dict:
    """What is active here: ``{"dense": ..., "core": ..., "jax": ...}``, each
    a line that says where it runs or why it does not."""
    backend = jax.default_backend()
    if _core.built():
        core = f"C core as XLA FFI targets, CPU, SIMD kernels {_core.simd()} (best here: {_core.simd_best()})"
        if not _core.enabled():
            core += "; switched off (PMJAX_NATIVE=0)"
    else:
        core = f"not built ({_core.LOAD_ERROR}); refinement runs on the dense engine"
    return {"dense": f"JAX kernels, {backend}", "core": core,
            "jax": "JAX kernels, eager single cameras where the core is not built"}
