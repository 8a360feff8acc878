"""pmjax: view-dependent refinement of progressive meshes with JAX.

A progressive mesh is the original mesh plus an ordered, batched list of
vertex-pair collapses (pcols). See ``docs/`` for the format and semantics.
"""

from ._meshfiles import MeshError, read_mesh
from ._meshio import CleanReport, clean_mesh, default_model_path, load_clean_mesh
from ._pmfile import METRICS, PMData, PMFormatError, read_arrays, read_pm, save_pm, validate_pm
from ._structure import check_structure, structure_known
from ._invariants import check_invariants, direct_killers
from ._levels import dependency_levels
from ._replay import active_faces, lod_mesh, mesh_for_executed, pcols_for_faces, prefix_executed, representatives
from ._camera import Camera, camera_count, fly_through, index_camera, load_cameras, look_at, save_cameras, stack_cameras
from ._camera_sets import random_views, standard_orbit
from ._model import PcolAttributes, ProgressiveMesh
from ._load import load
from ._view import kappa
from ._predicate import ALL_TESTS, Tests, collapse_mask, critical_tau, oriented_away, outside_frustum, small_on_screen
from ._refine import Refinement, critical_tolerances, faces_for_budget, propagate, refine, refine_batch
from .engines import core_enabled as native_available
from .engines import info as engine_info
from ._path import PathError, path_counts, refine_path
from ._oracle import oracle_refine
from ._soft import SoftRefinement, geomorph_blend, geomorph_positions, soft_refine, soft_tests, soft_weights
from ._normals import hierarchy_normals
from ._budget import BudgetSolution, soft_tau_for_budget
from ._geomorph import Geomorph, geomorph_mesh, geomorph_start, geomorph_step, hidden_pcols
from ._camera_table import CameraError, CameraTable, read_camera_table, table_from_cameras, write_camera_table
from ._eval import CameraSet, EvalError, EvalSummary, camera_set, evaluate
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
    "camera_count",
    "index_camera",
    "save_pm",
    "validate_pm",
    "check_invariants",
    "check_structure",
    "read_arrays",
    "structure_known",
    "direct_killers",
    "dependency_levels",
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
    "Camera",
    "fly_through",
    "load_cameras",
    "look_at",
    "random_views",
    "save_cameras",
    "stack_cameras",
    "CameraError",
    "CameraTable",
    "read_camera_table",
    "table_from_cameras",
    "write_camera_table",
    "CameraSet",
    "EvalError",
    "EvalSummary",
    "camera_set",
    "evaluate",
    "standard_orbit",
    "PcolAttributes",
    "ProgressiveMesh",
    "load",
    "ALL_TESTS",
    "Tests",
    "collapse_mask",
    "critical_tau",
    "kappa",
    "oriented_away",
    "outside_frustum",
    "small_on_screen",
    "Refinement",
    "critical_tolerances",
    "faces_for_budget",
    "propagate",
    "refine",
    "native_available",
    "engine_info",
    "refine_batch",
    "refine_path",
    "path_counts",
    "PathError",
    "oracle_refine",
    "SoftRefinement",
    "geomorph_blend",
    "geomorph_positions",
    "hierarchy_normals",
    "soft_refine",
    "soft_tests",
    "soft_weights",
    "BudgetSolution",
    "soft_tau_for_budget",
    "Geomorph",
    "geomorph_mesh",
    "geomorph_start",
    "geomorph_step",
    "hidden_pcols",
]
__version__ = "0.1.0"
