"""pmjax: view-dependent refinement of progressive meshes with JAX.

A progressive mesh is the original mesh plus an ordered, batched list of
vertex-pair collapses (pcols). See ``docs/`` for the format and semantics.

The public names are imported when first used (``pmjax.refine`` imports JAX and
the engines then), so ``import pmjax`` and the command line's help and argument
errors cost no JAX start-up.
"""

from __future__ import annotations

import importlib
import importlib.util
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names as a type checker and an editor see them
    from ._meshfiles import MeshError, read_mesh
    from ._meshio import CleanReport, clean_mesh, default_model_path, load_clean_mesh
    from ._pmfile import METRICS, PMData, PMFormatError, read_arrays, read_pm, save_pm, validate_pm
    from ._structure import check_structure, structure_known
    from ._invariants import check_invariants, direct_killers
    from ._levels import dependency_levels
    from ._replay import active_faces, lod_mesh, mesh_for_executed, pcols_for_faces, prefix_executed, representatives
    from ._camera import Camera, camera_count, fly_through, index_camera, look_at, stack_cameras
    from ._camera_files import load_cameras, save_cameras
    from ._camera_sets import random_views, standard_orbit
    from ._model import PcolAttributes, ProgressiveMesh
    from ._load import load
    from ._view import kappa
    from ._predicate import ALL_TESTS, Tests, collapse_mask, critical_tau, oriented_away, outside_frustum, small_on_screen
    from ._refine import (Refinement, critical_tolerances, faces_for_budget, faces_for_budget_batch, propagate, refine,
                          refine_batch)
    from .engines import core_enabled as native_available
    from .engines import info as engine_info
    from ._path import MeshChange, MeshStream, PathError, path_counts, path_mesh_changes, refine_path
    from ._oracle import oracle_refine
    from ._soft import SoftRefinement, geomorph_blend, geomorph_positions, soft_refine, soft_tests, soft_weights
    from ._normals import fitted_normals, hierarchy_normals
    from ._view_normals import ViewNormals
    from ._budget import BudgetSolution, soft_tau_for_budget
    from ._geomorph import Geomorph, geomorph_mesh, geomorph_start, geomorph_step, hidden_pcols
    from ._camera_table import CameraError, CameraTable, read_camera_table, table_from_cameras, write_camera_table
    from ._eval import CameraSet, EvalError, EvalInterrupted, EvalSummary, camera_set, evaluate
    from ._eval import read_job as read_eval_job
    from ._eval import CompactSummary, compact as compact_eval
    from ._cluster import slurm_cluster
    from ._distance import distance_to_surface, point_triangle_distance, sample_surface, surface_distance

# Public name -> (module, name in it).
_EXPORTS = {
    "CleanReport": ("._meshio", "CleanReport"),
    "MeshError": ("._meshfiles", "MeshError"),
    "clean_mesh": ("._meshio", "clean_mesh"),
    "default_model_path": ("._meshio", "default_model_path"),
    "load_clean_mesh": ("._meshio", "load_clean_mesh"),
    "read_mesh": ("._meshfiles", "read_mesh"),
    "METRICS": ("._pmfile", "METRICS"),
    "PMData": ("._pmfile", "PMData"),
    "PMFormatError": ("._pmfile", "PMFormatError"),
    "read_arrays": ("._pmfile", "read_arrays"),
    "read_pm": ("._pmfile", "read_pm"),
    "save_pm": ("._pmfile", "save_pm"),
    "validate_pm": ("._pmfile", "validate_pm"),
    "check_structure": ("._structure", "check_structure"),
    "structure_known": ("._structure", "structure_known"),
    "check_invariants": ("._invariants", "check_invariants"),
    "direct_killers": ("._invariants", "direct_killers"),
    "dependency_levels": ("._levels", "dependency_levels"),
    "active_faces": ("._replay", "active_faces"),
    "lod_mesh": ("._replay", "lod_mesh"),
    "mesh_for_executed": ("._replay", "mesh_for_executed"),
    "pcols_for_faces": ("._replay", "pcols_for_faces"),
    "prefix_executed": ("._replay", "prefix_executed"),
    "representatives": ("._replay", "representatives"),
    "Camera": ("._camera", "Camera"),
    "camera_count": ("._camera", "camera_count"),
    "fly_through": ("._camera", "fly_through"),
    "index_camera": ("._camera", "index_camera"),
    "load_cameras": ("._camera_files", "load_cameras"),
    "look_at": ("._camera", "look_at"),
    "save_cameras": ("._camera_files", "save_cameras"),
    "stack_cameras": ("._camera", "stack_cameras"),
    "random_views": ("._camera_sets", "random_views"),
    "standard_orbit": ("._camera_sets", "standard_orbit"),
    "PcolAttributes": ("._model", "PcolAttributes"),
    "ProgressiveMesh": ("._model", "ProgressiveMesh"),
    "load": ("._load", "load"),
    "kappa": ("._view", "kappa"),
    "ALL_TESTS": ("._predicate", "ALL_TESTS"),
    "Tests": ("._predicate", "Tests"),
    "collapse_mask": ("._predicate", "collapse_mask"),
    "critical_tau": ("._predicate", "critical_tau"),
    "oriented_away": ("._predicate", "oriented_away"),
    "outside_frustum": ("._predicate", "outside_frustum"),
    "small_on_screen": ("._predicate", "small_on_screen"),
    "Refinement": ("._refine", "Refinement"),
    "critical_tolerances": ("._refine", "critical_tolerances"),
    "faces_for_budget": ("._refine", "faces_for_budget"),
    "faces_for_budget_batch": ("._refine", "faces_for_budget_batch"),
    "propagate": ("._refine", "propagate"),
    "refine": ("._refine", "refine"),
    "refine_batch": ("._refine", "refine_batch"),
    "native_available": (".engines", "core_enabled"),
    "engine_info": (".engines", "info"),
    "PathError": ("._path", "PathError"),
    "path_counts": ("._path", "path_counts"),
    "refine_path": ("._path", "refine_path"),
    "MeshChange": ("._path", "MeshChange"),
    "MeshStream": ("._path", "MeshStream"),
    "path_mesh_changes": ("._path", "path_mesh_changes"),
    "oracle_refine": ("._oracle", "oracle_refine"),
    "SoftRefinement": ("._soft", "SoftRefinement"),
    "geomorph_blend": ("._soft", "geomorph_blend"),
    "geomorph_positions": ("._soft", "geomorph_positions"),
    "soft_refine": ("._soft", "soft_refine"),
    "soft_tests": ("._soft", "soft_tests"),
    "soft_weights": ("._soft", "soft_weights"),
    "hierarchy_normals": ("._normals", "hierarchy_normals"),
    "fitted_normals": ("._normals", "fitted_normals"),
    "ViewNormals": ("._view_normals", "ViewNormals"),
    "BudgetSolution": ("._budget", "BudgetSolution"),
    "soft_tau_for_budget": ("._budget", "soft_tau_for_budget"),
    "Geomorph": ("._geomorph", "Geomorph"),
    "geomorph_mesh": ("._geomorph", "geomorph_mesh"),
    "geomorph_start": ("._geomorph", "geomorph_start"),
    "geomorph_step": ("._geomorph", "geomorph_step"),
    "hidden_pcols": ("._geomorph", "hidden_pcols"),
    "CameraError": ("._camera_table", "CameraError"),
    "CameraTable": ("._camera_table", "CameraTable"),
    "read_camera_table": ("._camera_table", "read_camera_table"),
    "table_from_cameras": ("._camera_table", "table_from_cameras"),
    "write_camera_table": ("._camera_table", "write_camera_table"),
    "CameraSet": ("._eval", "CameraSet"),
    "EvalError": ("._eval", "EvalError"),
    "EvalInterrupted": ("._eval", "EvalInterrupted"),
    "read_eval_job": ("._eval", "read_job"),
    "compact_eval": ("._eval", "compact"),
    "CompactSummary": ("._eval", "CompactSummary"),
    "EvalSummary": ("._eval", "EvalSummary"),
    "camera_set": ("._eval", "camera_set"),
    "evaluate": ("._eval", "evaluate"),
    "slurm_cluster": ("._cluster", "slurm_cluster"),
    "distance_to_surface": ("._distance", "distance_to_surface"),
    "point_triangle_distance": ("._distance", "point_triangle_distance"),
    "sample_surface": ("._distance", "sample_surface"),
    "surface_distance": ("._distance", "surface_distance"),
}
# Subpackages reachable as attributes (``pmjax.engines.info()``).
_SUBPACKAGES = ("engines", "builders", "render")


def __getattr__(name: str):
    if name in _EXPORTS:
        module, attribute = _EXPORTS[name]
        value = getattr(importlib.import_module(module, __name__), attribute)
    elif name in _SUBPACKAGES or (name.startswith("_") and not name.startswith("__")
                                  and importlib.util.find_spec(f"{__name__}.{name}") is not None):
        value = importlib.import_module(f"{__name__}.{name}")  # a submodule, as after importing it
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # imported once
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS) | set(_SUBPACKAGES))


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
    "EvalInterrupted",
    "read_eval_job",
    "compact_eval",
    "CompactSummary",
    "EvalSummary",
    "camera_set",
    "evaluate",
    "slurm_cluster",
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
    "faces_for_budget_batch",
    "propagate",
    "refine",
    "native_available",
    "engine_info",
    "refine_batch",
    "refine_path",
    "path_counts",
    "PathError",
    "MeshChange",
    "MeshStream",
    "path_mesh_changes",
    "oracle_refine",
    "SoftRefinement",
    "geomorph_blend",
    "geomorph_positions",
    "hierarchy_normals",
    "fitted_normals",
    "ViewNormals",
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
