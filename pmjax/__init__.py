"""pmjax: view-dependent refinement of progressive meshes with JAX.

A progressive mesh is the original mesh plus an ordered, batched list of
vertex-pair collapses (pcols). See ``docs/`` for the format and semantics.
"""

from ._meshio import CleanReport, MeshError, clean_mesh, default_model_path, load_clean_mesh, read_mesh
from ._pmfile import METRICS, PMData, PMFormatError, read_pm, save_pm, validate_pm
from ._invariants import check_invariants, direct_killers
from ._replay import active_faces, lod_mesh, mesh_for_executed, pcols_for_faces, prefix_executed, representatives
from ._distance import distance_to_surface, point_triangle_distance, sample_surface, surface_distance

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
    "check_invariants",
    "direct_killers",
    "active_faces",
    "lod_mesh",
    "mesh_for_executed",
    "pcols_for_faces",
    "prefix_executed",
    "representatives",
    "distance_to_surface",
    "point_triangle_distance",
    "sample_surface",
    "surface_distance",
]
__version__ = "0.1.0"
