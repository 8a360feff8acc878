"""Soft refinement benchmark: cost of soft refinement and its gradient against the
hard engine, exact vs soft face budgets, and popping with and without geomorphs.

Usage: python benchmarks/soft.py [--models bunny,dragon] [--repeats 5] [--batch 256]
       [--budgets 2000,8000] [--popping-frames 240] [--geomorph 8,16] [--supersample 4]
       [--parts cost,budgets,popping] [--json OUT]

Cost (standard orbit, tau = 1 px, temperature 0.1 px, float32; medians over
``--repeats`` after one compile call):
- single camera: hard ``refine``; ``soft_refine`` (forward); the gradient of
  the soft face count with respect to tau and the eye (one reverse pass);
- batched, K cameras: hard ``refine_batch``; soft forward and gradient
  vectorized over cameras, 16 at a time (``lax.map`` with ``batch_size``).
Budgets (K cameras of the orbit): exact ``faces_for_budget`` (one sort per
camera) vs ``soft_tau_for_budget`` (every camera a lane of one solve); steps, convergence,
the hard face count at the soft tau and the two tolerances' ratio.
Popping (first model, ``--popping-frames`` frames, 0 to skip): per-frame popping
share and mean squared change, hard vs geomorphed over ``--geomorph`` frames.
"""

from __future__ import annotations

import argparse
import statistics
import sys

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import machine, median_time, write_json  # noqa: E402
from refine import pm_file  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import pmjax  # noqa: E402


CHUNK = 16  # cameras per vectorized soft call


def cost(pm, cams, K, repeats):
    cam = pmjax.index_camera(cams, 0)
    batch = pmjax.index_camera(cams, jnp.arange(K) % pmjax.camera_count(cams))
    T = jnp.float32(0.1)

    def soft_faces(c, tau):
        return pmjax.soft_refine(pm, c, tau, T).faces

    grad_one = jax.jit(jax.grad(lambda c, tau: soft_faces(c, tau), argnums=(0, 1), allow_int=True))
    # Vectorized over cameras in chunks (lax.map batch_size): a reverse pass
    # keeps every camera's [P] intermediates alive (the dragon at K = 256 would
    # need 46 GB at once).
    soft_many = jax.jit(lambda cams, tau: jax.lax.map(lambda c: soft_faces(c, tau), cams, batch_size=CHUNK))
    grad = jax.grad(soft_faces, argnums=(0, 1), allow_int=True)
    grad_many = jax.jit(lambda cams, tau: jax.lax.map(lambda c: grad(c, tau), cams, batch_size=CHUNK))
    tau = jnp.float32(1.0)
    runs = {
        "hard_ms": lambda: jax.block_until_ready(pmjax.refine(pm, cam, 1.0).n_faces),
        "soft_ms": lambda: jax.block_until_ready(pmjax.soft_refine(pm, cam, tau, T).faces),
        "soft_grad_ms": lambda: jax.block_until_ready(grad_one(cam, tau)),
        "hard_batch_s": lambda: pmjax.refine_batch(pm, batch, 1.0, chunk=K),
        "soft_batch_s": lambda: jax.block_until_ready(soft_many(batch, tau)),
        "soft_grad_batch_s": lambda: jax.block_until_ready(grad_many(batch, tau)),
    }
    out = {}
    for key, fn in runs.items():
        fn()  # compile
        med, _ = median_time(fn, repeats)
        out[key] = 1e3 * med if key.endswith("_ms") else med
    for key in ("hard_batch_s", "soft_batch_s", "soft_grad_batch_s"):
        out[key.replace("_s", "_cams_per_s")] = K / out.pop(key)
    return out


def budgets(pm, cams, budget, K):
    batch = pmjax.index_camera(cams, jnp.arange(K) % pmjax.camera_count(cams))
    sol = pmjax.soft_tau_for_budget(pm, batch, budget)  # compile
    jax.block_until_ready(sol.tau)
    soft_s, _ = median_time(lambda: jax.block_until_ready(pmjax.soft_tau_for_budget(pm, batch, budget).tau), 3)
    exact = []
    exact_s, _ = median_time(lambda: exact.append([pmjax.faces_for_budget(pm, pmjax.index_camera(batch, i), budget)
                                                   for i in range(K)]), 3)
    exact = exact[-1]
    hard = pmjax.refine_batch(pm, batch, 1.0)  # warm the engine
    hard = [int(pmjax.refine(pm, pmjax.index_camera(batch, i), float(sol.tau[i])).n_faces) for i in range(K)]
    ratio = [float(sol.tau[i]) / float(exact[i][0]) for i in range(K) if exact[i][0] > 0]
    steps = np.asarray(sol.steps)
    return dict(budget=budget, K=K, exact_ms_per_camera=1e3 * exact_s / K, soft_ms_per_camera=1e3 * soft_s / K,
                steps_median=float(np.median(steps)), steps_max=int(steps.max()),
                converged=float(np.mean(np.asarray(sol.converged))),
                exact_faces_median=statistics.median(e[1] for e in exact),
                hard_faces_at_soft_tau_median=statistics.median(hard),
                hard_faces_error_median=statistics.median(abs(h - budget) / budget for h in hard),
                tau_ratio_median=statistics.median(ratio) if ratio else float("nan"))


def popping(pm, cams, geomorphs, supersample, tau=1.0):
    from pmjax.render import path_fidelity

    rows = []
    for g in [0] + geomorphs:
        fid = path_fidelity(pm, cams, tau, geomorph=g, supersample=supersample, progress=True)[1:]
        rows.append(dict(geomorph=g, supersample=supersample,
                         popping_share=statistics.mean(r["popping_share"] for r in fid),
                         popping_mse=statistics.mean(r["popping_mse"] for r in fid),
                         differing_share=statistics.median(r["differing_share"] for r in fid),
                         faces=statistics.median(r["faces"] for r in fid)))
    for r in rows:
        r["share_ratio"] = rows[0]["popping_share"] / max(r["popping_share"], 1e-12)
        r["mse_ratio"] = rows[0]["popping_mse"] / max(r["popping_mse"], 1e-12)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="bunny,dragon")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--budgets", default="2000,8000")
    ap.add_argument("--popping-frames", type=int, default=240)
    ap.add_argument("--geomorph", default="8,16")
    ap.add_argument("--supersample", type=int, default=4,
                    help="popping renders: s×s samples per pixel (sub-pixel motion needs >= 4)")
    ap.add_argument("--parts", default="cost,budgets,popping", help="which measurements to run")
    ap.add_argument("--json")
    args = ap.parse_args()
    parts = set(args.parts.split(","))
    print(f"machine: {machine()}\n")
    report = dict(machine=machine(), cost=[], budgets=[], popping=[])
    for name in args.models.split(","):
        path = pm_file(name)
        pm = pmjax.load(path)
        verts = np.asarray(pm.vertices)[: pm.n_original_vertices]
        cams = pmjax.standard_orbit(verts, 240)
        if "cost" in parts:
            c = dict(model=name, K=args.batch, **cost(pm, cams, args.batch, args.repeats))
            report["cost"].append(c)
            print(f"{name}: single camera hard {c['hard_ms']:.2f} ms | soft {c['soft_ms']:.2f} ms "
                  f"({c['soft_ms'] / c['hard_ms']:.1f}x) | soft gradient {c['soft_grad_ms']:.2f} ms "
                  f"({c['soft_grad_ms'] / c['hard_ms']:.1f}x)", flush=True)
            print(f"{name}: K={args.batch} hard {c['hard_batch_cams_per_s']:.0f} cams/s | soft "
                  f"{c['soft_batch_cams_per_s']:.0f} cams/s | soft gradient "
                  f"{c['soft_grad_batch_cams_per_s']:.0f} cams/s", flush=True)
        for budget in [int(b) for b in args.budgets.split(",")] if "budgets" in parts else []:
            b = dict(model=name, **budgets(pm, cams, budget, min(args.batch, 64)))
            report["budgets"].append(b)
            print(f"{name}: budget {budget}: exact {b['exact_ms_per_camera']:.2f} ms/camera, soft "
                  f"{b['soft_ms_per_camera']:.2f} ms/camera; steps after the bracket median {b['steps_median']:.0f} max "
                  f"{b['steps_max']}, converged {b['converged']:.0%}; hard faces at soft tau median "
                  f"{b['hard_faces_at_soft_tau_median']:.0f} (error {b['hard_faces_error_median']:.1%}), exact "
                  f"{b['exact_faces_median']:.0f}; tau soft/exact {b['tau_ratio_median']:.3f}", flush=True)
        if "popping" in parts and args.popping_frames and name == args.models.split(",")[0]:
            frames = pmjax.standard_orbit(verts, args.popping_frames)
            for r in popping(pm, frames, [int(g) for g in args.geomorph.split(",")], args.supersample):
                r.update(model=name, frames=args.popping_frames)
                report["popping"].append(r)
                print(f"{name}: {args.popping_frames} frames, geomorph {r['geomorph']:2d}: popping share "
                      f"{r['popping_share']:.4%} ({r['share_ratio']:.2f}x less), mean squared change "
                      f"{r['popping_mse']:.3f} ({r['mse_ratio']:.2f}x less); differing {r['differing_share']:.2%}, "
                      f"faces {r['faces']:.0f}", flush=True)
    if args.json:
        write_json(args.json, report)


if __name__ == "__main__":
    main()
