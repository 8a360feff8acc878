"""pmjax.builders: batched progressive-mesh construction (GeMS × Visualizer).

Public API:
    build_pm, BuildOptions, METRIC_NAMES, vertex_normals, file_sha256
"""

from ._build import BuildOptions, build_pm, file_sha256, vertex_normals
from ._metrics import METRIC_NAMES

__all__ = ["BuildOptions", "build_pm", "file_sha256", "vertex_normals", "METRIC_NAMES"]
