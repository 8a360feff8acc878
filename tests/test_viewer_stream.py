"""The viewer draws each view's change written into its window's GPU buffers
in place: after each view the buffers hold the mesh stream's slots, and the
window shows what drawing each view's mesh anew shows (a real X window under
Xvfb, driven along a path with a cut and a wireframe interlude)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import pmjax

DRIVER = r'''
import sys, threading
import numpy as np
import pmjax
from OpenGL import GL
from pmjax.render._viewer import ViewerState, open_viewer

path, out, n, W, H = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
pm = pmjax.load(path)
v0 = np.asarray(pm.vertices)[: pm.n_original_vertices]
cams = pmjax.index_camera(pmjax.standard_orbit(v0, 2 * n, width=W, height=H), np.r_[0:n // 2, n + n // 2:2 * n])
grab, done = {"want": False}, threading.Event()

def read(buffer, nbytes):
    GL.glBindBuffer(GL.GL_COPY_READ_BUFFER, buffer)
    data = GL.glGetBufferSubData(GL.GL_COPY_READ_BUFFER, 0, nbytes)
    GL.glBindBuffer(GL.GL_COPY_READ_BUFFER, 0)
    return np.frombuffer(bytes(data), np.uint8)

def drawn(viewer):  # the window's thread, its context current, the scene drawn (no captions yet)
    if not grab["want"]:
        return
    grab["want"] = False
    GL.glReadBuffer(GL.GL_BACK)
    rgb = np.frombuffer(GL.glReadPixels(0, 0, W, H, GL.GL_RGB, GL.GL_UNSIGNED_BYTE), np.uint8).reshape(H, W, 3)
    depth = np.frombuffer(GL.glReadPixels(0, 0, W, H, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT), np.float32).reshape(H, W)
    got = dict(rgb=rgb.copy(), depth=depth.copy(), streamed=viewer.mesh._streamed)
    slots = viewer.mesh.slots
    if viewer.mesh._streamed:
        ids, faces = slots.stream.vertex_ids, slots.stream.faces
        got.update(ids=ids, faces=faces, primitive=id(slots.primitive), uploads=slots.uploads,
                   rows=read(slots.primitive._buffers[0], 24 * len(ids)),
                   tris=read(slots.primitive._buffers[-1], 12 * len(faces)))
    grab["got"] = got
    done.set()

def show(viewer, mesh, cam, wireframe=False):
    mesh.show(pmjax.refine(pm, cam, 1.0), viewer.render_lock, wireframe=wireframe)
    with viewer.render_lock:
        viewer._trackball._n_pose = np.asarray(cam.pose(), np.float64)  # pyrender's trackball: the view drawn
        done.clear()
        grab["want"] = True
    assert done.wait(60), "the window drew nothing"
    return grab["got"]

viewer, mesh, _ = open_viewer(pm, pmjax.index_camera(cams, 0), ViewerState(tau=1.0), drawn=drawn)
saved = {}
for name, stream in (("stream", True), ("anew", False)):
    mesh.stream = stream
    for i in range(n):
        if stream and i == n // 2 + 1:  # the wireframe overlay for a view: drawn anew, the stream left as it was
            assert not show(viewer, mesh, pmjax.index_camera(cams, i), wireframe=True)["streamed"]
        for k, val in show(viewer, mesh, pmjax.index_camera(cams, i)).items():
            saved[f"{name}_{i}_{k}"] = np.asarray(val)
viewer.close_external()
np.savez(out, **saved)
'''


@pytest.fixture(scope="module")
def cow(built, tmp_path_factory):
    data = built("cow.ply")
    path = str(tmp_path_factory.mktemp("viewer") / "cow.pmz")
    pmjax.save_pm(data, path)
    return path, pmjax.load(path)


@pytest.mark.skipif(not shutil.which("Xvfb"), reason="needs Xvfb")
@pytest.mark.slow
def test_viewer_writes_each_change_into_its_buffers(cow, tmp_path, xvfb_display):
    from pmjax.render._offscreen import shading_normals

    path, pm = cow
    n, W, H = 10, 200, 150
    driver, out = tmp_path / "drive.py", tmp_path / "seen.npz"
    driver.write_text(DRIVER)
    env = dict(os.environ, DISPLAY=xvfb_display)
    env.pop("PYOPENGL_PLATFORM", None)  # the viewer needs the X display, not EGL
    run = subprocess.run([sys.executable, str(driver), path, str(out), str(n), str(W), str(H)], env=env,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    seen = np.load(out)

    # The same refinements given to a stream of our own: the same slots.
    v0 = np.asarray(pm.vertices)[: pm.n_original_vertices]
    cams = pmjax.index_camera(pmjax.standard_orbit(v0, 2 * n, width=W, height=H), np.r_[0:n // 2, n + n // 2:2 * n])
    stream = pmjax.MeshStream(pm)
    primitives, covered = set(), []
    for i in range(n):
        stream.update(pmjax.refine(pm, pmjax.index_camera(cams, i), 1.0))
        ids, slots = seen[f"stream_{i}_ids"], seen[f"stream_{i}_faces"]
        assert bool(seen[f"stream_{i}_streamed"]) and not bool(seen[f"anew_{i}_streamed"])
        assert np.array_equal(ids, stream.vertex_ids) and np.array_equal(slots, stream.faces), i
        # The window's buffers hold the slots: position and normal rows per
        # vertex slot, a triangle per face slot (0, 0, 0 where free).
        rows = seen[f"stream_{i}_rows"].view(np.float32).reshape(-1, 6)
        live = ids >= 0
        assert np.array_equal(rows[live, :3], np.asarray(pm.vertices)[ids[live]]), i
        assert np.array_equal(rows[live, 3:], shading_normals(pm)[ids[live]]), i
        tris = seen[f"stream_{i}_tris"].view(np.uint32).reshape(-1, 3)
        assert np.array_equal(tris, np.maximum(slots, 0).astype(np.uint32)), i
        primitives.add(int(seen[f"stream_{i}_primitive"]))
        # The image of each view's mesh drawn anew: equal depth; colour may
        # differ only where two faces tie (drawn in another order).
        depth = seen[f"stream_{i}_depth"]
        assert np.array_equal(depth, seen[f"anew_{i}_depth"]), i
        assert np.count_nonzero(np.any(seen[f"stream_{i}_rgb"] != seen[f"anew_{i}_rgb"], axis=2)) <= 10, i
        covered.append(depth < 1)
    assert all(0.02 < c.mean() < 0.9 for c in covered)  # the model in view
    assert np.count_nonzero(covered[n // 2 - 1] != covered[n // 2]) > 100  # the cut: another view
    # Written in place: views past the first were uploads into existing
    # buffers; new buffers only for the first view and after the wireframe.
    assert int(seen[f"stream_{n - 1}_uploads"]) >= n - 3 and len(primitives) == 2
