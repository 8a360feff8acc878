"""Camera-path benchmark: coherent paths (consecutive frames per word) against per-frame refines.

Usage: python benchmarks/path.py [--models cow,bunny,terrain_gcanyon,terrain_sthelens,dragon]
       [--frames 240] [--tau 1] [--paths 256] [--many-model dragon] [--repeats 3] [--json FILE]
       python benchmarks/path.py --mesh [--mesh-models bunny,dragon] [--frames 240] [--tau 1] [--repeats 9]
              [--srmesh benchmarks/.cache/srmesh/bin/srmesh_adapt]
       python benchmarks/path.py --draw [--draw-model dragon] [--frames 240] [--tau 1] [--repeats 3]
       xvfb-run -a python benchmarks/path.py --viewer [--draw-model dragon] [--frames 24] [--repeats 3]

Per model and path (the standard orbit; a fly-through from far in front, close
past the side and round the back; the orbit jittered as if hand-held), all in
the same run: each frame refined alone by the dense engine and by the
output-sensitive one (medians over frames, after compilation), and the whole
path through ``pmjax.path_counts`` (counts) and ``pmjax.refine_path`` (a
``Refinement`` per frame), amortized per frame, medians over repeats. The
visited share is, per word of consecutive frames (16 in the C core, 32 as JAX
kernels), the pcols the word's traversal looked at over P, and over what one
frame alone visits, and the share of those the C core decided for all the
word's frames at once (the fat camera). Many paths: ``--paths`` orbits
of different radii and elevations advanced together, against ``refine_batch``
on the same cameras (dense and front), cameras per second.

Drawable meshes (``--mesh``, the standard orbit): per frame, amortized over the
path, medians over repeats, the variants alternated within each repeat:
``path_counts``; ``refine_path`` alone; ``refine_path`` with each frame's
``Refinement.mesh()`` (a mesh built from nothing per frame); ``refine_path``
with each frame's change (:class:`pmjax.MeshStream`), and that with the
stream's compacted mesh too (each of the two on a stream of its own that
follows the path pass after pass, as a viewer's does); and, on refinements
held in memory, the change alone (a stream never compacted),
``Refinement.mesh()`` alone and the compacted mesh alone (a stream compacted
every frame, less the change alone: the compaction and the logging of the
changes it merges).
With ``--srmesh DRIVER`` (``benchmarks/srmesh/build.py`` builds it and the
SR meshes), Hoppe's SrMesh runs in the same run on the same cameras and
tolerance, its passes alternated with the variants: per frame one
``set_view_params`` + ``adapt_refinement`` from the last frame's mesh (its
active mesh kept ready to draw), amortized over the path from the coarse
mesh, median over repeats; the faces each draws are printed. Without it, the
SrMesh figure is scaled: the ratio measured with it on one machine (SrMesh over
``refine_path`` + ``mesh()``: 0.052 / 0.160 on the bunny, 0.343 / 0.431 on the
dragon) applied to this run's ``refine_path`` + ``mesh()``, and labelled so.
Run pinned to one core (``taskset -c 0``).

Drawing (``--draw``, the standard orbit at 800x600, headless): per frame, what
a viewer pays from camera to image (refine, mesh, upload, draw), medians over
repeats, the variants alternated: each view refined alone (as ``pmjax view``
refines its live camera) or the path through ``refine_path``, each frame's mesh
built and drawn as a new scene or its change written into the GPU buffers in
place (``StreamScene``); and the draw of an unchanged scene alone.

Viewer (``--viewer``, needs a display: ``xvfb-run -a``): ``pmjax view``'s
window at 800x600 moved along the standard orbit, each view refined alone
and shown as the viewer shows it (``ViewerMesh``), per frame: the refine,
the mesh's change (or its arrays built anew) and the scene's update, the
changed rows written into the buffers before the draw (the stream only), and
the window's draw to ``glFinish`` (a new mesh's buffers made in it); the
two variants alternated in one window, means over frames, medians over
repeats.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import time

import jax
import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import alternating_medians, machine, median_time, write_json  # noqa: E402
from refine import pm_file  # noqa: E402
from srmesh.serve import SrMeshServer  # noqa: E402

import pmjax  # noqa: E402
from pmjax._camera import index_camera, stack_cameras  # noqa: E402
from pmjax._camera_table import fly_rows  # noqa: E402
from pmjax import _path  # noqa: E402
from pmjax._path import frames_per_word  # noqa: E402


def paths_for(v0, frames, seed=0):
    """The three paths of the benchmark, ``{name: Camera [frames]}``."""
    orbit = pmjax.standard_orbit(v0, frames)
    rng = np.random.default_rng(seed)
    c, r = v0.mean(0), 0.5 * np.linalg.norm(np.ptp(v0, 0))
    # Hand-held: the orbit's eyes shaken by 1 % of the model's size, the aim by 2 %.
    eyes = np.asarray(orbit.eye) + 0.01 * r * rng.normal(size=(frames, 3))
    aims = c + 0.02 * r * rng.normal(size=(frames, 3))
    hand = stack_cameras([pmjax.look_at(e, a) for e, a in zip(eyes, aims)])
    return {"orbit": orbit, "fly-through": fly_rows(v0, frames, 0, frames).camera(np.float32), "hand-held": hand}


def per_frame_ms(pm, cams, tau, method):
    views = [index_camera(cams, i) for i in range(pmjax.camera_count(cams))]
    for cam in views:  # compile, and grow the front's buffers to the whole path
        jax.block_until_ready(pmjax.refine(pm, cam, tau, method=method))
    out = []
    for cam in views:
        t = time.perf_counter()
        jax.block_until_ready(pmjax.refine(pm, cam, tau, method=method))
        out.append(time.perf_counter() - t)
    return 1e3 * statistics.median(out)


def one_path(name, pm, label, cams, tau, repeats):
    T = pmjax.camera_count(cams)
    # Compile every kernel the path uses and grow the buffers to the whole
    # path (a grown buffer set compiles anew), and check the counts against
    # per-frame refines on a few frames.
    for _ in range(2):
        counts = pmjax.path_counts(pm, cams, tau)
    for i in range(0, T, max(1, T // 6)):
        assert int(counts["faces"][i]) == int(pmjax.refine(pm, index_camera(cams, i), tau, method="dense").n_faces)
    sum(1 for _ in pmjax.refine_path(pm, cams, tau))
    dense = per_frame_ms(pm, cams, tau, "dense")
    front = per_frame_ms(pm, cams, tau, "front")
    sec, _ = median_time(lambda: pmjax.path_counts(pm, cams, tau), repeats)
    counts_ms = 1e3 * sec / T
    sec, _ = median_time(lambda: sum(1 for _ in pmjax.refine_path(pm, cams, tau)), repeats)
    path_ms = 1e3 * sec / T
    word = frames_per_word()
    at_once = [0]
    if pmjax.native_available():  # the pcols each word of the core visited, and decided for all frames at once
        from pmjax.engines import _core, derived

        d = derived(pm)
        n = T - T % word
        rows = _core.camera_rows(index_camera(cams, slice(0, n)), np.full(n, tau, np.float32), d.exponent)
        counts_w, at_once_w = _path._core_words(d.core_words, d.core, rows, pmjax.ALL_TESTS, False, False)[:2]
        union = np.asarray(counts_w)[::word, 0]
        at_once = np.asarray(at_once_w) / union
    else:  # words as JAX kernels
        union = [r.n_visited for i, r in enumerate(pmjax.refine_path(pm, cams, tau)) if i % word == 0]
    own = [pmjax.refine(pm, index_camera(cams, i), tau, method="front").n_visited for i in range(0, T, word)]
    row = dict(model=name, path=label, pcols=pm.n_pcols, frames=T, faces=int(np.median(counts["faces"])),
               dense_ms=dense, front_ms=front, path_counts_ms=counts_ms, refine_path_ms=path_ms,
               visited_share=float(np.median(union)) / pm.n_pcols, union_over_one=float(np.median(union) / np.median(own)),
               decided_at_once=float(np.median(at_once)))
    print(f"{name:16s} {label:11s} P {pm.n_pcols:7d} faces {row['faces']:6d} | per frame: dense {dense:6.3f} "
          f"front {front:6.3f} ms | path: counts {counts_ms:6.3f} ({dense / counts_ms:5.1f}x dense, "
          f"{front / counts_ms:4.1f}x front), refine_path {path_ms:6.3f} ms ({dense / path_ms:5.1f}x, "
          f"{front / path_ms:4.1f}x) | visited {row['visited_share']:5.1%} of P, "
          f"{row['union_over_one']:.2f}x one frame's, {row['decided_at_once']:.0%} decided at once", flush=True)
    return row


def many_paths(name, n_paths, frames, tau, repeats):
    pm = pmjax.load(pm_file(name))
    v0 = np.asarray(pm.vertices)[: pm.n_original_vertices]
    rng = np.random.default_rng(n_paths)
    c, r = v0.mean(0), 0.5 * np.linalg.norm(np.ptp(v0, 0))
    orbits = []
    for _ in range(n_paths):
        radius, elevation = r / np.sin(np.radians(22.5)) * rng.uniform(0.6, 1.6), np.radians(rng.uniform(-30, 60))
        a = np.linspace(0, 2 * np.pi, frames, endpoint=False) + rng.uniform(0, 2 * np.pi)
        eyes = c + radius * np.stack([np.cos(elevation) * np.cos(a), np.full(frames, np.sin(elevation)),
                                      np.cos(elevation) * np.sin(a)], 1)
        orbits.append(stack_cameras([pmjax.look_at(e, c) for e in eyes]))
    grid = jax.tree.map(lambda *a: np.stack(a), *orbits)  # [K, T]
    flat = jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), grid)
    K = n_paths * frames
    for _ in range(2):  # compile, grow the buffers to every path
        pmjax.path_counts(pm, grid, tau, paths=True)
    sec, _ = median_time(lambda: pmjax.path_counts(pm, grid, tau, paths=True), repeats)
    row = dict(model=name, paths=n_paths, frames=frames, path_cameras_per_s=K / sec)
    for m in ("dense", "front"):
        for _ in range(2):
            pmjax.refine_batch(pm, flat, tau, method=m)
        sec, _ = median_time(lambda: pmjax.refine_batch(pm, flat, tau, method=m), repeats)
        row[f"batch_{m}_cameras_per_s"] = K / sec
    print(f"{name}: {n_paths} orbits x {frames} frames: paths together {row['path_cameras_per_s']:8.0f} cameras/s, "
          f"refine_batch dense {row['batch_dense_cameras_per_s']:7.0f} ({row['path_cameras_per_s'] / row['batch_dense_cameras_per_s']:.1f}x), "
          f"front {row['batch_front_cameras_per_s']:7.0f}", flush=True)
    return row


# SrMesh's per-frame adapt over refine_path + mesh(), measured in one run on
# one machine (standard orbit, 240 frames, tau 1): this run's refine_path +
# mesh() times it gives SrMesh's on this machine when SrMesh is not run.
SRMESH_OVER_MESH = {"bunny": 0.052 / 0.160, "dragon": 0.343 / 0.431}


def srmesh_mesh(driver, name):
    """The SR mesh of ``name`` that ``benchmarks/srmesh/build.py`` makes beside
    its driver (``<out>/bin/srmesh_adapt``, ``<out>/<name>.sr.pm``)."""
    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(driver))), f"{name}.sr.pm")


def mesh_path(name, frames, tau, repeats, srmesh_driver=None):
    """Per-frame costs of drawable meshes along the standard orbit (``--mesh``);
    with ``srmesh_driver``, SrMesh's adapt on the same cameras, alternated."""
    pm = pmjax.load(pm_file(name))
    cams = pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], frames)
    held = list(pmjax.refine_path(pm, cams, tau))
    for r in held:  # every table made before the clocks start
        r.mesh()
    stream = pmjax.MeshStream(pm)
    for r in held:
        stream.update(r)
    stream.mesh()
    changed = []
    for r in held:
        change = stream.update(r)
        changed.append(len(change.face_slots))
    # The change alone on a stream of its own, never compacted (a compacted
    # stream logs its changes for the next compaction); warmed once.
    bare = pmjax.MeshStream(pm)
    for r in held:
        bare.update(r)

    # The two path variants follow the path with streams of their own, as a
    # viewer's loop does: one never compacted (no logging, as above), one
    # compacted every frame; each warmed once.
    drawn, drawn_compacted = pmjax.MeshStream(pm), pmjax.MeshStream(pm)

    def follow(with_mesh):
        own = drawn_compacted if with_mesh else drawn
        for _ in pmjax.path_mesh_changes(pm, cams, tau, stream=own):
            if with_mesh:
                own.mesh()

    follow(False)
    follow(True)

    variants = {
        "path_counts": lambda: pmjax.path_counts(pm, cams, tau),
        "refine_path": lambda: sum(1 for _ in pmjax.refine_path(pm, cams, tau)),
        "refine_path + mesh()": lambda: [r.mesh() for r in pmjax.refine_path(pm, cams, tau)],
        "path_mesh_changes (refine_path + change)": lambda: follow(False),
        "path_mesh_changes + compacted": lambda: follow(True),
        "change alone": lambda: [bare.update(r) for r in held],
        "mesh() alone": lambda: [r.mesh() for r in held],
        "compacted from the stream alone": lambda: [(stream.update(r), stream.mesh()) for r in held],
    }
    faces = np.asarray([int(r.n_faces) for r in held])
    with contextlib.ExitStack() as stack:
        srmesh_passes = []
        if srmesh_driver:
            # SrMesh's passes take their turn among the variants; each pass's
            # own per-frame clock is kept (the request and the untimed
            # coarsening before it are not SrMesh's per-frame work).
            server = stack.enter_context(SrMeshServer(srmesh_driver, srmesh_mesh(srmesh_driver, name), cams, tau))
            server.one_pass()  # warm: every pool and list grown along the path
            variants["SrMesh"] = lambda: srmesh_passes.append(server.one_pass())
        ms = alternating_medians(variants, repeats, frames)
    # The compacted mesh alone: the compacted stream's update and compaction
    # less the change alone (so the logging its compactions need counts).
    ms["compacted from the stream alone"] -= ms["change alone"]
    row = dict(model=name, pcols=pm.n_pcols, frames=frames, faces=int(np.median(faces)),
               faces_changed=float(np.median(changed)))
    if srmesh_passes:
        ms.pop("SrMesh")
        # Amortized over the path as refine_path is, median over passes.
        srmesh = float(np.median([p_ms.sum() / frames for p_ms, _, _ in srmesh_passes]))
        sr_faces = srmesh_passes[-1][1]
        row.update(srmesh_ms=srmesh, srmesh_source="measured in this run", srmesh_faces=int(np.median(sr_faces)),
                   srmesh_median_frame_ms=float(np.median([np.median(p_ms) for p_ms, _, _ in srmesh_passes])),
                   srmesh_cpu_ms=float(np.median([cpu / frames for _, _, cpu in srmesh_passes])))
        label = f"SrMesh {srmesh:.3f} ms per frame, measured here"
    elif name in SRMESH_OVER_MESH:
        srmesh = SRMESH_OVER_MESH[name] * ms["refine_path + mesh()"]
        row.update(srmesh_ms=srmesh, srmesh_source="scaled by SRMESH_OVER_MESH")
        label = (f"SrMesh ~ {srmesh:.3f} ms, scaled (= {SRMESH_OVER_MESH[name]:.3f} x "
                 f"refine_path + mesh(), a ratio from another machine)")
    else:
        srmesh = None
        label = "no SrMesh figure for this model (--srmesh DRIVER measures one)"
    row["ms"] = ms
    print(f"{name}: P {pm.n_pcols}, faces {row['faces']} (median), faces changed per frame "
          f"{row['faces_changed']:.0f} (median); {label}")
    if srmesh_passes:
        ratio = sr_faces / faces
        print(f"  faces drawn: pmjax {row['faces']}, SrMesh {row['srmesh_faces']} (median); SrMesh / pmjax per frame "
              f"{np.median(ratio):.2f} (median), {ratio.min():.2f}..{ratio.max():.2f}; SrMesh's median frame "
              f"{row['srmesh_median_frame_ms']:.3f} ms, its CPU time {row['srmesh_cpu_ms']:.3f} ms per frame")
        if row["srmesh_cpu_ms"] < 0.9 * srmesh:
            print("  NOTE: SrMesh's CPU time is under 90 % of its wall time: it was preempted (a busy machine)")
        if not 0.75 <= np.median(ratio) <= 1.25:
            print("  WARNING: SrMesh's faces differ from pmjax's by over 25 %: check the SR mesh and the cameras")
    base = ms["refine_path + mesh()"]
    for key, value in ms.items():
        versus = f"   {srmesh / value:5.2f}x SrMesh" if srmesh is not None else ""
        print(f"  {key:42s} {value:7.4f} ms per frame   {base / value:5.2f}x refine_path + mesh(){versus}", flush=True)
    return row


def draw_path(name, frames, tau, repeats, size=(800, 600)):
    """Per-frame costs from camera to image along the standard orbit (``--draw``)."""
    from pmjax.render import Renderer
    from pmjax.render._offscreen import StreamScene, refined_arrays

    pm = pmjax.load(pm_file(name))
    cams = pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], frames, width=size[0],
                                height=size[1])
    views = [index_camera(cams, i) for i in range(frames)]
    with Renderer(*size) as renderer:
        def drawn_anew(refinements):
            for cam, r in zip(views, refinements):
                v, f, _, normals = refined_arrays(pm, r)
                renderer.render_mesh(v, f, cam, normals=normals)

        def streamed(refinements):
            scene = StreamScene(renderer, pm)
            for cam, r in zip(views, refinements):
                scene.update(r)
                scene.render(cam)

        def unchanged():
            scene = StreamScene(renderer, pm)
            scene.update(pmjax.refine(pm, views[0], tau))
            for cam in views:
                scene.render(cam)

        one_by_one = lambda: (pmjax.refine(pm, cam, tau) for cam in views)
        variants = {
            "views one by one, mesh drawn anew": lambda: drawn_anew(one_by_one()),
            "views one by one, change in place": lambda: streamed(one_by_one()),
            "refine_path, mesh drawn anew": lambda: drawn_anew(pmjax.refine_path(pm, cams, tau)),
            "refine_path, change in place": lambda: streamed(pmjax.refine_path(pm, cams, tau)),
            "draw alone (scene unchanged)": unchanged,
        }
        for fn in variants.values():  # compiled, contexts and tables made
            fn()
        ms = alternating_medians(variants, repeats, frames)
    print(f"{name}: {size[0]}x{size[1]}, {frames} frames, tau {tau}")
    for key, value in ms.items():
        print(f"  {key:36s} {value:8.3f} ms per frame", flush=True)
    return dict(model=name, size=list(size), frames=frames, ms=ms)


def viewer_path(name, frames, tau, repeats, size=(800, 600)):
    """Per-frame costs of ``pmjax view``'s window along the standard orbit (``--viewer``)."""
    import threading

    from OpenGL import GL

    from pmjax.render._viewer import ViewerState, check_display, open_viewer

    check_display()
    pm = pmjax.load(pm_file(name))
    cams = pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], frames, width=size[0],
                                height=size[1])
    views = [index_camera(cams, i) for i in range(frames)]
    clock = {"want": False, "start": 0.0, "end": 0.0}
    done = threading.Event()

    gl = {}

    def drawn(viewer):  # the window's thread: the scene drawn
        if not gl:
            gl.update(renderer=GL.glGetString(GL.GL_RENDERER).decode(), version=GL.glGetString(GL.GL_VERSION).decode())
        if clock["want"]:
            GL.glFinish()
            clock["want"], clock["end"] = False, time.perf_counter()
            done.set()

    viewer, mesh, _ = open_viewer(pm, views[0], ViewerState(tau=tau), drawn=drawn)
    before_draw = mesh.before_draw

    def timed_before_draw():  # the draw's start: the upload comes first
        clock["start"] = time.perf_counter()
        before_draw()
        clock["uploaded"] = time.perf_counter()

    mesh.before_draw = timed_before_draw

    def one_pass(stream):
        mesh.stream = stream
        parts = np.zeros((frames, 4))
        for i, cam in enumerate(views):
            t0 = time.perf_counter()
            r = pmjax.refine(pm, cam, tau)
            jax.block_until_ready(r.n_faces)
            # Held over the show and the request: the next draw is the first
            # with this view (the wait for a draw in progress not timed).
            with viewer.render_lock:
                t1 = time.perf_counter()
                mesh.show(r, viewer.render_lock)
                t2 = time.perf_counter()
                viewer._trackball._n_pose = np.asarray(cam.pose(), np.float64)
                done.clear()
                clock["want"] = True
            if not done.wait(120):
                raise RuntimeError("the viewer's window drew nothing")
            parts[i] = (t1 - t0, t2 - t1, clock["uploaded"] - clock["start"], clock["end"] - clock["uploaded"])
        return 1e3 * parts.mean(axis=0)

    variants = {"change in place": True, "mesh drawn anew": False}
    try:
        for stream in variants.values():  # compiled, tables and buffers made
            one_pass(stream)
        times = {k: [] for k in variants}
        for _ in range(repeats):
            for key, stream in variants.items():
                times[key].append(one_pass(stream))
    finally:
        viewer.close_external()
    print(f"{name}: pmjax view's window {size[0]}x{size[1]}, {frames} frames, tau {tau}; "
          f"OpenGL {gl.get('version')}, {gl.get('renderer')}")
    ms = {}
    for key, rows in times.items():
        refine_ms, mesh_ms, upload_ms, draw_ms = np.median(np.asarray(rows), axis=0)
        ms[key] = dict(refine=refine_ms, mesh=mesh_ms, upload=upload_ms, draw=draw_ms,
                       frame=refine_ms + mesh_ms + upload_ms + draw_ms)
        print(f"  {key:16s} frame {ms[key]['frame']:8.3f} ms = refine {refine_ms:7.3f} + change/mesh "
              f"{mesh_ms:7.3f} + rows written {upload_ms:7.3f} + draw {draw_ms:8.3f}", flush=True)
    return dict(model=name, size=list(size), frames=frames, ms=ms, gl=gl)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="cow,bunny,terrain_gcanyon,terrain_sthelens,dragon")
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--tau", type=float, default=1.0)
    ap.add_argument("--paths", type=int, default=256, help="orbits advanced together (0: skip)")
    ap.add_argument("--many-model", default="dragon")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", help="also write results as JSON")
    ap.add_argument("--mesh", action="store_true", help="drawable meshes along the orbit, per frame (only)")
    ap.add_argument("--mesh-models", default="bunny,dragon")
    ap.add_argument("--srmesh", metavar="DRIVER", help="with --mesh: run SrMesh's driver (benchmarks/srmesh/build.py "
                    "makes it and the SR meshes beside it) in the same run, instead of the scaled figure")
    ap.add_argument("--draw", action="store_true", help="camera to image along the orbit, per frame (only)")
    ap.add_argument("--draw-model", default="dragon")
    ap.add_argument("--viewer", action="store_true", help="pmjax view's window along the orbit, per frame (only)")
    args = ap.parse_args()
    if args.srmesh and not args.mesh:
        ap.error("--srmesh goes with --mesh")
    print(f"machine: {machine()}\n")
    if args.viewer:
        row = viewer_path(args.draw_model, args.frames, args.tau, args.repeats)
        if args.json:
            write_json(args.json, dict(machine=machine(), viewer=row))
        return
    if args.draw:
        row = draw_path(args.draw_model, args.frames, args.tau, args.repeats)
        if args.json:
            write_json(args.json, dict(machine=machine(), draw=row))
        return
    if args.mesh:
        rows = [mesh_path(name, args.frames, args.tau, args.repeats, args.srmesh)
                for name in args.mesh_models.split(",")]
        if args.json:
            write_json(args.json, dict(machine=machine(), mesh=rows))
        return
    rows = []
    for name in args.models.split(","):
        pm = pmjax.load(pm_file(name))
        v0 = np.asarray(pm.vertices)[: pm.n_original_vertices]
        for label, cams in paths_for(v0, args.frames).items():
            rows.append(one_path(name, pm, label, cams, args.tau, args.repeats))
        jax.clear_caches()  # each hierarchy compiles its own kernels
    many = [many_paths(args.many_model, args.paths, args.frames, args.tau, args.repeats)] if args.paths else []
    if args.json:
        write_json(args.json, dict(machine=machine(), paths=rows, many=many))


if __name__ == "__main__":
    main()
