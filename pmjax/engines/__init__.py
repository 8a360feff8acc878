"""The refinement engines behind one seam.

- ``_dense``: every pcol tested, the decisions propagated batch by batch (JAX
  kernels; the reference and the GPU path);
- ``_core``: the front engine's C core (``core/``, API in ``core/pmx.h``) as
  XLA FFI calls on the CPU;
- ``_front_jax``: the front engine as JAX kernels, where the core is not built.

:func:`select` is the one place that decides which engine a call uses
(``pmjax.refine`` and every other call go through it); the front engines'
tables are derived from a mesh's arrays and cached under their contents
(:func:`derived`). :func:`info` says what is active here.
"""

from ._choose import FRONT_BATCH_FROM_PCOLS, FRONT_FROM_PCOLS, METHODS, info, is_traced, select, without_core
from ._core import built as core_built
from ._core import enabled as core_enabled
from ._core import mesh_ranks, simd, simd_best
from ._tables import derived

__all__ = ["FRONT_BATCH_FROM_PCOLS", "FRONT_FROM_PCOLS", "METHODS", "core_built", "core_enabled", "derived", "info",
           "is_traced", "mesh_ranks", "select", "simd", "simd_best", "without_core"]
