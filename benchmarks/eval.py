"""Evaluation-job benchmark: streaming, Dask, the compilation cache, many models.

Usage: python benchmarks/eval.py [--parts stream,dask,cache,models,paths,budgets,startup,fidelity]
       [--cameras 1000000] [--dask-cameras 20000] [--path-frames 7680] [--budget-cameras 2048]
       [--budget-models bunny,dragon] [--budget-sets random,orbit]
       [--startup-cameras 100000] [--startup-repeats 3] [--fidelity-cameras 8] [--json out.json]

- stream: random views of the bunny streamed to Parquet by ``pmjax eval`` (a
  child process per run, for its peak RSS): the full set against 10,000
  cameras, and the job's cameras/s against raw ``refine_batch`` on the same
  cameras in the same run.
- dask: the dragon, a local Dask cluster of 2 single-threaded workers against
  one process (both with a warm compilation cache; wall time of the whole job).
- cache: a job over 5 models run twice with a fresh persistent compilation
  cache: time until the first part is written, first run against second.
- models: one process evaluates 30 hierarchies in turn, each at 3 image sizes:
  XLA compilations per model and the RSS after each model.
- paths: the standard orbit of the dragon (7,680 frames) as an evaluation job,
  in-process with the model loaded and the kernels compiled, against
  ``path_counts`` on the same cameras: medians of 3 alternating runs.
- budgets: the bunny and the dragon, random views and the standard orbit: a
  job with three face budgets against a job with three tolerances on the same
  cameras (the budgets: the median face counts of the tolerances), in-process
  with the model loaded and the kernels compiled, start-up subtracted (a job
  of 32 cameras of each kind); medians of 3 alternating runs.
- startup: where a fresh cluster's time goes before its first part (worker
  processes: cluster start, each worker's imports, model load and first
  compile from a warm persistent cache), and the dragon's random views as
  ``pmjax eval`` from a fresh Python: in-process, ``--workers 2`` (threads of
  this process) and a local cluster of 2 single-threaded worker processes;
  time to the first part written and in all, medians of 3 alternating runs.
- fidelity: milliseconds per camera of an orbit job with and without
  ``fidelity`` (bunny and dragon, 800x600, model loaded and compiled),
  medians of 3 alternating runs.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import DATA, machine, write_json  # noqa: E402
from refine import pm_file  # noqa: E402

import pmjax  # noqa: E402

PARTS = ("stream", "dask", "cache", "models", "paths", "budgets", "startup", "fidelity")


def _child(code: str) -> dict:
    """Run ``code`` in a fresh Python; it prints one JSON line last."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


_STREAM_CHILD = """
import json, resource, sys, time
import pmjax
t = time.perf_counter()
s = pmjax.evaluate([{model!r}], ["random:{n}:1"], {folder!r}, taus=[1.0], compile_cache={cache!r}, progress=False)
print(json.dumps(dict(seconds=time.perf_counter() - t, rate=s.cameras_per_s, rows=s.rows,
                      peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)))
"""

_RAW_CHILD = """
import json, time
import pmjax
from pmjax._camera_table import random_rows
pm, data = pmjax.load({model!r}), pmjax.read_pm({model!r})
v0 = data.vertices[: data.n_original_vertices]
pmjax.refine_batch(pm, random_rows(v0, 1, 0, 256).camera(), 1.0)  # compile
busy = 0.0
for lo in range(0, {n}, 4096):
    cams = random_rows(v0, 1, lo, min(lo + 4096, {n})).camera()  # made outside the timing
    t = time.perf_counter()
    pmjax.refine_batch(pm, cams, 1.0)
    busy += time.perf_counter() - t
print(json.dumps(dict(rate={n} / busy)))
"""


def stream(n: int, work: str) -> dict:
    model = pm_file("bunny")
    cache = os.path.join(work, "xla-stream")
    runs = {}
    for count in (10_000, n):
        folder = os.path.join(work, f"stream-{count}")
        runs[count] = _child(_STREAM_CHILD.format(model=model, n=count, folder=folder, cache=cache))
        shutil.rmtree(folder)
    raw = _child(_RAW_CHILD.format(model=model, n=n))
    row = dict(model="bunny", cameras=n, peak_mb_small=runs[10_000]["peak_mb"], peak_mb=runs[n]["peak_mb"],
               eval_rate=runs[n]["rate"], raw_rate=raw["rate"], eval_seconds=runs[n]["seconds"])
    print(f"stream bunny: {n} cameras peak RSS {row['peak_mb']:.0f} MB vs 10,000 cameras {row['peak_mb_small']:.0f} MB "
          f"({row['peak_mb'] / row['peak_mb_small']:.2f}x); eval {row['eval_rate']:.0f} cameras/s vs raw refine_batch "
          f"{row['raw_rate']:.0f} cameras/s ({row['eval_rate'] / row['raw_rate']:.2f}x)", flush=True)
    return row


def dask_vs_process(n: int, work: str) -> dict:
    from dask.distributed import Client, LocalCluster

    model = pm_file("dragon")
    job = dict(taus=[1.0], compile_cache=os.path.join(work, "xla-dask"), progress=False)
    pmjax.evaluate([model], ["random:512:9"], os.path.join(work, "warm"), **job)  # fill the compilation cache
    pmjax._eval._LOADED.clear()

    def timed(seed, **kw):
        folder = os.path.join(work, f"dask-{seed}")
        t = time.perf_counter()
        pmjax.evaluate([model], [f"random:{n}:{seed}"], folder, **job, **kw)
        shutil.rmtree(folder)
        return time.perf_counter() - t

    # Each side twice: the first job loads the model and its kernels, the second finds them.
    process = [timed(1), timed(2)]
    t = time.perf_counter()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster):
        start = time.perf_counter() - t
        dask = [timed(1, scheduler=cluster.scheduler_address), timed(2, scheduler=cluster.scheduler_address)]
    row = dict(model="dragon", cameras=n, process_s=process, cluster_start_s=start, dask_s=dask)
    print(f"dask dragon, {n} cameras: one process {process[0]:.1f} s (then {process[1]:.1f} s with the model loaded); "
          f"local cluster of 2 single-threaded workers {start:.1f} s to start + {dask[0]:.1f} s "
          f"(then {dask[1]:.1f} s on warm workers); rate ratio dask / process: fresh cluster "
          f"{process[0] / (start + dask[0]):.2f}x, warm {process[1] / dask[1]:.2f}x", flush=True)
    return row


FIVE = ("cow", "bunny", "horse", "spot", "gears")

_FIRST_PART_CHILD = """
import json, os, threading, time
t0 = time.perf_counter()
import pmjax
imported = time.perf_counter()
folder, first = {folder!r}, []

def watch():
    while not first:
        if os.path.isdir(folder) and any(n.startswith("part-") for n in os.listdir(folder)):
            first.append(time.perf_counter())
        time.sleep(0.005)

threading.Thread(target=watch, daemon=True).start()
pmjax.evaluate({models!r}, ["orbit:64"], folder, taus=[1.0], compile_cache={cache!r}, progress=False)
end = time.perf_counter()
print(json.dumps(dict(import_s=imported - t0, first_part_s=first[0] - imported, total_s=end - imported)))
"""


def cache(work: str) -> dict:
    models = [pm_file(n) for n in FIVE]
    xla = os.path.join(work, "xla-cache")
    runs = []
    for k in range(2):
        folder = os.path.join(work, f"cache-{k}")
        runs.append(_child(_FIRST_PART_CHILD.format(folder=folder, models=models, cache=xla)))
        shutil.rmtree(folder)
    row = dict(models=list(FIVE), first_run=runs[0], second_run=runs[1])
    print(f"compilation cache, 5 models (after imports, {runs[0]['import_s']:.1f} s): first part after "
          f"{runs[0]['first_part_s']:.2f} s with a cold cache vs {runs[1]['first_part_s']:.2f} s warm = "
          f"{runs[0]['first_part_s'] / runs[1]['first_part_s']:.1f}x sooner; whole job {runs[0]['total_s']:.1f} vs "
          f"{runs[1]['total_s']:.1f} s ({runs[0]['total_s'] / runs[1]['total_s']:.1f}x)", flush=True)
    return row


def _variants(count: int) -> list[str]:
    """``count`` distinct hierarchies: the shared models, each built to a few face targets."""
    from pmjax.builders import BuildOptions, build_pm

    names = [p.stem for p in sorted(DATA.glob("*.ply")) if p.stem not in ("dragon", "terrain_sthelens")]
    out = []
    folder = os.path.join(os.path.dirname(pm_file("cow")), "variants")
    os.makedirs(folder, exist_ok=True)
    for k in range(count):
        name, target = names[k % len(names)], (0, 2000, 500)[k // len(names)]
        path = os.path.join(folder, f"{name}-t{target}.pmz")
        if not os.path.exists(path):
            v, f, _, _ = pmjax.load_clean_mesh(DATA / f"{name}.ply")
            pmjax.save_pm(build_pm(v, f, BuildOptions(target_faces=target)), path)
        out.append(path)
    return out


def models(work: str, count: int = 30) -> dict:
    import jax

    paths = _variants(count)
    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, d, **kw: compiles.append(d) if event == "/jax/core/compile/backend_compile_duration" else None)
    sizes = [(800, 600), (320, 240), (1920, 1080)]
    per_model, rss = [], []
    t0 = time.perf_counter()
    extra = []
    for k, path in enumerate(paths):
        sets = [pmjax.camera_set("orbit:64", width=w, height=h) for w, h in sizes]
        # The first size compiles the model's kernels; the other two must not.
        before = len(compiles)
        pmjax.evaluate([path], sets[:1], os.path.join(work, f"models-{k}a"), taus=[1.0], compile_cache=None,
                       progress=False)
        middle = len(compiles)
        pmjax.evaluate([path], sets[1:], os.path.join(work, f"models-{k}b"), taus=[1.0], compile_cache=None,
                       progress=False)
        per_model.append(middle - before)
        extra.append(len(compiles) - middle)
        with open("/proc/self/statm") as fh:
            rss.append(int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20)
    row = dict(models=count, sizes=len(sizes), compiles_per_model=per_model, compiles_other_sizes=extra, rss_mb=rss,
               seconds=time.perf_counter() - t0)
    print(f"{count} models x {len(sizes)} image sizes in one process: XLA compilations per model "
          f"{min(per_model)}-{max(per_model)} for its first size, {sum(extra)} in all for the other sizes; RSS after model 5 {rss[4]:.0f} MB, "
          f"after model {count} {rss[-1]:.0f} MB (max {max(rss):.0f} MB); {row['seconds']:.0f} s", flush=True)
    return row


def paths(frames: int, work: str, model: str = "dragon", repeats: int = 3) -> dict:
    from pmjax._camera_table import orbit_rows

    path = pm_file(model)
    pm, data = pmjax.load(path), pmjax.read_pm(path)
    cams = orbit_rows(data.vertices[: data.n_original_vertices], frames, 0, frames).camera()
    job = dict(taus=[1.0], compile_cache=None, progress=False)
    pmjax.evaluate([path], [f"orbit:{frames}"], os.path.join(work, "paths-warm"), **job)  # load and compile
    pmjax.path_counts(pm, cams, 1.0)
    times = {"eval": [], "start_up": [], "path_counts": []}
    for k in range(repeats):
        folder = os.path.join(work, f"paths-{k}")
        t = time.perf_counter()
        pmjax.evaluate([path], [f"orbit:{frames}"], folder, **job)
        times["eval"].append(time.perf_counter() - t)
        shutil.rmtree(folder)
        # The job's start-up (reading and hashing the model, the job file) and
        # one small part: what a job of one 16-frame path costs.
        t = time.perf_counter()
        pmjax.evaluate([path], ["orbit:16"], folder, **job)
        times["start_up"].append(time.perf_counter() - t)
        shutil.rmtree(folder)
        t = time.perf_counter()
        pmjax.path_counts(pm, cams, 1.0)
        times["path_counts"].append(time.perf_counter() - t)
    med = {k: float(np.median(v)) for k, v in times.items()}
    steady = med["eval"] - med["start_up"]
    row = dict(model=model, frames=frames, seconds=times, eval_ms_per_frame=1e3 * med["eval"] / frames,
               start_up_s=med["start_up"], eval_steady_ms_per_frame=1e3 * steady / frames,
               path_counts_ms_per_frame=1e3 * med["path_counts"] / frames, ratio=med["eval"] / med["path_counts"],
               steady_ratio=steady / med["path_counts"])
    print(f"paths {model}, orbit of {frames} frames: eval {row['eval_ms_per_frame']:.4f} ms/frame "
          f"({row['eval_steady_ms_per_frame']:.4f} after its start-up of {med['start_up']:.3f} s), path_counts "
          f"{row['path_counts_ms_per_frame']:.4f} ms/frame; ratio {row['ratio']:.2f}x, "
          f"{row['steady_ratio']:.2f}x start-up subtracted", flush=True)
    return row


def budgets(n: int, work: str, repeats: int = 3, models: tuple = ("bunny", "dragon"),
            sets: tuple = ("random", "orbit")) -> list:
    from pmjax._camera_table import orbit_rows, random_rows

    taus = [0.5, 1.0, 2.0]
    rows = []
    for model in models:
        path = pm_file(model)
        pm, data = pmjax.load(path), pmjax.read_pm(path)
        v0 = data.vertices[: data.n_original_vertices]
        for spec in [s for s in (f"random:{n}:7", f"orbit:{n}") if s.split(":")[0] in sets]:
            table = random_rows(v0, 7, 0, n) if spec.startswith("random") else orbit_rows(v0, n, 0, n)
            cams = table.camera()
            values = [int(np.median(pmjax.refine_batch(pm, cams, t)["faces"])) for t in taus]
            small = spec.replace(f":{n}", ":32")
            jobs = {"tau": (spec, dict(taus=taus)), "budget": (spec, dict(budgets=values)),
                    "tau_start": (small, dict(taus=taus)), "budget_start": (small, dict(budgets=values))}
            times = {k: [] for k in jobs}
            for rep in range(repeats + 1):  # the first round loads and compiles
                for kind, (cameras, values_kw) in jobs.items():
                    folder = os.path.join(work, f"budgets-{model}-{kind}-{rep}")
                    t = time.perf_counter()
                    pmjax.evaluate([path], [cameras], folder, compile_cache=None, progress=False, **values_kw)
                    if rep:
                        times[kind].append(time.perf_counter() - t)
                    shutil.rmtree(folder)
            med = {k: float(np.median(v)) for k, v in times.items()}
            steady = {k: med[k] - med[f"{k}_start"] for k in ("tau", "budget")}
            rate = {k: 3 * (n - 32) / steady[k] for k in steady}
            row = dict(model=model, cameras=spec.split(":")[0], n=n, taus=taus, budgets=values, seconds=times,
                       tau_rate=rate["tau"], budget_rate=rate["budget"], ratio=rate["budget"] / rate["tau"])
            print(f"budgets {model} {spec}: tau job (taus {taus}) {rate['tau']:.0f} camera-values/s, budget job "
                  f"(budgets {values}) {rate['budget']:.0f} camera-values/s, budget / tau rate "
                  f"{row['ratio']:.2f} (start-up subtracted)", flush=True)
            rows.append(row)
    return rows


_STARTUP_CHILD = """
import json, os, sys, threading, time
t0 = time.perf_counter()
folder, first = {folder!r}, []


def phases(model, digest, cache):
    # On a fresh worker process (sent by value, so nothing is imported before
    # it runs): seconds to import pmjax's evaluation, load the model, and make
    # and run its first batch (compiled or loaded from the persistent cache).
    t = time.perf_counter()
    import pmjax
    import pmjax._eval as E
    from pmjax._camera_table import random_rows

    out = dict(imports=time.perf_counter() - t)
    t = time.perf_counter()
    E._compile_cache(cache)
    pm, _ = E._model(model, digest)
    out["model"] = time.perf_counter() - t
    data = pmjax.read_pm(model)
    cams = random_rows(data.vertices[: data.n_original_vertices], 1, 0, 256).camera()
    t = time.perf_counter()
    pmjax.refine_batch(pm, cams, 1.0, chunk=256)
    out["compile"] = time.perf_counter() - t
    return out

def watch():
    while not first:
        if os.path.isdir(folder) and any(n.startswith("part-") for n in os.listdir(folder)):
            first.append(time.perf_counter())
        time.sleep(0.005)

if __name__ == "__main__":
    # Imported here: worker processes start by importing this file, and the
    # imports are part of what each worker pays before its first task.
    sys.path.insert(0, {bench!r})
    import pmjax
    from dask.distributed import LocalCluster

    threading.Thread(target=watch, daemon=True).start()
    job = dict(taus=[1.0], compile_cache={cache!r}, progress=False)
    found = None
    if {mode!r} == "processes":
        t = time.perf_counter()
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
            start = time.perf_counter() - t
            if {breakdown!r}:
                from dask.distributed import Client
                from pmjax._pmfile import file_sha256
                with Client(cluster, set_as_default=False) as client:
                    digest = file_sha256({model!r})
                    futures = [client.submit(phases, {model!r}, digest, {cache!r}, pure=False, workers=[w])
                               for w in client.scheduler_info()["workers"]]
                    found = dict(cluster_start=start, workers=[f.result() for f in futures])
            else:
                pmjax.evaluate([{model!r}], ["random:{n}:3"], folder, scheduler=cluster.scheduler_address, **job)
    else:
        pmjax.evaluate([{model!r}], ["random:{n}:3"], folder, workers={workers}, **job)
    end = time.perf_counter()
    print(json.dumps(dict(first_s=(first[0] - t0) if first else None, total_s=end - t0, phases=found)))
"""


def startup(n: int, work: str, repeats: int = 3) -> dict:
    """The breakdown, then ``repeats`` alternating runs of each variant (0: the breakdown only)."""
    model = pm_file("dragon")
    cache_dir = os.path.join(work, "xla-startup")
    pmjax.evaluate([model], ["random:4096:3"], os.path.join(work, "startup-warm"), taus=[1.0], compile_cache=cache_dir,
                   progress=False)  # fill the compilation cache
    bench = os.path.dirname(os.path.abspath(__file__))

    def child(mode, breakdown=False):
        folder = os.path.join(work, f"startup-{mode}")
        code = _STARTUP_CHILD.format(bench=bench, folder=folder, cache=cache_dir, mode=mode, breakdown=breakdown,
                                     model=model, n=n, workers=2 if mode == "threads" else 0)
        path = os.path.join(work, f"startup_{mode}.py")  # a file: worker processes start by importing it
        with open(path, "w") as fh:
            fh.write(code)
        out = subprocess.run([sys.executable, path], capture_output=True, text=True, check=True, cwd=work)
        shutil.rmtree(folder, ignore_errors=True)
        return json.loads(out.stdout.strip().splitlines()[-1])

    phases = child("processes", breakdown=True)["phases"]
    runs = {m: [] for m in ("process", "threads", "processes")}
    for _ in range(repeats):
        for mode in runs:
            runs[mode].append(child(mode))
    med = {m: dict(first_s=float(np.median([r["first_s"] for r in rs])),
                   total_s=float(np.median([r["total_s"] for r in rs]))) for m, rs in runs.items() if rs}
    workers = phases["workers"]
    row = dict(model="dragon", cameras=n, phases=phases, runs=runs, medians=med)
    print(f"startup, fresh cluster of 2 worker processes (dragon, warm compile cache): cluster start "
          f"{phases['cluster_start']:.2f} s; per worker imports "
          + ", ".join(f"{w['imports']:.2f}" for w in workers) + " s, model load "
          + ", ".join(f"{w['model']:.2f}" for w in workers) + " s, first batch (kernel load) "
          + ", ".join(f"{w['compile']:.2f}" for w in workers) + " s", flush=True)
    for mode, m in med.items():
        print(f"startup dragon {n} random views, {mode}: first part after {m['first_s']:.1f} s, all after "
              f"{m['total_s']:.1f} s (from a fresh Python)", flush=True)
    return row


def fidelity(count: int, work: str, repeats: int = 3) -> list:
    rows = []
    for name in ("bunny", "dragon"):
        model = pm_file(name)
        job = dict(taus=[1.0], compile_cache=None, progress=False)
        pmjax.evaluate([model], [f"orbit:{count}"], os.path.join(work, f"fid-warm-{name}"), fidelity=True, **job)
        times = {False: [], True: []}
        for k in range(repeats):
            for on in (False, True):
                folder = os.path.join(work, f"fid-{name}-{on}-{k}")
                t = time.perf_counter()
                pmjax.evaluate([model], [f"orbit:{count}"], folder, fidelity=on, **job)
                times[on].append(time.perf_counter() - t)
                shutil.rmtree(folder)
        off, on = (1e3 * float(np.median(times[x])) / count for x in (False, True))
        rows.append(dict(model=name, cameras=count, seconds={str(k): v for k, v in times.items()}, ms_per_camera=off,
                         fidelity_ms_per_camera=on))
        print(f"fidelity {name}, orbit of {count} cameras at 800x600: {off:.1f} ms per camera without, "
              f"{on:.0f} ms with fidelity ({on / off:.0f}x)", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--cameras", type=int, default=1_000_000)
    ap.add_argument("--dask-cameras", type=int, default=20_000)
    ap.add_argument("--path-frames", type=int, default=7680)
    ap.add_argument("--budget-cameras", type=int, default=2048)
    ap.add_argument("--budget-models", default="bunny,dragon", help="budgets: the models, comma-separated")
    ap.add_argument("--budget-sets", default="random,orbit", help="budgets: the camera sets (random, orbit)")
    ap.add_argument("--startup-cameras", type=int, default=100_000)
    ap.add_argument("--startup-repeats", type=int, default=3)
    ap.add_argument("--fidelity-cameras", type=int, default=8)
    ap.add_argument("--json")
    args = ap.parse_args()
    parts = args.parts.split(",")
    print(machine(), flush=True)
    report = dict(machine=machine())
    with tempfile.TemporaryDirectory(prefix="pmjax-bench-eval-") as work:
        if "stream" in parts:
            report["stream"] = stream(args.cameras, work)
        if "dask" in parts:
            report["dask"] = dask_vs_process(args.dask_cameras, work)
        if "cache" in parts:
            report["cache"] = cache(work)
        if "models" in parts:
            report["models"] = models(work)
        if "paths" in parts:
            report["paths"] = paths(args.path_frames, work)
        if "budgets" in parts:
            report["budgets"] = budgets(args.budget_cameras, work, models=tuple(args.budget_models.split(",")),
                                        sets=tuple(args.budget_sets.split(",")))
        if "startup" in parts:
            report["startup"] = startup(args.startup_cameras, work, args.startup_repeats)
        if "fidelity" in parts:
            report["fidelity"] = fidelity(args.fidelity_cameras, work)
    print(f"peak RSS of this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    if args.json:
        write_json(args.json, report)


if __name__ == "__main__":
    main()
