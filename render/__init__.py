"""pmjax.render: pyrender display of refinement results.

Headless rendering (EGL by default, or ``PYOPENGL_PLATFORM=osmesa``) of single
views, camera paths (MP4/GIF/PNG), the paper's figures and image-space
fidelity; an interactive viewer under a display. pyrender is imported lazily.
"""

from ._gl import RenderError, pyrender_module
from ._scene import (
    batch_levels,
    build_scene,
    face_levels,
    frustum_lines,
    frustum_past_model,
    level_colors,
    vertex_normals,
)
from ._offscreen import (
    Renderer,
    NORMALS,
    SlotMesh,
    StreamScene,
    check_frames_output,
    check_normals,
    original_arrays,
    path_geometry,
    refined_arrays,
    render_path,
    render_refinement,
    view_normals,
    write_frames,
    write_png,
)
from ._fidelity import DIFF_THRESHOLD, camera_fidelity, flip_difference, image_difference, path_fidelity, silhouette_difference
from ._figures import FIGURES, overview_camera, paper_figures, phantom
from ._viewer import KEYS, ViewerMesh, ViewerState, camera_from_pose, open_viewer, run_viewer

__all__ = [
    "RenderError",
    "pyrender_module",
    "batch_levels",
    "build_scene",
    "face_levels",
    "frustum_lines",
    "frustum_past_model",
    "level_colors",
    "vertex_normals",
    "Renderer",
    "NORMALS",
    "SlotMesh",
    "StreamScene",
    "check_frames_output",
    "check_normals",
    "original_arrays",
    "path_geometry",
    "refined_arrays",
    "render_path",
    "render_refinement",
    "view_normals",
    "write_frames",
    "write_png",
    "DIFF_THRESHOLD",
    "camera_fidelity",
    "flip_difference",
    "image_difference",
    "path_fidelity",
    "silhouette_difference",
    "FIGURES",
    "overview_camera",
    "paper_figures",
    "phantom",
    "KEYS",
    "ViewerMesh",
    "ViewerState",
    "camera_from_pose",
    "open_viewer",
    "run_viewer",
]
