"""pmjax: view-dependent refinement of progressive meshes with JAX.

A progressive mesh is the original mesh plus an ordered, batched list of
vertex-pair collapses (pcols). See ``docs/`` for the format and semantics.
"""

from ._meshio import CleanReport, MeshError, clean_mesh, default_model_path, load_clean_mesh, read_mesh
from ._pmfile import METRICS, PMData, PMFormatError, read_pm, save_pm, validate_pm

__all__ = [
    "CleanReport",
    "MeshError",
    "clean_mesh",
    "default_model_path",
    "load_clean_mesh",
    "read_mesh",
    "METRICS",
    "PMData",
    "PMFormatError",
    "read_pm",
    "save_pm",
    "validate_pm",
]
__version__ = "0.1.0"
