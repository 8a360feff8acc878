"""The front engine's calls as a user makes them: eager, under jax.jit, under jax.vmap.

One process, one model (standard orbit, 800x600, 45 degrees, tau = 1 px):

- ``refine``: an eager ``pmjax.refine`` per orbit frame (median over two
  passes of the 240 frames); ``mesh``: its ``Refinement.mesh()``;
- ``jit_refine``: ``jax.jit(lambda c: pmjax.refine(pm, c, 1.0).n_faces)`` per
  frame (the mesh closed over, compiled once);
- ``batch``: ``pmjax.refine_batch`` of 256 random views (seed 256, 0.8-3x the
  orbit distance), cameras per second, median of nine calls;
- ``vmap``: ``jax.jit(jax.vmap(lambda c: pmjax.refine(pm, c, 1.0).n_faces))``
  on the same 256 views;
- ``path_counts``: ``pmjax.path_counts`` of a 7,680-frame orbit, ms per frame
  (median of three);
- ``refine_path_mesh``: ``pmjax.refine_path`` of the 240-frame orbit with each
  frame's ``mesh()``, ms per frame (median of three).

Prints one JSON line (``--json`` to a file too). ``benchmarks/compare.py``
runs it under two checkouts in alternating processes for same-run ratios;
measurements the checkout cannot make (no jit or vmap of ``refine``) are
left out.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax

import pmjax
from pmjax._camera import index_camera

from _common import machine, pin_cores, write_json


def median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def measure(path: str) -> dict:
    pm = pmjax.load(path)
    data = pmjax.read_pm(path)
    v0 = data.vertices[: data.n_original_vertices]
    orbit = pmjax.standard_orbit(v0, 240)
    frames = [index_camera(orbit, i) for i in range(240)]
    out = {}
    for cam in frames[:8]:
        pmjax.refine(pm, cam, 1.0).mesh()
    refine_s, mesh_s = [], []
    for _ in range(2):
        for cam in frames:
            t0 = time.perf_counter()
            r = pmjax.refine(pm, cam, 1.0)
            t1 = time.perf_counter()
            r.mesh()
            refine_s.append(t1 - t0)
            mesh_s.append(time.perf_counter() - t1)
    out["refine_ms"] = 1e3 * statistics.median(refine_s)
    out["mesh_ms"] = 1e3 * statistics.median(mesh_s)
    try:
        compiled = jax.jit(lambda c: pmjax.refine(pm, c, 1.0).n_faces)
        compiled(frames[0]).block_until_ready()
    except Exception:  # a checkout whose refine is not a JAX function
        compiled = None
    if compiled is not None:
        jit_s = []
        for _ in range(2):
            for cam in frames:
                t0 = time.perf_counter()
                compiled(cam).block_until_ready()
                jit_s.append(time.perf_counter() - t0)
        out["jit_refine_ms"] = 1e3 * statistics.median(jit_s)
    views = pmjax.random_views(v0, 256, seed=256, min_scale=0.8, max_scale=3)
    pmjax.refine_batch(pm, views, 1.0, method="front")
    out["batch_cameras_per_s"] = 256 / median_seconds(lambda: pmjax.refine_batch(pm, views, 1.0, method="front"), 9)
    try:
        mapped = jax.jit(jax.vmap(lambda c: pmjax.refine(pm, c, 1.0).n_faces))
        mapped(views).block_until_ready()
    except Exception:
        mapped = None
    if mapped is not None:
        out["vmap_cameras_per_s"] = 256 / median_seconds(lambda: mapped(views).block_until_ready(), 9)
    long = pmjax.standard_orbit(v0, 7680)
    pmjax.path_counts(pm, index_camera(long, slice(0, 240)), 1.0)
    out["path_counts_ms_per_frame"] = 1e3 * median_seconds(lambda: pmjax.path_counts(pm, long, 1.0), 3) / 7680

    def path_meshes():
        for r in pmjax.refine_path(pm, orbit, 1.0):
            r.mesh()

    path_meshes()
    out["refine_path_mesh_ms_per_frame"] = 1e3 * median_seconds(path_meshes, 3) / 240
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="dragon", help="a model of the data folder (default dragon)")
    ap.add_argument("--pm", help="a .pmz file instead of building the model")
    ap.add_argument("--cores", type=int, help="run on this many CPUs only")
    ap.add_argument("--json", help="also write the result here")
    args = ap.parse_args()
    if args.cores:
        pin_cores(args.cores)
    path = args.pm
    if path is None:
        from refine import pm_file

        path = pm_file(args.model)
    result = dict(model=args.model, machine=machine(), **{k: round(v, 5) for k, v in measure(path).items()})
    print(json.dumps(result))
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
