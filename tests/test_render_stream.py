"""Rendering along a path from GPU buffers updated in place by each frame's
change: the buffers hold the stream's slots, and the images are those of
each frame's mesh drawn anew (headless, for real)."""

import numpy as np
import pytest

import pmjax



@pytest.fixture(scope="module")
def cow(built):
    data = built("cow.ply")
    return data, pmjax.ProgressiveMesh.from_data(data)


def orbit_with_cut(data, n=20, size=(200, 150)):
    """The standard orbit, jumping half-way round at frame n // 2."""
    v0 = data.vertices[: data.n_original_vertices]
    cams = pmjax.standard_orbit(v0, 2 * n, width=size[0], height=size[1])
    frames = np.r_[0:n // 2, n + n // 2:2 * n]
    return pmjax.index_camera(cams, frames), len(frames)


def read_buffer(buffer, nbytes):
    from OpenGL import GL

    GL.glBindBuffer(GL.GL_COPY_READ_BUFFER, buffer)
    out = GL.glGetBufferSubData(GL.GL_COPY_READ_BUFFER, 0, nbytes)
    GL.glBindBuffer(GL.GL_COPY_READ_BUFFER, 0)
    return np.frombuffer(bytes(out), np.uint8)


def test_stream_scene_buffers_and_images_follow_the_path(cow):
    from pmjax.render import Renderer, render_refinement
    from pmjax.render._offscreen import StreamScene, shading_normals

    data, pm = cow
    cams, n = orbit_with_cut(data)
    refinements = list(pmjax.refine_path(pm, cams, 1.0))
    with Renderer(200, 150) as renderer:
        scene = StreamScene(renderer, pm)
        images, uploads, primitives = [], 0, set()
        for i, r in enumerate(refinements):
            change = scene.update(r)
            images.append(scene.render(pmjax.index_camera(cams, i)))
            primitives.add(id(scene._primitive))
            if i and scene._primitive._vaid is not None and len(change.face_slots):
                uploads += 1
            # The GPU's buffers hold the stream's slots: rows of position and
            # normal per vertex slot, a triangle per face slot (0, 0, 0 if free).
            vertex_buffer, index_buffer = scene._primitive._buffers[0], scene._primitive._buffers[-1]
            ids, slots = scene.stream.vertex_ids, scene.stream.faces
            rows = read_buffer(vertex_buffer, 24 * len(ids)).view(np.float32).reshape(-1, 6)
            live = ids >= 0
            assert np.array_equal(rows[live, :3], np.asarray(pm.vertices)[ids[live]]), i
            assert np.array_equal(rows[live, 3:], shading_normals(pm)[ids[live]]), i
            tris = read_buffer(index_buffer, 12 * len(slots)).view(np.uint32).reshape(-1, 3)
            assert np.array_equal(tris, np.maximum(slots, 0).astype(np.uint32)), i
        # The buffers were written in place, not made again (but when the slots outgrow them).
        assert uploads >= n - 2 and len(primitives) <= 2
        # The same images as each frame's mesh drawn anew: equal depth; colour
        # may differ only where two faces tie (drawn in another order).
        for i, r in enumerate(refinements):
            rgb, depth = render_refinement(renderer, pm, r, pmjax.index_camera(cams, i), normals="stored")
            assert np.array_equal(depth, images[i][1]), i
            assert np.count_nonzero(np.any(rgb != images[i][0], axis=2)) <= 10, i


@pytest.mark.parametrize("normals", ["stored", "view"])
def test_render_path_draws_from_the_stream(cow, tmp_path, normals):
    """pmjax render's path: the frames written are the stream scene's, with
    the stored normals or those fitted per view on its live slots: the same
    images as each frame's refinement drawn anew with them."""
    from pmjax.render import Renderer, render_path, render_refinement

    data, pm = cow
    cams, n = orbit_with_cut(data, n=8)
    out = tmp_path / "frames"
    result = render_path(pm, cams, 1.0, str(out), progress=False, normals=normals)
    assert result["frames"] == n
    assert result["faces"].tolist() == [int(r.n_faces) for r in pmjax.refine_path(pm, cams, 1.0)]
    import imageio.v3 as iio

    files = sorted(out.iterdir())
    assert len(files) == n
    with Renderer(200, 150) as renderer:
        for i, (f, r) in enumerate(zip(files, pmjax.refine_path(pm, cams, 1.0))):
            want, _ = render_refinement(renderer, pm, r, pmjax.index_camera(cams, i), normals=normals)
            assert np.count_nonzero(np.any(iio.imread(f)[..., :3] != want, axis=2)) <= 10, i
            other, _ = render_refinement(renderer, pm, r, pmjax.index_camera(cams, i),
                                         normals="view" if normals == "stored" else "stored")
            assert np.count_nonzero(np.any(iio.imread(f)[..., :3] != other, axis=2)) > 10, i
