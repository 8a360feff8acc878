"""Loading a ``.pmz`` file onto the JAX device, checked."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ._model import ProgressiveMesh
from ._pmfile import read_arrays
from ._structure import NestingCheck, check_normals, check_structure, remember_structure, structure_known
from ._subtree import subtree_bounds
from ._units import host_lengths_in_model_units, unit_exponent
from .engines._tables import derived


def load(path, *, batches: int | None = None) -> ProgressiveMesh:
    """Read, validate and move a ``.pmz`` file to the JAX device.

    Args:
        path: a ``.pmz`` file, or a binary file object reading one.
        batches: read only the base mesh and the ``batches`` coarsest batches
            (a version 2 file is read only that far); see :func:`pmjax.read_pm`.

    Raises:
        PMFormatError: see :func:`pmjax.read_pm`.
    """
    data, fingerprint = read_arrays(path, batches=batches, call="load")
    pm = ProgressiveMesh.from_data(data)
    if structure_known(fingerprint):
        return pm
    source = str(getattr(path, "name", "<stream>")) if hasattr(path, "read") else os.fspath(path)
    # The structure check runs beside the subtree bounds (both mostly NumPy,
    # which releases the GIL), and the attributes' nesting inside the bounds'
    # pass, which gathers the same parent-child pairs; the bounds are then
    # the front engines' (kept with the mesh's derived tables). validate_pm
    # has already bounded every index, so the pass is safe on a forged file.
    check_normals(data, source)
    # The bounds are the tables', so in model units (pmjax._units).
    attrs = pm.attributes
    host = {k: np.asarray(getattr(attrs, k)) for k in ("center", "axis", "sin_alpha", "cos_alpha")}
    host.update(radius=data.radius, delta=data.delta, mu=data.mu)
    exponent = unit_exponent(data.radius)
    host = host_lengths_in_model_units(host, exponent)
    with ThreadPoolExecutor(max_workers=1) as pool:
        check = pool.submit(check_structure, data, source=source, threads=1, nesting=False)
        bounds = subtree_bounds(host["center"].T, host["axis"].T, host["radius"], host["sin_alpha"], host["cos_alpha"],
                                host["delta"], host["mu"], np.asarray(pm.child1), np.asarray(pm.child2),
                                data.batch_offsets, nesting=NestingCheck(data, source, exponent))
        check.result()
    remember_structure(fingerprint)
    derived(pm).seed_bounds(bounds)
    return pm
