"""Builder benchmark: time, memory, hierarchy size and LOD quality vs fast-simplification.

Usage: python benchmarks/build.py [--models bunny,dragon,terrain_sthelens] [--repeats 3] [--samples 200000]
       python benchmarks/build.py --sweep 0.25,0.5,0.75,1 [--models bunny,dragon] [--repeats 3]

Each model is built in a fresh subprocess: a first build gives the peak RSS
(loading and building), then timed builds alternate with fast-simplification
runs to 1 % of the faces in that process, and the ratio of the medians is
reported; then the same back to back (all fast-simplification runs, then all
builds); then the build time of the same hierarchy without the C loops. Quality is the
symmetric Hausdorff and RMS distance / bbox diagonal between the original and the
LOD at ~10 % and ~1 % of the faces, next to fast-simplification at the same face
counts, in the same run.

``--sweep`` builds each model in process at each batch share (the share of the
cheapest candidates a batch may take from) and reports, against one
fast-simplification run to 1 % of the faces timed in the same process: build
time (median of the repeats) and its ratio to fast-simplification, batches,
RMS and Hausdorff distance / diagonal at 10 % and 1 %, and the faces drawn at
tau = 1 px along the standard orbit (median of 24 frames, the hierarchy's
quality for view-dependent use: fewer faces for the same error is better).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import DATA, machine, median_time, write_json  # noqa: E402


def one_model(name: str, repeats: int, samples: int) -> dict:
    import resource

    import pmjax
    from pmjax.builders import _native, build_pm

    v, f, _, _ = pmjax.load_clean_mesh(DATA / f"{name}.ply")
    try:
        import fast_simplification
    except ImportError:
        fast_simplification = None
    v32, f32 = v.astype(np.float32), f.astype(np.int32)
    holder = {}

    def simplify():
        fast_simplification.simplify(v32, f32, target_reduction=0.99)

    def build():
        holder.update(pm=build_pm(v, f))

    # A first build, alone in the process so far: the peak RSS is loading
    # and building (and this build's time, with fresh pages, is not counted).
    build()
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    # Then builds alternate with fast-simplification runs to 1 %, so that
    # both see the same load on the machine.
    times, fs_times = [], []
    for _ in range(repeats):
        if fast_simplification is not None:
            fs_times.append(median_time(simplify, 1)[0])
        times.append(median_time(build, 1)[0])
    med = float(np.median(times))
    pm = holder["pm"]
    # Back to back as well: all fast-simplification runs, then all builds
    # (fast-simplification runs faster on warm caches; the other reading).
    b2b_fs, b2b_build = [], []
    if fast_simplification is not None:
        _, b2b_fs = median_time(simplify, repeats)
        _, b2b_build = median_time(build, repeats)
    # The same hierarchy without the C loops (NumPy batch choice).
    numpy_s = None
    if _native.available():
        with _native.use_native(False):
            numpy_s, _ = median_time(build, repeats)
    diag = float(np.linalg.norm(np.ptp(v, 0)))
    row = dict(model=name, faces=len(f), vertices=len(v), build_s=med, build_runs_s=times, peak_rss_mb=peak_mb,
               fs_1pct_s=float(np.median(fs_times)) if fs_times else None, fs_runs_s=fs_times,
               numpy_build_s=numpy_s, native=_native.available(),
               back_to_back=dict(fs_runs_s=b2b_fs, build_runs_s=b2b_build),
               pcols=pm.n_pcols, batches=pm.n_batches, base_faces=pm.header["build"]["base_faces"], quality=[])
    for frac in (0.1, 0.01):
        n = pmjax.pcols_for_faces(pm, int(frac * len(f)))
        lv, lf, _ = pmjax.mesh_for_executed(pm, pmjax.prefix_executed(pm, n))
        d = pmjax.surface_distance((v, f), (lv, lf), samples)
        q = dict(fraction=frac, faces=len(lf), rms=d["rms"] / diag, hausdorff=d["hausdorff"] / diag)
        if fast_simplification is not None:
            fv, ff = fast_simplification.simplify(v.astype(np.float32), f.astype(np.int32),
                                                  target_reduction=1 - len(lf) / len(f))
            fd = pmjax.surface_distance((v, f), (fv, ff), samples)
            q.update(fs_faces=len(ff), fs_rms=fd["rms"] / diag, fs_hausdorff=fd["hausdorff"] / diag)
        row["quality"].append(q)
    return row


def sweep_model(name: str, shares: list[float], repeats: int, samples: int) -> list[dict]:
    import fast_simplification

    import pmjax
    from pmjax.builders import BuildOptions, build_pm

    v, f, _, _ = pmjax.load_clean_mesh(DATA / f"{name}.ply")
    diag = float(np.linalg.norm(np.ptp(v, 0)))
    v32, f32 = v.astype(np.float32), f.astype(np.int32)
    fs_s, _ = median_time(lambda: fast_simplification.simplify(v32, f32, target_reduction=0.99), repeats)
    rows = []
    for share in shares:
        holder = {}
        build_s, _ = median_time(lambda: holder.update(pm=build_pm(v, f, BuildOptions(batch_share=share))), repeats)
        data = holder["pm"]
        row = dict(model=name, batch_share=share, build_s=build_s, fs_1pct_s=fs_s, batches=data.n_batches,
                   pcols=data.n_pcols)
        for frac in (0.1, 0.01):
            n = pmjax.pcols_for_faces(data, int(frac * len(f)))
            lv, lf, _ = pmjax.mesh_for_executed(data, pmjax.prefix_executed(data, n))
            d = pmjax.surface_distance((v, f), (lv, lf), samples)
            row[f"rms_{frac}"], row[f"hausdorff_{frac}"] = d["rms"] / diag, d["hausdorff"] / diag
        pm = pmjax.ProgressiveMesh.from_data(data)
        cams = pmjax.standard_orbit(v, 24)
        row["faces_tau1"] = int(np.median(pmjax.refine_batch(pm, cams, 1.0)["faces"]))
        rows.append(row)
        print(f"{name:8s} share {share:4.2f}: build {build_s:6.2f} s ({build_s / fs_s:5.1f}x fast-simplification "
              f"{fs_s:.2f} s) | {row['batches']:3d} batches | 10 %: RMS {row['rms_0.1']:.3e} Hausdorff "
              f"{row['hausdorff_0.1']:.3e} | 1 %: RMS {row['rms_0.01']:.3e} Hausdorff {row['hausdorff_0.01']:.3e} | "
              f"faces at tau 1: {row['faces_tau1']}", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="bunny,dragon,terrain_sthelens")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--sweep", help="comma-separated batch shares to compare (in process)")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    ap.add_argument("--json", help="also write the rows as JSON")
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one_model(args.one, args.repeats, args.samples)))
        return
    print(f"machine: {machine()}")
    if args.sweep:
        shares = [float(x) for x in args.sweep.split(",")]
        rows = [r for name in args.models.split(",") for r in sweep_model(name, shares, args.repeats, args.samples)]
        if args.json:
            write_json(args.json, dict(machine=machine(), sweep=rows))
        return
    rows = []
    for name in args.models.split(","):
        out = subprocess.run([sys.executable, __file__, "--one", name, "--repeats", str(args.repeats),
                              "--samples", str(args.samples)], capture_output=True, text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"\n{name}: {r['faces']} faces -> {r['pcols']} pcols, {r['batches']} batches, base {r['base_faces']} faces")
        print(f"  build median of {args.repeats}: {r['build_s']:.2f} s  (runs: {', '.join(f'{t:.2f}' for t in r['build_runs_s'])})"
              f"  peak RSS {r['peak_rss_mb']:.0f} MB")
        if r["fs_1pct_s"]:
            print(f"  fast-simplification to 1 %, same process: {r['fs_1pct_s']:.2f} s  (runs: "
                  f"{', '.join(f'{t:.2f}' for t in r['fs_runs_s'])})  ->  build / fast-simplification "
                  f"{r['build_s'] / r['fs_1pct_s']:.2f}x")
        b2b = r["back_to_back"]
        if b2b["fs_runs_s"]:
            fs_b, build_b = float(np.median(b2b["fs_runs_s"])), float(np.median(b2b["build_runs_s"]))
            print(f"  back to back ({args.repeats} fast-simplification runs, then {args.repeats} builds): "
                  f"{fs_b:.3f} s and {build_b:.3f} s  ->  {build_b / fs_b:.2f}x")
        if r["numpy_build_s"]:
            print(f"  without the C loops (NumPy batch choice, same hierarchy): {r['numpy_build_s']:.2f} s")
        for q in r["quality"]:
            line = f"  {q['fraction']:>4.0%}: {q['faces']} faces  RMS/diag {q['rms']:.3e}  Hausdorff/diag {q['hausdorff']:.3e}"
            if "fs_rms" in q:
                line += (f"  | fast-simplification {q['fs_faces']} faces  RMS/diag {q['fs_rms']:.3e}  "
                         f"Hausdorff/diag {q['fs_hausdorff']:.3e}  (RMS ratio pmjax/fs {q['rms'] / q['fs_rms']:.2f})")
            print(line)
    if args.json:
        write_json(args.json, dict(machine=machine(), rows=rows))


if __name__ == "__main__":
    main()
