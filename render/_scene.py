"""A pyrender scene for a refined mesh: smooth (Gouraud-like) shading, one
directional light at the eye, optional wireframe overlay, batch-level colours
and a camera frustum drawn as lines."""

from __future__ import annotations

import numpy as np

from pmjax import Camera, ProgressiveMesh

from ._gl import pyrender_module

BASE_COLOR = (0.72, 0.74, 0.78, 1.0)
EDGE_COLOR = (0.05, 0.05, 0.08, 1.0)
FRUSTUM_COLOR = (0.95, 0.15, 0.1, 1.0)
BACKGROUND = (1.0, 1.0, 1.0, 1.0)
AMBIENT = (0.12, 0.12, 0.12)


def vertex_normals(vertices, faces) -> np.ndarray:
    """Area-weighted unit vertex normals ``float32[V, 3]`` (zero for isolated vertices)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    n = np.zeros_like(v)
    if len(f):
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        for k in range(3):
            np.add.at(n, f[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(length > 0, length, 1.0)).astype(np.float32)


def batch_levels(pm: ProgressiveMesh, vertex_ids) -> np.ndarray:
    """How coarse each output vertex is: 0 for an original vertex, ``b + 1`` for
    one created in batch ``b`` (``vertex_ids`` from :meth:`Refinement.mesh`)."""
    ids = np.asarray(vertex_ids, np.int64)
    V0 = pm.n_original_vertices
    batch_of = np.searchsorted(np.asarray(pm.batch_offsets), np.maximum(ids - V0, 0), side="right")
    return np.where(ids >= V0, batch_of, 0)


LEVEL_BANDS = 8


def level_colors(levels, n_batches: int) -> np.ndarray:
    """``float32[N, 4]`` colours for levels: blue (original, fine) to red (coarsest batch)."""
    t = np.clip(np.asarray(levels, np.float64) / max(n_batches, 1), 0.0, 1.0)
    rgb = np.stack([0.15 + 0.8 * t, 0.35 + 0.3 * (1 - abs(2 * t - 1)), 0.95 - 0.8 * t], axis=1)
    return np.concatenate([rgb, np.ones((len(t), 1))], axis=1).astype(np.float32)


def face_levels(faces, vertex_levels) -> np.ndarray:
    """A face is as coarse as its coarsest corner."""
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    return np.asarray(vertex_levels)[f].max(axis=1) if len(f) else np.zeros(0, np.int64)


def pyrender_camera(camera: Camera):
    """The pyrender camera for one :class:`pmjax.Camera` (same fov, aspect, clip planes)."""
    pyrender = pyrender_module()
    near, far = float(camera.near), float(camera.far)
    if camera.orthographic:
        half = 0.5 * float(camera.ortho_height)
        return pyrender.OrthographicCamera(half * (int(camera.width) / int(camera.height)), half, znear=near, zfar=far)
    return pyrender.PerspectiveCamera(float(camera.fov_y), aspectRatio=(int(camera.width) / int(camera.height)),
                                      znear=near, zfar=far)


def mesh_node_geometry(vertices, faces, *, levels=None, n_batches=1, wireframe=False, normals=None):
    """A ``pyrender.Mesh`` of a triangle mesh with smooth per-vertex normals.

    Args:
        vertices: ``[V, 3]``; faces: ``[F, 3]``.
        levels: optional ``[F]`` batch level per face: the faces are drawn in
            :data:`LEVEL_BANDS` colour bands (one material each; pyrender's
            vertex colours bypass its lighting, so they are not used).
        n_batches: the level of the coarsest batch (colour scale).
        wireframe: draw the overlay edges instead of filled faces.
        normals: optional ``[V, 3]`` unit vertex normals (default: from the
            faces, area-weighted).
    """
    pyrender = pyrender_module()
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.uint32).reshape(-1, 3)
    normals = vertex_normals(v, f) if normals is None else np.asarray(normals, np.float32)

    def primitive(face_subset, color):
        material = pyrender.MetallicRoughnessMaterial(
            baseColorFactor=color, metallicFactor=0.0, roughnessFactor=0.9, doubleSided=True, wireframe=wireframe
        )
        return pyrender.Primitive(positions=v, normals=normals, indices=face_subset, material=material,
                                  mode=pyrender.GLTF.TRIANGLES)

    if wireframe:
        return pyrender.Mesh([primitive(f, EDGE_COLOR)])
    if levels is None:
        return pyrender.Mesh([primitive(f, BASE_COLOR)])
    band = np.minimum((np.asarray(levels) * LEVEL_BANDS) // max(n_batches, 1), LEVEL_BANDS - 1)
    prims = []
    for b in np.unique(band):
        color = level_colors([(b + 0.5) * max(n_batches, 1) / LEVEL_BANDS], n_batches)[0]
        prims.append(primitive(f[band == b], tuple(float(c) for c in color)))
    return pyrender.Mesh(prims)


def frustum_lines(camera: Camera, depth: float) -> np.ndarray:
    """Line segments ``float32[16, 3]`` (8 pairs) outlining ``camera``'s view
    pyramid from the eye to ``depth`` along the view direction."""
    R = np.asarray(camera.rotation, np.float64)
    eye = np.asarray(camera.eye, np.float64)
    right, up, fwd = R[:, 0], R[:, 1], -R[:, 2]
    if camera.orthographic:
        hy = 0.5 * float(camera.ortho_height)
        hx = hy * (int(camera.width) / int(camera.height))
        near_c = [eye + sx * hx * right + sy * hy * up for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    else:
        hy = np.tan(0.5 * float(camera.fov_y)) * depth
        hx = hy * (int(camera.width) / int(camera.height))
        near_c = [eye] * 4
    far_c = [eye + depth * fwd + sx * hx * right + sy * hy * up for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    segs = []
    for i in range(4):
        segs += [near_c[i], far_c[i], far_c[i], far_c[(i + 1) % 4]]
    return np.asarray(segs, np.float32)


def frustum_past_model(pm: ProgressiveMesh, camera: Camera) -> np.ndarray:
    """:func:`frustum_lines` of ``camera`` reaching just past the farthest
    original vertex, so the whole model lies inside the drawn pyramid."""
    verts = np.asarray(pm.vertices)[: pm.n_original_vertices]
    reach = float(np.linalg.norm(verts - np.asarray(camera.eye), axis=1).max())
    return frustum_lines(camera, reach)


def new_scene():
    """An empty ``pyrender.Scene`` with the project's background and ambient light."""
    return pyrender_module().Scene(bg_color=BACKGROUND, ambient_light=AMBIENT)


def place_view(scene, camera: Camera, held=(), *, light: bool = True) -> tuple:
    """Put ``camera`` in ``scene`` with (``light``) one directional light at
    the eye, after removing the nodes ``held`` (a previous view's; None
    entries skipped), so one scene can be drawn from view after view.

    Returns:
        ``(camera node, light node or None)``.
    """
    pyrender = pyrender_module()
    for node in held:
        if node is not None:
            scene.remove_node(node)
    pose = camera.pose()
    camera_node = scene.add(pyrender_camera(camera), pose=pose, name="camera")
    light_node = (scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=3.0), pose=pose, name="light")
                  if light else None)
    return camera_node, light_node


def build_scene(vertices, faces, camera: Camera, *, levels=None, n_batches=1, wireframe=False, extra_lines=None,
                light=True, normals=None):
    """Scene with the mesh, an optional wireframe overlay, optional line
    segments (``[2n, 3]``), the camera and (``light``) one directional light at the eye.

    Returns:
        ``(scene, mesh_nodes)``; ``mesh_nodes`` can be swapped for a new refinement.
    """
    scene = new_scene()
    nodes = add_mesh(scene, vertices, faces, levels=levels, n_batches=n_batches, wireframe=wireframe, normals=normals)
    if extra_lines is not None and len(extra_lines):
        scene.add(lines_mesh(extra_lines), name="frustum")
    place_view(scene, camera, light=light)
    return scene, nodes


def add_mesh(scene, vertices, faces, *, levels=None, n_batches=1, wireframe=False, normals=None) -> list:
    """Add the shaded mesh (and the overlay) to ``scene``; returns the new nodes."""
    nodes = []
    if len(np.asarray(faces).reshape(-1, 3)):
        geometry = mesh_node_geometry(vertices, faces, levels=levels, n_batches=n_batches, normals=normals)
        nodes.append(scene.add(geometry, name="mesh"))
        if wireframe:
            nodes.append(scene.add(mesh_node_geometry(vertices, faces, wireframe=True), name="wireframe"))
    return nodes


def lines_mesh(segments):
    """A ``pyrender.Mesh`` of red line segments (``[2n, 3]``, pairs of endpoints)."""
    pyrender = pyrender_module()
    material = pyrender.MetallicRoughnessMaterial(baseColorFactor=FRUSTUM_COLOR, emissiveFactor=FRUSTUM_COLOR[:3])
    return pyrender.Mesh([pyrender.Primitive(positions=np.asarray(segments, np.float32), mode=pyrender.GLTF.LINES,
                                             material=material)])
