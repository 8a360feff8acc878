"""Large models made from the shared data: build, file and refine at millions of faces.

A model is ``NAME:LEVELS``: the shared mesh ``NAME`` (``dragon``,
``terrain_gcanyon``, ...) with every triangle split in four ``LEVELS`` times
(edge midpoints), each new vertex moved by Gaussian noise of 5 % of the
original mesh's median edge length (seeded), so that the hierarchy is not a
replay of the subdivision. ``dragon:1`` has 3.5 M faces, ``dragon:2`` 14 M,
``terrain_gcanyon:4`` 20 M; ``dragon:0`` is the original, for comparison.
Nothing is kept: each model is made by a subprocess into a temporary
folder (``.npy``, float64 positions, int32 faces as the mesh loaders give
them) and removed after its row.

Each model in a fresh subprocess, same run: it reads the model, then one
build (time, and the peak RSS of the process: imports, the model's arrays
and the build, per input face), then one fast-simplification run to 1 % of
the faces; the ``.pmz`` sizes as version 1 and version 2; ``pmjax.load`` of
each (median of 3, alternating, structure known); and ``pmjax.refine`` at
tau = 1 px along the standard orbit (24 frames, medians of time and faces
after two warm-up frames), and ``Refinement.mesh()`` of each frame's
refinement (median).

``--stages MODEL`` instead builds one model with its main thread's steps
labelled (edges, costs, the cheapest share, the batch choice, ...) and the
process's RSS sampled every 2 ms: per step the peak RSS above the model's
arrays (per input face) and the main thread's time in it.

``--alternate A,B`` instead times refine and ``Refinement.mesh()`` of two
models side by side in one process, pinned to ``--cores`` CPUs (one by
default): each is made and built once by subprocesses (its ``.pmz`` kept in
``--keep``, and read from there when it is already made; a ``.pmz`` path may
stand for a model), both are loaded, then every round runs the 24 standard-
orbit frames at tau = 1 px, alternating the models frame by frame (refine of
A, its ``mesh()``, refine of B, its ``mesh()``), after two warm-up frames of
each. Per model the median over each round's frames, the median over
``--rounds`` rounds, and the ratio B / A of those medians, so that both run
under the same load and caches: of refine (counts only), of ``mesh()``, and
of the two together per frame (a drawable mesh from a camera).

Usage::

    python benchmarks/large.py [--models dragon:0,dragon:1] [--json out.json]
    python benchmarks/large.py --stages dragon:1
    taskset -c 0 python benchmarks/large.py --alternate dragon:0,dragon:2 --keep /tmp/large --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import DATA, machine, pin_cores, write_json  # noqa: E402

NOISE = 0.05
SEED = 44


def subdivide(v: np.ndarray, f: np.ndarray, rng, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle split in four at its edge midpoints (shared between
    neighbours), the new vertices moved by Gaussian noise of ``sigma``."""
    V = len(v)
    edges = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2), axis=1)
    key = edges[:, 0].astype(np.int64) * V + edges[:, 1]
    uniq, inv = np.unique(key, return_inverse=True)
    a, b = uniq // V, uniq % V
    mid = (v[a] + v[b]) / 2 + rng.normal(0.0, sigma, (len(uniq), 3))
    m = (V + inv).reshape(-1, 3)  # midpoints of edges 01, 12, 20
    c0, c1, c2 = f[:, 0], f[:, 1], f[:, 2]
    faces = np.concatenate([np.stack([c0, m[:, 0], m[:, 2]], 1), np.stack([c1, m[:, 1], m[:, 0]], 1),
                            np.stack([c2, m[:, 2], m[:, 1]], 1), m])
    return np.concatenate([v, mid]), faces.astype(np.int64)


def make(spec: str) -> tuple[np.ndarray, np.ndarray]:
    import pmjax

    name, _, levels = spec.partition(":")
    v, f, _, _ = pmjax.load_clean_mesh(DATA / f"{name}.ply")
    v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1)
    sigma = NOISE * float(np.median(edge))
    rng = np.random.default_rng(SEED)
    for _ in range(int(levels or 0)):
        v, f = subdivide(v, f, rng, sigma)
    # Positions as a mesh file stores them (float32).
    return v.astype(np.float32).astype(np.float64), f


def save_model(spec: str, folder: str) -> float:
    """Make ``spec`` into ``folder`` (``v.npy``, ``f.npy``); seconds taken."""
    t = time.perf_counter()
    v, f = make(spec)
    np.save(os.path.join(folder, "v.npy"), v)
    np.save(os.path.join(folder, "f.npy"), f.astype(np.int32))
    return time.perf_counter() - t


def one_model(spec: str, folder: str) -> dict:
    import resource

    import pmjax
    from pmjax.builders import build_pm

    v, f = np.load(os.path.join(folder, "v.npy")), np.load(os.path.join(folder, "f.npy"))
    t = time.perf_counter()
    pm = build_pm(v, f)
    build_s = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    try:
        import fast_simplification

        t = time.perf_counter()
        fast_simplification.simplify(v.astype(np.float32), f.astype(np.int32), target_reduction=0.99)
        fs_s = time.perf_counter() - t
    except ImportError:
        fs_s = None
    work = tempfile.mkdtemp(prefix="pmjax-large-")
    os.environ["PMJAX_KNOWN_STRUCTURES"] = os.path.join(work, "known")
    paths = {1: os.path.join(work, "v1.pmz"), 2: os.path.join(work, "v2.pmz")}
    save_s = {}
    for version, path in paths.items():
        t = time.perf_counter()
        pmjax.save_pm(pm, path, version=version)
        save_s[version] = time.perf_counter() - t
    sizes = {version: os.path.getsize(path) for version, path in paths.items()}
    loads = {1: [], 2: []}
    for _ in range(3):
        for version, path in paths.items():
            t = time.perf_counter()
            mesh = pmjax.load(path)
            loads[version].append(time.perf_counter() - t)
    times, faces, mesh_times = [], [], []
    for cam in orbit_frames(mesh):
        refine_s, n, mesh_s = time_frame(mesh, cam)
        times.append(refine_s)
        faces.append(n)
        mesh_times.append(mesh_s)
    shutil.rmtree(work)
    return dict(model=spec, faces=len(f), vertices=len(v), pcols=pm.n_pcols, batches=pm.n_batches,
                build_s=build_s, fs_1pct_s=fs_s, peak_rss_bytes=peak,
                peak_bytes_per_face=peak / len(f), v1_bytes=sizes[1], v2_bytes=sizes[2],
                save_v1_s=save_s[1], save_v2_s=save_s[2], load_v1_s=statistics.median(loads[1]),
                load_v2_s=statistics.median(loads[2]), refine_ms=1e3 * statistics.median(times),
                refine_faces=int(statistics.median(faces)), mesh_ms=1e3 * statistics.median(mesh_times))


def save_built(folder: str, path: str) -> float:
    """Build the model in ``folder`` (``v.npy``, ``f.npy``) and save it to
    ``path`` (``.pmz``, as ``pmjax build`` writes it); seconds taken."""
    import pmjax
    from pmjax.builders import build_pm

    t = time.perf_counter()
    pm = build_pm(np.load(os.path.join(folder, "v.npy")), np.load(os.path.join(folder, "f.npy")))
    pmjax.save_pm(pm, path)
    return time.perf_counter() - t


def kept_model(spec: str, keep: str) -> str:
    """The ``.pmz`` of ``spec``: the path itself for a ``.pmz`` file, else
    ``keep/NAME_LEVELS.pmz``, made and built by subprocesses if not there
    (the build's peak memory is kept out of this process); a file already
    there is reused, and said so: delete it to build it with this checkout."""
    if spec.endswith(".pmz"):
        if not os.path.isfile(spec):
            raise FileNotFoundError(f"--alternate: no model file {spec}")
        return spec
    name, _, levels = spec.partition(":")
    path = os.path.join(keep, f"{name}_{levels or 0}.pmz")
    if os.path.isfile(path):
        print(f"{spec}: reusing {path} (delete it to build again)")
        return path
    os.makedirs(keep, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="pmjax-large-model-") as folder:
        for step in (["--make", spec], ["--save-built", path]):
            done = subprocess.run([sys.executable, __file__, *step, "--folder", folder], capture_output=True,
                                  text=True)
            if done.returncode:
                raise RuntimeError(f"{spec}: {step[0]} failed\n{done.stderr[-2000:]}")
    return path


def orbit_frames(mesh) -> list:
    """The 24 cameras of the standard orbit around ``mesh``, one per frame,
    after two warm-up frames (the first calls compile and size the scratch)."""
    import jax

    import pmjax

    orbit = pmjax.standard_orbit(mesh.vertices[: mesh.n_original_vertices], 24)
    frames = [jax.tree.map(lambda x, i=i: x[i], orbit) for i in range(24)]
    for cam in frames[:2]:
        time_frame(mesh, cam)
    return frames


def time_frame(mesh, cam) -> tuple[float, int, float]:
    """Seconds of one ``refine`` of ``mesh`` at tau = 1 px from ``cam``, the
    faces it draws, and seconds of its ``mesh()``."""
    import pmjax

    t = time.perf_counter()
    r = pmjax.refine(mesh, cam, 1.0)
    n = int(r.n_faces)
    refine_s = time.perf_counter() - t
    t = time.perf_counter()
    np.asarray(r.mesh()[1])
    return refine_s, n, time.perf_counter() - t


def alternate(paths: list[str], rounds: int) -> list[dict]:
    """Refine and ``mesh()`` of the models in ``paths`` alternated frame by
    frame in this process: per model the median over rounds of each round's
    median over the 24 frames (milliseconds) of refine, of ``mesh()`` and of
    the two together (a drawable mesh from a camera), and the faces drawn."""
    import pmjax

    models = []
    for path in paths:
        mesh = pmjax.load(path)
        models.append(dict(mesh=mesh, frames=orbit_frames(mesh), refine=[], mesh_ms=[], both=[], faces=[]))
    for _ in range(rounds):
        per = [dict(refine=[], mesh=[], both=[]) for _ in models]
        for i in range(24):
            for m, p in zip(models, per):
                refine_s, n, mesh_s = time_frame(m["mesh"], m["frames"][i])
                p["refine"].append(refine_s)
                p["mesh"].append(mesh_s)
                p["both"].append(refine_s + mesh_s)
                m["faces"].append(n)
        for m, p in zip(models, per):
            m["refine"].append(1e3 * statistics.median(p["refine"]))
            m["mesh_ms"].append(1e3 * statistics.median(p["mesh"]))
            m["both"].append(1e3 * statistics.median(p["both"]))
    return [dict(model=path, refine_ms=statistics.median(m["refine"]), mesh_ms=statistics.median(m["mesh_ms"]),
                 refine_mesh_ms=statistics.median(m["both"]), refine_rounds=m["refine"], mesh_rounds=m["mesh_ms"],
                 faces=int(statistics.median(m["faces"])))
            for path, m in zip(paths, models)]


# The builder's main-thread steps that --stages labels: (module, name, label).
STAGES = (
    ("qd", "vertex_quadrics", "initial quadrics (and, beside them, the attribute start)"),
    ("native", "Scratch", "buffers of the C loops"),
    ("build", "unique_edges", "edges, recounted every batch"),
    ("build", "evaluate_metric", "costs of the first batch"),
    ("build", "_cached_costs", "costs carried, fresh pairs placed"),
    ("build", "_sorted_by_key", "cost cache"),
    ("native", "Mesh", "faces around each vertex"),
    ("build", "_cheapest", "the cheapest share"),
    ("build", "_select_batch", "the batch choice (greedy, validity)"),
    ("native", "apply_batch", "applying the batch"),
    ("build", "fitted_normals", "the shading normals' fit, after the batches"),
)


def stages(spec: str, folder: str) -> dict:
    """Peak RSS and main-thread time per labelled step of one build."""
    import threading

    from pmjax.builders import _build

    v, f = np.load(os.path.join(folder, "v.npy")), np.load(os.path.join(folder, "f.npy"))
    page = os.sysconf("SC_PAGE_SIZE")

    def rss():
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * page

    label, peak, spent, done = ["other"], {}, {}, threading.Event()

    def sample():
        while not done.is_set():
            r, at = rss(), label[0]
            peak[at] = max(peak.get(at, 0), r)
            time.sleep(0.002)

    modules = dict(qd=_build.qd, native=_build.native, build=_build)
    for module, name, text in STAGES:
        def labelled(*args, _fn=getattr(modules[module], name), _text=text, **kwargs):
            before, label[0] = label[0], _text
            t = time.perf_counter()
            try:
                return _fn(*args, **kwargs)
            finally:
                spent[_text] = spent.get(_text, 0.0) + time.perf_counter() - t
                label[0] = before
        setattr(modules[module], name, labelled)
    base = rss()
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t = time.perf_counter()
    _build.build_pm(v, f)
    build_s = time.perf_counter() - t
    done.set()
    sampler.join()
    F = len(f)
    rows = [dict(step=text, peak_bytes_per_face=(peak.get(text, base) - base) / F, main_s=spent.get(text, 0.0))
            for _, _, text in STAGES] + [dict(step="other", peak_bytes_per_face=(peak["other"] - base) / F,
                                              main_s=build_s - sum(spent.values()))]
    return dict(model=spec, faces=F, base_bytes_per_face=base / F, build_s=build_s, stages=rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="dragon:0,dragon:1")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    ap.add_argument("--make", help=argparse.SUPPRESS)
    ap.add_argument("--folder", help=argparse.SUPPRESS)
    ap.add_argument("--json", help="also write the rows as JSON")
    ap.add_argument("--stages", help="one model: peak RSS and main-thread time per step of its build")
    ap.add_argument("--stages-of", help=argparse.SUPPRESS)
    ap.add_argument("--save-built", help=argparse.SUPPRESS)
    ap.add_argument("--alternate", metavar="A,B",
                    help="two models (NAME:LEVELS or .pmz files): refine and mesh() alternated frame by frame in one "
                         "process, B's time over A's")
    ap.add_argument("--keep", default=None,
                    help="with --alternate: folder of the built models' .pmz, made there once (default: "
                         f"{os.path.join(tempfile.gettempdir(), 'pmjax-large')})")
    ap.add_argument("--rounds", type=int, default=None, help="with --alternate: rounds of the 24 frames (default 3)")
    ap.add_argument("--cores", type=int, default=None, help="with --alternate: CPUs to run on (default 1)")
    args = ap.parse_args(argv)
    alternate_only = [f"--{k}" for k in ("keep", "rounds", "cores") if getattr(args, k) is not None]
    if alternate_only and not args.alternate:
        ap.error(f"{', '.join(alternate_only)} only go{'es' if len(alternate_only) == 1 else ''} with --alternate")
    keep = args.keep or os.path.join(tempfile.gettempdir(), "pmjax-large")
    rounds = 3 if args.rounds is None else args.rounds
    cores = 1 if args.cores is None else args.cores
    if args.save_built:
        print(json.dumps(dict(build_s=save_built(args.folder, args.save_built))))
        return 0
    if args.alternate:
        specs = args.alternate.split(",")
        if len(specs) != 2 or rounds < 1:
            ap.error("--alternate takes two models, A,B, and --rounds at least 1")
        # The models are made first: their builds run in subprocesses that
        # would inherit this process's pinning.
        paths = [kept_model(spec, keep) for spec in specs]
        pin_cores(cores)
        print(machine())
        rows = alternate(paths, rounds)
        for spec, row in zip(specs, rows):
            print(f"{spec:12s} {row['faces']:>7,d} faces drawn  refine {row['refine_ms']:.3f} ms  "
                  f"mesh() {row['mesh_ms']:.3f} ms  refine + mesh() {row['refine_mesh_ms']:.3f} ms  (rounds: "
                  + ", ".join(f"{a:.3f}/{b:.3f}" for a, b in zip(row["refine_rounds"], row["mesh_rounds"])) + ")")
        a, b = rows
        print(f"{specs[1]} / {specs[0]}: faces {b['faces'] / a['faces']:.2f}x  refine "
              f"{b['refine_ms'] / a['refine_ms']:.2f}x  mesh() {b['mesh_ms'] / a['mesh_ms']:.2f}x  "
              f"refine + mesh() {b['refine_mesh_ms'] / a['refine_mesh_ms']:.2f}x  "
              f"(medians over {rounds} rounds of 24 frames, alternated in one process)")
        if args.json:
            write_json(args.json, dict(machine=machine(), rows=rows, specs=specs, rounds=rounds))
        return 0
    if args.stages_of:
        print(json.dumps(stages(args.stages_of, args.folder)))
        return 0
    if args.stages:
        print(machine())
        with tempfile.TemporaryDirectory(prefix="pmjax-large-model-") as folder:
            subprocess.run([sys.executable, __file__, "--make", args.stages, "--folder", folder], check=True,
                           capture_output=True)
            out = subprocess.run([sys.executable, __file__, "--stages-of", args.stages, "--folder", folder],
                                 check=True, capture_output=True, text=True)
        row = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{row['model']}: {row['faces']:,d} faces, build {row['build_s']:.1f} s, before the build "
              f"{row['base_bytes_per_face']:.0f} B/face (imports, the model's arrays)")
        for stage in row["stages"]:
            print(f"  {stage['step']:58s} peak {stage['peak_bytes_per_face']:5.0f} B/face above that, "
                  f"main thread {stage['main_s']:6.2f} s")
        if args.json:
            write_json(args.json, dict(machine=machine(), **row))
        return 0
    if args.make:
        print(json.dumps(dict(make_s=save_model(args.make, args.folder))))
        return 0
    if args.one:
        print(json.dumps(one_model(args.one, args.folder)))
        return 0
    print(machine())
    rows = []
    for spec in args.models.split(","):
        with tempfile.TemporaryDirectory(prefix="pmjax-large-model-") as folder:
            made = subprocess.run([sys.executable, __file__, "--make", spec, "--folder", folder], capture_output=True,
                                  text=True)
            if made.returncode:
                print(f"{spec}: making the model failed\n{made.stderr[-2000:]}", file=sys.stderr)
                return 1
            out = subprocess.run([sys.executable, __file__, "--one", spec, "--folder", folder], capture_output=True,
                                 text=True)
        if out.returncode:
            print(f"{spec}: failed\n{out.stderr[-2000:]}", file=sys.stderr)
            return 1
        row = json.loads(out.stdout.strip().splitlines()[-1])
        row["make_s"] = json.loads(made.stdout.strip().splitlines()[-1])["make_s"]
        rows.append(row)
        fs = f"{row['fs_1pct_s']:.1f} s ({row['build_s'] / row['fs_1pct_s']:.2f}x)" if row["fs_1pct_s"] else "-"
        print(f"{spec:12s} {row['faces']:>10,d} faces  build {row['build_s']:.1f} s, fast-simpl. {fs}  "
              f"peak {row['peak_rss_bytes'] / 1e9:.2f} GB ({row['peak_bytes_per_face']:.0f} B/face)  "
              f"pmz v1 {row['v1_bytes'] / 1e6:.1f} MB v2 {row['v2_bytes'] / 1e6:.1f} MB  "
              f"load v1 {row['load_v1_s']:.2f} s v2 {row['load_v2_s']:.2f} s  "
              f"refine {row['refine_ms']:.2f} ms, {row['refine_faces']:,d} faces, mesh() {row['mesh_ms']:.2f} ms",
              flush=True)
    if args.json:
        write_json(args.json, dict(machine=machine(), rows=rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
