"""A progressive mesh as host (NumPy) arrays, and the error of a bad one."""

from __future__ import annotations

import dataclasses

import numpy as np

# name -> (dtype, shape in terms of the counts V (all vertices), V0, F, P, B1)
ARRAY_SPECS: dict[str, tuple[str, tuple[str, ...]]] = {
    "vertices": ("float32", ("V", "3")),
    "normals": ("float32", ("V", "3")),
    "faces": ("int32", ("F", "3")),
    "v1": ("int32", ("P",)),
    "v2": ("int32", ("P",)),
    "radius": ("float32", ("P",)),
    "alpha": ("float32", ("P",)),
    "delta": ("float32", ("P",)),
    "mu": ("float32", ("P",)),
    "cost": ("float64", ("P",)),
    "metric": ("uint8", ("P",)),
    "batch_offsets": ("int64", ("B1",)),
    "killer": ("int32", ("F",)),
}

# Arrays a file may hold or omit (files written before they existed still
# read): name -> (dtype, shape), as ARRAY_SPECS.
OPTIONAL_ARRAY_SPECS: dict[str, tuple[str, tuple[str, ...]]] = {
    # Unit shading normals fitted to the original surface (pmjax.fitted_normals);
    # zero for a vertex with no face area below it.
    "shading_normals": ("float32", ("V", "3")),
}

# Metric ids stored per pcol.
METRICS = ("quadric", "quadric-memoryless", "edge", "pm", "hybrid")


class PMFormatError(ValueError):
    """A ``.pmz`` file is missing, truncated, forged or inconsistent."""


@dataclasses.dataclass(frozen=True, eq=False)
class PMData:
    """A progressive mesh as host (NumPy) arrays; see ``docs/format.md``.

    Vertices ``0..V0-1`` are the original mesh; pcol ``p`` creates vertex
    ``V0 + p``. Pcols are sorted fine-to-coarse, batch by batch, and
    ``batch_offsets[b]:batch_offsets[b+1]`` is batch ``b``.
    """

    vertices: np.ndarray  # float32[V0+P, 3]
    normals: np.ndarray  # float32[V0+P, 3], unit
    faces: np.ndarray  # int32[F, 3], original vertex ids
    v1: np.ndarray  # int32[P]
    v2: np.ndarray  # int32[P]
    radius: np.ndarray  # float32[P], bounding-sphere radius (model units)
    alpha: np.ndarray  # float32[P], normal-cone half-angle (radians)
    delta: np.ndarray  # float32[P], deviation along the normal (model units)
    mu: np.ndarray  # float32[P], uniform deviation (model units)
    cost: np.ndarray  # float64[P], metric cost when collapsed
    metric: np.ndarray  # uint8[P], index into METRICS
    batch_offsets: np.ndarray  # int64[B+1]
    killer: np.ndarray  # int32[F], pcol that removes the face, -1 if none
    header: dict = dataclasses.field(default_factory=dict)
    shading_normals: np.ndarray | None = None  # float32[V0+P, 3], unit or zero; optional


    @property
    def n_original_vertices(self) -> int:
        return int(len(self.vertices) - len(self.v1))

    @property
    def n_pcols(self) -> int:
        return int(len(self.v1))

    @property
    def n_batches(self) -> int:
        return int(len(self.batch_offsets) - 1)

    @property
    def kills(self) -> np.ndarray:
        """int64[P]: faces each pcol removes (derived from ``killer``)."""
        return np.bincount(self.killer[self.killer >= 0], minlength=self.n_pcols)

    def arrays(self) -> dict[str, np.ndarray]:
        """All arrays by name, in :data:`ARRAY_SPECS` order, then the optional
        ones present (:data:`OPTIONAL_ARRAY_SPECS`)."""
        out = {name: getattr(self, name) for name in ARRAY_SPECS}
        out.update({name: getattr(self, name) for name in OPTIONAL_ARRAY_SPECS if getattr(self, name) is not None})
        return out
