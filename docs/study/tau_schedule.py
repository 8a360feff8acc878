"""Worked study: choose a tolerance per frame along a camera path to minimise the
screen-space error under a total face budget, with optimistix.

Usage: python docs/study/tau_schedule.py [--pm MODEL.pmz] [--frames 48] [--budget-share 0.2]
       [--path flight|orbit] [--out docs/figures] [--json RESULTS.json]

Without ``--pm`` it builds the model bundled with pmjax (Spot). With ``--path
flight`` (the default) the camera flies in from far away, passes close to the
model and leaves again, so frames differ in how many faces a given tolerance
needs; ``--path orbit`` takes the standard orbit (``pmjax.standard_orbit``),
where frames differ in what faces the camera and in the silhouette.

Three schedules spend the same total number of faces, ``frames × budget``
(``budget`` = ``--budget-share`` of the original faces):

- constant: one tau for every frame (root find of the total soft face count);
- equal faces: every frame gets ``budget`` faces (:func:`pmjax.soft_tau_for_budget`);
- optimised: per-frame tau minimising ``Σ_i E_i²``, the sum of squared soft
  screen-space errors per frame (one frame with a large error is worse than
  several with small ones), subject to the total face count, by an augmented
  Lagrangian whose inner problems optimistix's BFGS solves over ``log tau``.

For the plain sum ``Σ_i E_i`` the constant tau is already optimal: it
collapses exactly the pcols of smallest error across all frames; the squared
objective trades some of that total for a more even error along the path.

Soft quantities use a temperature of 5 % of each frame's tau. The hard face
count and hard error (the soft ones at zero temperature) are reported for each
schedule; the plot shows tau and hard faces per frame.

It also reports what the study costs: the compile time and the warm time of
one value and gradient of the objective over all frames, the optimiser's wall
time and steps, and the process's peak memory.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import pmjax

RELATIVE_TEMPERATURE = 0.05
FRAMES_AT_ONCE = 4


def flight(vertices, frames: int):
    """Cameras flying from far away past the model and out again."""
    lo, hi = vertices.min(0), vertices.max(0)
    centre, r = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    keys = [(centre + r * np.array([0.0, 0.6, 9.0]), centre),
            (centre + r * np.array([1.2, 0.3, 1.6]), centre),
            (centre + r * np.array([2.4, 0.2, -1.2]), centre),
            (centre + r * np.array([3.0, 0.8, -7.0]), centre)]
    return pmjax.fly_through(keys, frames)


def per_frame(pm, cams, log_tau, temperature_share=RELATIVE_TEMPERATURE):
    """Soft faces and soft error (pixels) per frame for per-frame ``log tau``."""

    # A few frames at a time, checkpointed: memory follows FRAMES_AT_ONCE, not
    # the path's length, and reverse mode recomputes each group's refinement
    # instead of keeping its intermediates (one more forward pass).
    @jax.checkpoint
    def one(frame):
        cam, s = frame
        tau = jnp.exp(s)
        soft = pmjax.soft_refine(pm, cam, tau, temperature_share * tau)
        return soft.faces, soft.error

    return jax.lax.map(one, (cams, log_tau), batch_size=FRAMES_AT_ONCE)


def constant_schedule(pm, cams, total):
    """One tau for all frames whose total soft face count is ``total`` (Newton on log tau)."""
    K = pmjax.camera_count(cams)

    def excess(s, _):
        faces, _ = per_frame(pm, cams, jnp.full(K, s))
        return jnp.log(jnp.sum(faces)) - jnp.log(total)

    sol = optx.root_find(excess, optx.Newton(rtol=1e-5, atol=1e-5), jnp.float32(0.0), max_steps=50)
    return jnp.full(K, sol.value)


def optimised_schedule(pm, cams, total, start, outer: int = 8, penalty: float = 50.0):
    """Per-frame log tau minimising Σ error² subject to Σ faces = total.

    Augmented Lagrangian on the constraint ``c = Σ faces / total − 1``: each
    outer round minimises ``Σ error² / S0 + λ c + (ρ/2) c²`` with BFGS, then
    ``λ += ρ c``.
    """
    _, err0 = per_frame(pm, cams, start)
    scale = jnp.sum(err0**2)

    def objective(s, lam):
        faces, error = per_frame(pm, cams, s)
        c = jnp.sum(faces) / total - 1.0
        return jnp.sum(error**2) / scale + lam * c + 0.5 * penalty * c * c

    solver = optx.BFGS(rtol=1e-5, atol=1e-5)
    s, lam, history = start, jnp.float32(0.0), []
    for _ in range(outer):
        t0 = time.perf_counter()
        sol = optx.minimise(objective, solver, s, lam, max_steps=200, throw=False)
        s = jax.block_until_ready(sol.value)
        seconds = time.perf_counter() - t0
        faces, error = per_frame(pm, cams, s)
        c = float(jnp.sum(faces) / total - 1.0)
        history.append(dict(constraint=c, squared_error=float(jnp.sum(error**2)), steps=int(sol.stats["num_steps"]),
                            seconds=seconds))
        lam = lam + penalty * c
        if abs(c) < 1e-3:
            break
    return s, history


def gradient_cost(pm, cams, log_tau, repeats: int = 3) -> dict:
    """Compile time and warm time of one value and gradient of a per-frame
    objective (``Σ error² + Σ faces``) over all frames."""
    value_and_grad = jax.jit(jax.value_and_grad(lambda s: jnp.sum(sum(x**2 for x in per_frame(pm, cams, s)))))
    t0 = time.perf_counter()
    compiled = value_and_grad.lower(log_tau).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(log_tau))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(log_tau))
        times.append(time.perf_counter() - t0)
    warm = float(np.median(times))
    return dict(compile_s=compile_s, gradient_s=warm, gradient_ms_per_frame=1e3 * warm / len(log_tau))


def hard_totals(pm, cams, log_tau):
    """Hard faces and hard error per frame (zero temperature: the engine's refinement)."""
    faces, errors = [], []
    for i in range(pmjax.camera_count(cams)):
        cam = pmjax.index_camera(cams, i)
        tau = float(jnp.exp(log_tau[i]))
        faces.append(int(pmjax.refine(pm, cam, tau).n_faces))
        errors.append(float(pmjax.soft_refine(pm, cam, tau, 1e-30).error))
    return np.array(faces), np.array(errors)


def build_default(workdir):
    from pmjax.builders import build_pm

    v, f, _, _ = pmjax.load_clean_mesh(pmjax.default_model_path())
    path = os.path.join(workdir, "spot.pmz")
    pmjax.save_pm(build_pm(v, f), path)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pm", help="progressive mesh (.pmz); default: build the bundled model")
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--budget-share", type=float, default=0.2, help="faces per frame, share of the original")
    ap.add_argument("--path", choices=("flight", "orbit"), default="flight", help="camera path (default: flight)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "..", "figures"))
    ap.add_argument("--json")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        pm = pmjax.load(args.pm or build_default(tmp))
    verts = np.asarray(pm.vertices)[: pm.n_original_vertices]
    cams = flight(verts, args.frames) if args.path == "flight" else pmjax.standard_orbit(verts, args.frames)
    budget = args.budget_share * pm.n_faces
    total = budget * args.frames

    started = time.perf_counter()
    schedules = {"constant": constant_schedule(pm, cams, total)}
    equal = pmjax.soft_tau_for_budget(pm, cams, budget)
    schedules["equal faces"] = jnp.log(equal.tau)
    cost = gradient_cost(pm, cams, schedules["constant"])
    t0 = time.perf_counter()
    schedules["optimised"], history = optimised_schedule(pm, cams, total, schedules["constant"])
    cost.update(optimiser_s=time.perf_counter() - t0, optimiser_steps=sum(h["steps"] for h in history),
                schedules_s=time.perf_counter() - started)

    cost["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    results = dict(frames=args.frames, path=args.path, budget_per_frame=budget, total_budget=total,
                   original_faces=pm.n_faces, pcols=pm.n_pcols, augmented_lagrangian=history, cost=cost, schedules={})
    print(f"{args.frames} frames ({args.path}), budget {budget:.0f} faces per frame ({total:.0f} in all)")
    print(f"cost: value and gradient over all frames compiles in {cost['compile_s']:.1f} s, runs in "
          f"{1e3 * cost['gradient_s']:.0f} ms ({cost['gradient_ms_per_frame']:.1f} ms per frame); optimiser "
          f"{cost['optimiser_s']:.1f} s for {cost['optimiser_steps']} BFGS steps; three schedules in "
          f"{cost['schedules_s']:.1f} s; peak memory {cost['peak_mb']:.0f} MB")
    for name, s in schedules.items():
        soft_faces, soft_error = per_frame(pm, cams, s)
        faces, error = hard_totals(pm, cams, s)
        results["schedules"][name] = dict(
            tau=np.exp(np.asarray(s)).tolist(), soft_faces_total=float(jnp.sum(soft_faces)),
            soft_error_total=float(jnp.sum(soft_error)), soft_squared_error=float(jnp.sum(soft_error**2)),
            hard_faces=faces.tolist(), hard_error=error.tolist(), hard_faces_total=int(faces.sum()),
            hard_error_total=float(error.sum()), hard_squared_error=float((error**2).sum()))
        print(f"  {name:12s} soft: faces {float(jnp.sum(soft_faces)):8.0f}, Σ error {float(jnp.sum(soft_error)):8.0f} px, "
              f"Σ error² {float(jnp.sum(soft_error**2)):.3e} | hard: faces {faces.sum():7d}, Σ error {error.sum():8.0f} px, "
              f"Σ error² {(error**2).sum():.3e}, max {error.max():6.0f} px")

    os.makedirs(args.out, exist_ok=True)
    # The bundled model's flight keeps the plain name; others say what they show.
    stem = "" if not args.pm and args.path == "flight" else \
        f"_{os.path.splitext(os.path.basename(args.pm or 'spot'))[0]}_{args.path}"
    png = os.path.join(args.out, f"study_tau_schedule{stem}.png")
    plot(results, png)
    results["plot"] = png
    print(f"plot: {png}")
    if args.json:
        from pmjax._atomic import atomic_path

        with atomic_path(args.json) as tmp_path, open(tmp_path, "w") as fh:
            json.dump(results, fh, indent=1)
    return results


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pmjax._atomic import atomic_path

    fig, (ax_tau, ax_faces, ax_error) = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for name, r in results["schedules"].items():
        ax_tau.plot(r["tau"], label=name)
        ax_faces.plot(r["hard_faces"], label=name)
        ax_error.plot(r["hard_error"], label=f"{name} (Σ error² {r['hard_squared_error']:.2e})")
    ax_faces.axhline(results["budget_per_frame"], color="grey", lw=0.8, ls="--", label="budget per frame")
    ax_tau.set_yscale("log")
    ax_tau.set_ylabel("tau (pixels)")
    ax_faces.set_ylabel("faces drawn")
    ax_error.set_ylabel("screen-space error (px)")
    ax_error.set_xlabel("frame")
    for ax in (ax_tau, ax_faces, ax_error):
        ax.legend(fontsize=8)
    ax_tau.set_title(f"Same total faces, {results['frames']} frames: where to spend them")
    fig.tight_layout()
    with atomic_path(path, ".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


if __name__ == "__main__":
    main()
