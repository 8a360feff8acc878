"""Refinement benchmark: the paper's Table 1, vectorized vs oracle, batched throughput,
compile/load time and memory.

Usage: python benchmarks/refine.py [--models cow,bunny,dragon,terrain_gcanyon,terrain_sthelens]
       [--frames 240] [--tau 1] [--batched bunny,dragon] [--ks 1,16,256,4096] [--cores N]
       [--parts table1,oracle,batched,front]

Standard orbit (the camera circles the bounding-box centre at r / sin 22.5°,
r half the box diagonal, 20° elevation, 800×600, 45° fov, 240 frames). The
front part compares the output-sensitive engine with the dense one per model. PM files are built
once into benchmarks/.cache (per builder version). Per-frame times are full single-camera refines
(executed set, vref, face mask, counts) after compilation; medians over frames.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import DATA, machine, median_time, pin_cores, write_json  # noqa: E402

import pmjax  # noqa: E402
from pmjax._camera import index_camera  # noqa: E402
from pmjax import collapse_mask  # noqa: E402

# PMJAX_BENCH_CACHE moves the cache (to carry prebuilt PM files to another machine).
CACHE = os.environ.get("PMJAX_BENCH_CACHE", os.path.join(os.path.dirname(os.path.abspath(__file__)), ".cache"))


PARTS = ("table1", "oracle", "batched", "front")


def pm_file(name: str) -> str:
    """Path of the default build of ``name``, cached per builder version (a
    digest of the builder's source, so a changed builder never reuses an old
    hierarchy)."""
    import pmjax.builders
    from pmjax.builders import build_pm

    digest = hashlib.sha256()
    for folder in pmjax.builders.__path__:
        for source in sorted(Path(folder).glob("*.py")):
            digest.update(source.read_bytes())
    os.makedirs(CACHE, exist_ok=True)
    path = os.path.join(CACHE, f"{name}-{digest.hexdigest()[:12]}.pmz")
    if not os.path.exists(path):
        v, f, _, _ = pmjax.load_clean_mesh(DATA / f"{name}.ply")
        pmjax.save_pm(build_pm(v, f), path)
    return path


def table1(names, frames, tau):
    rows = []
    for name in names:
        path = pm_file(name)
        t_load, _ = median_time(lambda: pmjax.load(path), 3)
        pm = pmjax.load(path)
        data = pmjax.read_pm(path)
        cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], frames)
        t = time.perf_counter()
        jax.block_until_ready(pmjax.refine(pm, index_camera(cams, 0), tau, method="dense"))
        compile_s = time.perf_counter() - t
        faces, verts, ms = [], [], []
        for i in range(frames):
            cam = index_camera(cams, i)
            t = time.perf_counter()
            r = jax.block_until_ready(pmjax.refine(pm, cam, tau, method="dense"))
            ms.append(1e3 * (time.perf_counter() - t))
            faces.append(int(r.n_faces))
            verts.append(int(r.n_vertices))
        row = dict(model=name, V=data.n_original_vertices, F=len(data.faces), pcols=data.n_pcols,
                   batches=data.n_batches, refined_V=int(np.median(verts)), refined_F=int(np.median(faces)),
                   reduction=float(np.median(faces)) / len(data.faces), ms=statistics.median(ms),
                   load_ms=1e3 * t_load, compile_s=compile_s)
        rows.append(row)
        print(f"{name:18s} V {row['V']:7d} F {row['F']:7d} pcols {row['pcols']:7d} B {row['batches']:3d} | "
              f"refined V {row['refined_V']:6d} F {row['refined_F']:6d} ({row['reduction']:6.2%}) | "
              f"{row['ms']:7.3f} ms/frame {1e3 / row['ms']:8.1f} fps | load {row['load_ms']:6.1f} ms "
              f"compile {row['compile_s']:.2f} s", flush=True)
    return rows


def versus_oracle(name, tau, frames=5):
    """Engine vs the sequential oracle on the same frames.

    The oracle's time is the whole view, as the tests run it: the shared
    per-pcol decisions (``collapse_mask``, compiled) and then the Python loop
    of Fig. 6; the loop alone is reported too. The engine's time per frame is
    the median of 10 calls; both are medians over the frames.
    """
    path = pm_file(name)
    pm, data = pmjax.load(path), pmjax.read_pm(path)
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], frames)
    eng, orc, loop = [], [], []
    for i in range(frames):
        cam = index_camera(cams, i)
        jax.block_until_ready(pmjax.refine(pm, cam, tau, method="dense"))
        jax.block_until_ready(collapse_mask(pm.attributes, cam, np.float32(tau)))
        # The engine call is short, so one call is at the mercy of a hiccup:
        # take the median of 10 calls for this frame.
        eng.append(median_time(lambda: jax.block_until_ready(pmjax.refine(pm, cam, tau, method="dense")), 10)[0])
        t = time.perf_counter()
        collapse = np.asarray(collapse_mask(pm.attributes, cam, np.float32(tau)))
        t_loop = time.perf_counter()
        pmjax.oracle_refine(data, collapse)
        done = time.perf_counter()
        orc.append(done - t)
        loop.append(done - t_loop)
    e, o, lp = statistics.median(eng), statistics.median(orc), statistics.median(loop)
    print(f"{name}: engine {1e3 * e:.3f} ms, sequential oracle {1e3 * o:.1f} ms (loop alone {1e3 * lp:.1f} ms) "
          f"-> {o / e:.0f}x", flush=True)
    return dict(model=name, engine_ms=1e3 * e, oracle_ms=1e3 * o, oracle_loop_ms=1e3 * lp, ratio=o / e)


def batched(name, ks, tau, chunk):
    path = pm_file(name)
    pm, data = pmjax.load(path), pmjax.read_pm(path)
    rows = []
    for K in ks:
        cams = pmjax.random_views(data.vertices[: data.n_original_vertices], K, seed=K, min_scale=0.8, max_scale=3)
        c = min(chunk, K)
        pmjax.refine_batch(pm, cams, tau, chunk=c, method="dense")  # compile
        med, _ = median_time(lambda: pmjax.refine_batch(pm, cams, tau, chunk=c, method="dense"), 3)
        rows.append(dict(model=name, K=K, chunk=c, seconds=med, cameras_per_s=K / med))
        print(f"{name} K={K:5d} chunk={c:4d}: {med * 1e3:9.1f} ms  {K / med:9.0f} cameras/s "
              f"({1e3 * med / K:.3f} ms/camera)", flush=True)
    return rows


def front_vs_dense(name, frames, tau, K, chunk):
    """The output-sensitive engine against the dense reference, same run, same
    cameras: one camera along the standard orbit (refine, and the mesh of the
    result), the visited region, and a batch of K random views."""
    path = pm_file(name)
    pm, data = pmjax.load(path), pmjax.read_pm(path)
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], frames)
    t = {m: [] for m in ("dense", "front", "mesh_dense", "mesh_front")}
    visited, not_run, faces = [], [], []
    for m in ("dense", "front"):  # compile, and size the front's buffers on a few frames
        for i in range(0, frames, max(1, frames // 8)):
            jax.block_until_ready(pmjax.refine(pm, index_camera(cams, i), tau, method=m)).mesh()
    # Each engine runs whole passes over the path (as a user's loop would, with
    # its own data in cache), the passes alternating so drift hits both alike.
    views = [index_camera(cams, i) for i in range(frames)]
    for rep in range(2):
        for m in ("dense", "front"):
            for cam in views:
                t0 = time.perf_counter()
                r = jax.block_until_ready(pmjax.refine(pm, cam, tau, method=m))
                t1 = time.perf_counter()
                r.mesh()
                t[m].append(t1 - t0)
                t["mesh_" + m].append(time.perf_counter() - t1)
                if rep == 0 and m == "front":
                    visited.append(r.n_visited)
                    not_run.append(data.n_pcols - int(r.n_executed))
                    faces.append(int(r.n_faces))
    med = {k: 1e3 * statistics.median(v) for k, v in t.items()}
    row = dict(model=name, pcols=data.n_pcols, frames=frames, faces=int(np.median(faces)),
               visited=int(np.median(visited)), not_executed=int(np.median(not_run)),
               dense_ms=med["dense"], front_ms=med["front"], mesh_dense_ms=med["mesh_dense"],
               mesh_front_ms=med["mesh_front"])
    # Exact face budgets (faces_for_budget) on a few orbit frames, the budget
    # being the frame's own count at tau (so both methods must find tau back).
    budget = {m: [] for m in ("dense", "front")}
    for cam in views[:: max(1, frames // 12)]:
        faces = int(pmjax.refine(pm, cam, tau, method="dense").n_faces)
        for m in ("dense", "front"):
            pmjax.faces_for_budget(pm, cam, faces, method=m)  # compile
            t0 = time.perf_counter()
            pmjax.faces_for_budget(pm, cam, faces, method=m)
            budget[m].append(time.perf_counter() - t0)
    row["budget_dense_ms"], row["budget_front_ms"] = (1e3 * statistics.median(budget[m]) for m in ("dense", "front"))
    rv = pmjax.random_views(data.vertices[: data.n_original_vertices], K, seed=K, min_scale=0.8, max_scale=3)
    batch = {m: [] for m in ("dense", "front")}
    for m in batch:
        pmjax.refine_batch(pm, rv, tau, chunk=chunk, method=m)  # compile (and grow buffers)
    # Passes of three calls per engine, the passes alternating so that drift
    # hits both alike. A user's thousands of cameras run one engine's chunks
    # back to back; a call right after the other engine also pays for the
    # cache lines that engine took (about 6 % of a front batch after a dense
    # one), which the first call of each pass keeps in the median.
    for rep in range(3):
        for m in batch:
            for _ in range(3):
                t0 = time.perf_counter()
                pmjax.refine_batch(pm, rv, tau, chunk=chunk, method=m)
                batch[m].append(time.perf_counter() - t0)
    for m in batch:
        row[f"batch_{m}_cameras_per_s"] = K / statistics.median(batch[m])
    print(f"{name:16s} P {row['pcols']:7d} | visited {row['visited']:6d} ({row['visited'] / row['pcols']:5.1%} of P, "
          f"{row['visited'] / max(1, row['not_executed']):.2f}x not executed, {row['visited'] / row['faces']:.2f}x faces) | "
          f"refine dense {med['dense']:6.3f} front {med['front']:6.3f} ms ({med['dense'] / med['front']:4.2f}x) | "
          f"mesh dense {med['mesh_dense']:6.3f} front {med['mesh_front']:6.3f} ms "
          f"({med['mesh_dense'] / med['mesh_front']:4.2f}x) | budget dense {row['budget_dense_ms']:6.2f} front "
          f"{row['budget_front_ms']:6.2f} ms | batch K={K}: dense {row['batch_dense_cameras_per_s']:7.0f} "
          f"front {row['batch_front_cameras_per_s']:7.0f} cameras/s", flush=True)
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="cow,bunny,dragon,terrain_gcanyon,terrain_sthelens")
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--tau", type=float, default=1.0)
    ap.add_argument("--batched", default="bunny,dragon")
    ap.add_argument("--ks", default="1,16,256,4096")
    ap.add_argument("--chunk", type=int, default=256)
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated subset of {','.join(PARTS)}")
    ap.add_argument("--json", help="also write results as JSON")
    ap.add_argument("--cores", type=int, help="run on this many CPUs only (default: all); docs/bench-refine.md")
    args = ap.parse_args()
    if args.cores:
        try:
            pin_cores(args.cores)
        except ValueError as e:
            ap.error(str(e))
    parts = set(args.parts.split(","))
    if parts - set(PARTS):
        ap.error(f"unknown part(s) {sorted(parts - set(PARTS))}")
    print(f"machine: {machine()}\n")
    t1, vo, bt, fr = [], [], [], []
    if "table1" in parts:
        print(f"Table 1 (standard orbit, {args.frames} frames, tau = {args.tau} px, 800x600, 45 deg):")
        t1 = table1(args.models.split(","), args.frames, args.tau)
    if "oracle" in parts:
        print("\nVectorized engine vs sequential oracle (single camera, median of 5 frames):")
        vo = [versus_oracle(n, args.tau) for n in ("bunny", "dragon") if n in args.models.split(",")]
    if "batched" in parts:
        print("\nBatched throughput (random views around the model, counts only):")
        for n in args.batched.split(","):
            bt += batched(n, [int(k) for k in args.ks.split(",")], args.tau, args.chunk)
    if "front" in parts:
        print("\nOutput-sensitive (front) vs dense engine, same run (standard orbit; batch: random views):")
        fr = [front_vs_dense(n, args.frames, args.tau, 256, args.chunk) for n in args.models.split(",")]
    print(f"\npeak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    if args.json:
        write_json(args.json, dict(machine=machine(), table1=t1, oracle=vo, batched=bt, front=fr))


if __name__ == "__main__":
    main()
