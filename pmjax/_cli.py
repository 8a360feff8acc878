"""The ``pmjax`` command line: build, info, lod, camera, refine, path, eval, render, figures, view, demo."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys

import numpy as np

from pmjax._atomic import atomic_path, check_distinct, check_output_path
from pmjax._terminate import sigterm_exits


def _whole(low: int, high: int | None = None, hint: str = ""):
    """argparse type: a whole number in ``[low, high]`` (``hint`` follows a
    value out of range)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(
                f"{value} is out of range (must be >= {low}{'' if high is None else f' and <= {high:,}'}){hint}")
        return value

    return parse


def _real(low: float = 0.0, high: float = math.inf, *, open_low=False, open_high=False, infinite=False):
    """argparse type: a real number in the interval (NaN is always refused;
    ``inf`` only where ``infinite``)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if math.isinf(value) and value > 0 and infinite:
            return value
        ok = (math.isfinite(value) and (value > low if open_low else value >= low)
              and (value < high if open_high else value <= high))
        if not ok and math.isinf(low) and math.isinf(high):
            raise argparse.ArgumentTypeError(f"{text} is not a finite number")
        if not ok:
            where = f"{'(' if open_low else '['}{low:g}, {high:g}{')' if open_high or math.isinf(high) else ']'}"
            raise argparse.ArgumentTypeError(f"{text} is out of range (must be in {where}"
                                             f"{' or inf' if infinite else ''})")
        return value

    return parse


TAU = _real(0.0, infinite=True)
FINITE = _real(-math.inf)  # pixels; inf collapses everything collapsible
COUNT = _whole(1)
# Cameras a command holds at once (about 100 bytes each); evaluation streams
# any number in parts.
MAX_FRAMES = 1_000_000
FRAMES = _whole(1, MAX_FRAMES, "; pmjax eval streams larger camera sets in parts (--orbit N, --random N)")
SIZE = _whole(1, 65536)
# A camera's defaults (vertical field of view in degrees, image size in
# pixels, up direction).
DEFAULT_FOV, DEFAULT_SIZE, DEFAULT_UP = 45.0, (800, 600), (0.0, 1.0, 0.0)


def _write_mesh(path: str, vertices, faces) -> None:
    """Write a mesh atomically in the format of its extension (.ply, .obj,
    .off, .stl, .glb; see :func:`pmjax._meshfiles.write_mesh`), or refuse the
    extension with the formats written."""
    from pmjax._meshfiles import write_mesh

    write_mesh(path, vertices, faces)


def _write_text(path, text):
    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        fh.write(text)


def cmd_build(args) -> int:
    from pmjax import load_clean_mesh, save_pm
    from pmjax.builders import BuildOptions, build_pm, file_sha256

    options = BuildOptions(
        metric=args.metric,
        pair_distance=args.pair_distance,
        target_faces=args.target_faces,
        target_vertices=args.target_vertices,
        max_error=args.max_error,
        batch_share=args.batch_share,
        linear=args.linear,
        allow_topology_change=args.allow_topology_change,
        boundary_weight=args.boundary_weight,
    )
    # A mistyped option is refused before the mesh is read.
    options.validate()
    vertices, faces, _, report = load_clean_mesh(args.mesh)
    for line in report.messages():
        print(f"{args.mesh}: {line}", file=sys.stderr)
    pm = build_pm(vertices, faces, options, progress=not args.quiet, source_sha256=file_sha256(args.mesh))
    pm.header["source"] = os.path.basename(args.mesh)
    save_pm(pm, args.output, version=args.file_version)
    b = pm.header["build"]
    print(
        f"{args.output}: {len(faces)} faces -> base {b['base_faces']} faces, "
        f"{pm.n_pcols} pcols in {pm.n_batches} batches, {b['seconds']:.2f} s"
    )
    return 0


def info_dict(pm, path: str) -> dict:
    """Counts, per-batch face counts, sizes and build parameters of a PM."""
    from pmjax._levels import dependency_levels
    from pmjax._replay import active_faces, prefix_executed

    kills = pm.kills
    per_batch = np.add.reduceat(kills, pm.batch_offsets[:-1]) if pm.n_pcols else np.zeros(0, int)
    faces_after = len(pm.faces) - np.cumsum(per_batch)
    base = int(active_faces(pm, prefix_executed(pm, pm.n_pcols)).sum())
    return dict(
        file=path,
        file_bytes=os.path.getsize(path),
        original_vertices=pm.n_original_vertices,
        original_faces=int(len(pm.faces)),
        pcols=pm.n_pcols,
        batches=pm.n_batches,
        dependency_height=int(dependency_levels(pm).max(initial=0)),
        base_vertices=pm.n_original_vertices - pm.n_pcols,
        base_faces=base,
        batches_detail=[
            dict(batch=b, pcols=int(pm.batch_offsets[b + 1] - pm.batch_offsets[b]), faces_after=int(faces_after[b]))
            for b in range(pm.n_batches)
        ],
        array_bytes={k: int(a.nbytes) for k, a in pm.arrays().items()},
        header={k: v for k, v in pm.header.items() if k not in ("counts",)},
    )


def engine_lines() -> list[str]:
    """What refines here: each engine and where it runs (or why it does not)."""
    from pmjax import engine_info

    return [f"  {name:5s} {text}" for name, text in engine_info().items()]


def compiled_loops() -> dict:
    """Whether each optional ctypes extension is active here (else its NumPy
    steps run: the same results, slower)."""
    from pmjax import _codec, _normals
    from pmjax.builders import _native

    return {"builder": _native.available(), "pmz decoder": _codec.native is not None,
            "shading normals' fit": _normals.native is not None}


def cmd_info(args) -> int:
    from pmjax import engine_info, read_pm

    if args.engines:
        loops = compiled_loops()
        if args.json:
            print(json.dumps(dict(engine_info(), compiled_loops=loops), indent=1))
        else:
            print("engines:")
            print("\n".join(engine_lines()))
            print("compiled loops (else NumPy, the same results):")
            print("\n".join(f"  {name}: {'C' if on else 'NumPy'}" for name, on in loops.items()))
        if args.pm is None:
            return 0
    if args.pm is None:
        raise SystemExit("pmjax info: give a .pmz file (or --engines)")
    pm = read_pm(args.pm)
    info = info_dict(pm, args.pm)
    if args.json:
        print(json.dumps(info, indent=1))
        return 0
    print(f"{args.pm} ({info['file_bytes'] / 1e6:.2f} MB)")
    print(f"  original: {info['original_vertices']} vertices, {info['original_faces']} faces")
    print(f"  base:     {info['base_vertices']} vertices, {info['base_faces']} faces")
    print(f"  pcols:    {info['pcols']} in {info['batches']} batches, dependency height {info['dependency_height']}")
    build = info["header"].get("build", {})
    if build:
        print(f"  build:    metric={build.get('metric')} pair_distance={build.get('pair_distance')} "
              f"batch_share={build.get('batch_share')} ({build.get('seconds')} s)")
    print("  batch   pcols   faces after")
    for row in info["batches_detail"]:
        print(f"  {row['batch']:5d} {row['pcols']:7d} {row['faces_after']:13d}")
    return 0


def cmd_lod(args) -> int:
    from pmjax import read_pm
    from pmjax._replay import lod_mesh

    pm = read_pm(args.pm)
    batch = pm.n_batches - 1 if args.batch is None else args.batch
    vertices, faces, _ = lod_mesh(pm, batch)
    _write_mesh(args.output, vertices, faces)
    print(f"{args.output}: LOD after batch {batch}: {len(vertices)} vertices, {len(faces)} faces")
    return 0


def _stats(r, ms=None) -> dict:
    out = dict(faces=int(r.n_faces), vertices=int(r.n_vertices), executed=int(r.n_executed))
    if ms is not None:
        out["milliseconds"] = round(ms, 4)
    return out


def _tests(args):
    from pmjax import Tests

    off = set(args.no or [])
    return Tests(frustum="frustum" not in off, orientation="orientation" not in off, screen="screen" not in off)


def _look_at(args, **kw):
    """The camera of --eye/--target/--up; flags that make no camera are
    refused naming them."""
    import pmjax

    eye, target, up = (np.asarray(getattr(args, k), float) for k in ("eye", "target", "up"))
    if np.array_equal(eye, target):
        raise ValueError("--eye and --target are the same point: the camera needs a direction to look in")
    if not np.any(up):
        raise ValueError("--up is zero: give the image's up direction (default 0 1 0)")
    return pmjax.look_at(args.eye, args.target, args.up, **kw)


def cmd_refine(args) -> int:
    import time

    import jax

    import pmjax

    if args.camera is None and args.target is None:
        raise ValueError("--eye needs --target")
    # The camera first: a bad one is refused before the model is loaded.
    if args.camera:
        from pmjax._camera_files import load_first_camera

        given = [f"--{k}" for k in ("target", "up", "fov", "size") if getattr(args, k) is not None]
        if given:
            raise ValueError(f"--camera gives the whole camera; {', '.join(given)} only go with --eye")
        cam = load_first_camera(args.camera)
    else:
        args.up = DEFAULT_UP if args.up is None else args.up
        size = DEFAULT_SIZE if args.size is None else args.size
        cam = _look_at(args, width=size[0], height=size[1], fov_y_deg=DEFAULT_FOV if args.fov is None else args.fov)
    pm = pmjax.load(args.pm)
    r = pmjax.refine(pm, cam, args.tau, tests=_tests(args), method=args.method)
    jax.block_until_ready(r)
    t = time.perf_counter()
    r = pmjax.refine(pm, cam, args.tau, tests=_tests(args), method=args.method)
    jax.block_until_ready(r)
    ms = 1e3 * (time.perf_counter() - t)
    v, f, _ = r.mesh(pm)
    _write_mesh(args.output, v, f)
    stats = _stats(r, ms)
    if args.stats_json:
        _write_text(args.stats_json, json.dumps(stats, indent=1))
    print(f"{args.output}: {stats['faces']} faces, {stats['vertices']} vertices ({ms:.2f} ms)")
    return 0


def cmd_path(args) -> int:
    import pmjax
    from pmjax._path import frames_per_word

    pm = pmjax.load(args.pm)
    cams = _path_cameras(pm, args)
    tests = _tests(args)
    K = pmjax._camera.camera_count(cams)
    counts = pmjax.path_counts(pm, cams, args.tau, tests=tests, coherent=not args.per_frame, method=args.method,
                               timing=True, progress=not args.quiet)
    rows = [dict(frame=i, faces=int(counts["faces"][i]), vertices=int(counts["vertices"][i]),
                 executed=int(counts["executed_count"][i]), milliseconds=round(float(counts["milliseconds"][i]), 4))
            for i in range(K)]
    cols = ["frame", "faces", "vertices", "executed", "milliseconds"]
    if args.fidelity:
        from pmjax.render import path_fidelity

        fidelity = path_fidelity(pm, cams, args.tau, tests=tests, geomorph=args.geomorph,
                                 coherent=not args.per_frame, progress=not args.quiet,
                                 normals="stored" if args.stored_normals else "view",
                                 **({} if args.supersample is None else dict(supersample=args.supersample)))
        for row, fid in zip(rows, fidelity):
            row.update({k: round(float(fid[k]), 6) for k in FIDELITY_COLUMNS})
        cols += list(FIDELITY_COLUMNS)
    lines = [",".join(cols)] + [",".join(str(r[c]) for c in cols) for r in rows]
    if args.csv:
        _write_text(args.csv, "\n".join(lines) + "\n")
    faces = np.array([r["faces"] for r in rows])
    ms = np.array([r["milliseconds"] for r in rows])
    how = "each frame alone" if args.per_frame else f"{frames_per_word()} consecutive frames at a time"
    print(f"{K} frames at tau={args.tau}: faces median {int(np.median(faces))} "
          f"(min {faces.min()}, max {faces.max()}), median {np.median(ms):.3f} ms/frame ({how})")
    if args.fidelity:
        share = np.array([r["differing_share"] for r in rows])
        pop = np.array([r["popping_share"] for r in rows[1:]]) if K > 1 else np.zeros(1)
        silhouette = np.array([r["silhouette_share"] for r in rows])
        flip = np.array([r["flip_model_mean"] for r in rows])
        cost = np.array([r["fidelity_ms"] for r in rows])
        print(f"fidelity: median {np.median(share):.3%} of the model's pixels differ from the original "
              f"(max {share.max():.3%}; {np.median(silhouette):.3%} by geometry alone, drawn unlit); "
              f"FLIP over the model's pixels median {np.median(flip):.4f}; "
              f"popping median {np.median(pop):.3%} per frame; measuring cost median {np.median(cost):.0f} ms/frame")
    return 0


FIDELITY_COLUMNS = ("differing_share", "psnr", "silhouette_share", "popping_share", "popping_mse",
                    "flip_mean", "flip_model_mean", "render_ms", "fidelity_ms")


def cmd_eval(args) -> int:
    from pmjax._eval import DEFAULT_COMPILE_CACHE, EvalError, EvalInterrupted, camera_set, compact, evaluate

    if args.compact is not None:
        done = compact(args.compact)
        print(f"{done.folder}: {done.rows} rows in {done.parts} parts; {done.files_before} files compacted into "
              f"{done.files_after} ({done.seconds:.1f} s)")
        return 0
    image = dict(width=args.size[0], height=args.size[1], fov_y_deg=args.fov)
    sets = [camera_set(spec, **image) for spec in args.cameras or []]
    sets += [camera_set(f"orbit:{n}", **image) for n in args.orbit or []]
    sets += [camera_set(f"fly:{n}", **image) for n in args.fly or []]
    sets += [camera_set(f"random:{n}:{args.seed}", **image) for n in args.random or []]
    if not sets:
        sets = [camera_set("orbit:240", **image)]
    taus = args.tau or ([] if args.budget else [1.0])
    cluster, scheduler = None, args.scheduler
    if args.slurm is not None:
        if args.scheduler or args.workers:
            raise EvalError("--slurm starts its own cluster: give it without --scheduler and --workers")
        from pmjax._cluster import slurm_cluster

        try:
            cluster = slurm_cluster(args.slurm, cores=args.slurm_cores, memory=args.slurm_memory,
                                    walltime=args.slurm_walltime, queue=args.slurm_queue, account=args.slurm_account)
        except (RuntimeError, ValueError) as exc:
            raise EvalError(f"--slurm: {exc}") from None
        scheduler = cluster.scheduler_address
    try:
        summary = evaluate(args.models, sets, args.output, taus=taus, budgets=args.budget or [], tests=_tests(args),
                           method=args.method, chunk=args.chunk,
                           compile_cache=None if args.no_compile_cache else (args.compile_cache
                                                                             or DEFAULT_COMPILE_CACHE),
                           scheduler=scheduler, workers=args.workers, progress=not args.quiet,
                           camera_columns=args.camera_columns, fidelity=args.fidelity)
    except EvalInterrupted as exc:  # Ctrl-C: one line, the parts kept and how to resume
        print(f"pmjax eval: {exc}", file=sys.stderr)
        return 130
    finally:
        if cluster is not None:  # its batch jobs are cancelled
            cluster.close()
    print(f"{summary.folder}: {summary.rows} rows; {summary.parts_written} parts written now "
          f"({summary.cameras} cameras, {summary.cameras_per_s:.0f} cameras/s over {summary.seconds:.1f} s), "
          f"{summary.parts_skipped} parts found done")
    return 0


def _model_vertices(path: str) -> np.ndarray:
    """The original vertices of a ``.pmz``, or of a mesh file once cleaned
    (the vertices a hierarchy built from it would have: float32, as stored)."""
    import pmjax

    if path.endswith(".pmz"):
        pm = pmjax.read_pm(path)
        return pm.vertices[: pm.n_original_vertices]
    return pmjax.load_clean_mesh(path)[0].astype(np.float32)


def cmd_camera(args) -> int:
    import pmjax
    from pmjax._camera_table import camera_file_kind, fly_rows, orbit_rows, random_rows, table_from_cameras

    image = dict(width=args.size[0], height=args.size[1], fov_y_deg=args.fov)
    if args.kind == "look-at":
        near_far = {k: getattr(args, k) for k in ("near", "far") if getattr(args, k) is not None}
        table = table_from_cameras(_look_at(args, **image, **near_far, host=True))
    else:
        v = _model_vertices(args.model)
        if args.kind == "orbit":
            table = orbit_rows(v, args.n, 0, args.n, elevation_deg=args.elevation, **image)
        elif args.kind == "fly":
            table = fly_rows(v, args.n, 0, args.n, **image)
        else:
            table = random_rows(v, args.seed, 0, args.n, **image)
    if camera_file_kind(args.output) in ("npz", "parquet"):
        pmjax.write_camera_table(table, args.output)
    else:
        pmjax.save_cameras(table.camera(np.float64), args.output)
    n = len(table)
    print(f"{args.output}: {n} camera{'s' if n != 1 else ''} ({args.kind})")
    return 0


def _path_cameras(pm, args):
    import pmjax

    if getattr(args, "path", None):
        return pmjax.load_cameras(args.path)
    return pmjax.standard_orbit(pm.vertices[: pm.n_original_vertices], args.orbit)


def cmd_render(args) -> int:
    import pmjax
    from pmjax.render import overview_camera, render_path

    pm = pmjax.load(args.pm)
    cams = _path_cameras(pm, args)
    view = None
    if args.phantom:
        view = overview_camera(np.asarray(pm.vertices)[: pm.n_original_vertices], pmjax.index_camera(cams, 0))
    out = render_path(pm, cams, args.tau, args.output, tests=_tests(args), wireframe=args.wireframe,
                      color_levels=args.levels, phantom=view, geomorph=args.geomorph, fps=args.fps,
                      coherent=not args.per_frame, progress=not args.quiet,
                      normals="stored" if args.stored_normals else "view")
    print(f"{args.output}: {out['frames']} frames, faces median {int(np.median(out['faces']))}")
    return 0


def cmd_figures(args) -> int:
    import pmjax
    from pmjax.render import paper_figures

    out = paper_figures(pmjax.load(args.pm), args.output, normals="stored" if args.stored_normals else "view")
    for name, (path, faces) in out.items():
        print(f"{path}: {faces} faces")
    return 0


def cmd_view(args) -> int:
    from pmjax.render import run_viewer

    run_viewer(args.pm, tau=args.tau, size=tuple(args.size), close_after=args.close_after,
               camera_file=args.camera_file)
    return 0


def cmd_demo(args) -> int:
    """Build the bundled model, refine it along the standard orbit, export results."""
    import pmjax
    from pmjax.builders import build_pm, file_sha256

    os.makedirs(args.out, exist_ok=True)  # its parent exists (checked)
    src = args.mesh or pmjax.default_model_path()
    v, f, _, report = pmjax.load_clean_mesh(src)
    print(f"model: {src} ({len(v)} vertices, {len(f)} faces)")
    data = build_pm(v, f, progress=True, source_sha256=file_sha256(src))
    data.header["source"] = os.path.basename(src)
    pmz = os.path.join(args.out, "model.pmz")
    pmjax.save_pm(data, pmz)
    print(f"built {pmz}: {data.n_pcols} pcols in {data.n_batches} batches "
          f"({data.header['build']['seconds']} s), base mesh {data.header['build']['base_faces']} faces")
    pm = pmjax.load(pmz)
    cams = pmjax.standard_orbit(v, 240)
    out = pmjax.refine_batch(pm, cams, 1.0, progress=True)
    print(f"standard orbit, 240 frames, tau = 1 px: faces median {int(np.median(out['faces']))} "
          f"({np.median(out['faces']) / len(f):.1%} of the original)")
    cam = pmjax._camera.index_camera(cams, 0)
    for tau in (0.5, 1.0, 4.0):
        r = pmjax.refine(pm, cam, tau)
        path = os.path.join(args.out, f"refined_tau{tau:g}.ply")
        _write_mesh(path, *r.mesh(pm)[:2])
        print(f"{path}: frame 0 refined at tau = {tau:g} px: {int(r.n_faces)} faces")
    pmjax.save_cameras(cam, os.path.join(args.out, "camera0.json"))
    from pmjax.render import RenderError, paper_figures, render_path

    try:
        gif = os.path.join(args.out, "orbit.gif")
        render_path(pm, pmjax.standard_orbit(v, 48, width=400, height=300), 1.0, gif, wireframe=True)
        print(f"{gif}: 48-frame orbit at tau = 1 px (wireframe)")
        for name, (path, faces) in paper_figures(pm, os.path.join(args.out, "figures")).items():
            print(f"{path}: {faces} faces")
    except RenderError as exc:  # no OpenGL here: the meshes above are still written
        print(f"rendering skipped: {exc}")
    return 0


class _Version(argparse.Action):
    """``--version``: pmjax's version and its engines (computed when asked:
    it loads JAX and the core)."""

    def __call__(self, parser, namespace, values, option_string=None):
        from pmjax import __version__

        print(f"pmjax {__version__}\nengines:\n" + "\n".join(engine_lines()))
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pmjax",
        description="View-dependent refinement of progressive meshes (JAX).",
    )
    parser.add_argument("--version", action=_Version, nargs=0, help="the version and the engines active here")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("build", help="build a progressive mesh (.pmz) from a mesh file",
                       description="Batched pair-contraction simplification into a .pmz progressive mesh.")
    p.add_argument("mesh", help="input mesh (.ply, .obj, .off, .stl, .glb, or another format trimesh reads)")
    p.add_argument("-o", "--output", required=True, help="output .pmz path")
    p.add_argument("--metric", default="quadric",
                   help="metric or schedule, e.g. 'quadric' or 'edge:2,quadric' "
                        "(quadric, quadric-memoryless, edge, pm, hybrid)")
    p.add_argument("--pair-distance", type=_real(0.0, 1.0), default=0.0,
                   help="also pair vertices closer than t × bbox diagonal (0: edges only)")
    p.add_argument("--target-faces", type=_whole(0), default=0, help="stop at this many faces (0: as far as possible)")
    p.add_argument("--target-vertices", type=_whole(0), default=0, help="stop at this many vertices")
    p.add_argument("--max-error", type=_real(0.0, infinite=True), default=math.inf, help="never take a collapse costing more")
    p.add_argument("--batch-share", type=_real(0.0, 1.0, open_low=True), default=0.5,
                   help="share of the cheapest candidates a batch may take from (quality knob, (0, 1])")
    p.add_argument("--linear", action="store_true", help="one collapse per batch, strict cost order (slow reference)")
    p.add_argument("--allow-topology-change", action="store_true", help="skip the link test for edges")
    p.add_argument("--boundary-weight", type=_real(0.0), default=1.0, help="weight of border-preserving planes")
    p.add_argument("--file-version", type=int, choices=(1, 2), default=2,
                   help="2: compressed, coarse to fine, readable a prefix at a time (default); "
                        "1: uncompressed zip, 2-3x larger, faster to read again once its content is known")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("info", help="describe a .pmz file, or the engines active here",
                       description="Counts, batches, sizes and build parameters; with --engines, which refinement "
                                   "engines are active (the front engine's C core, or why not).")
    p.add_argument("pm", nargs="?", help=".pmz file")
    p.add_argument("--engines", action="store_true", help="which refinement engines are active here")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("lod", help="export the discrete LOD after a batch",
                       description="Replay pcols of batches 0..k and write the mesh.")
    p.add_argument("pm", help=".pmz file")
    p.add_argument("--batch", type=_whole(-1), default=None, help="last batch to execute (-1: original; default: all)")
    p.add_argument("-o", "--output", required=True, help="output mesh (.ply, .obj, .off, .stl or .glb)")
    p.set_defaults(func=cmd_lod)

    def add_path_args(p):
        # read by _path_cameras
        g = p.add_mutually_exclusive_group(required=True)
        g.add_argument("--orbit", type=FRAMES, help="the standard orbit with N frames (round the bounding-box centre "
                       "at r / sin 22.5°, r the half diagonal, 20° elevation)")
        g.add_argument("--path", help="camera file (.json, .csv, .npz or .parquet)")

    def add_per_frame_arg(p):
        p.add_argument("--per-frame", action="store_true",
                       help="refine each frame alone (same results) instead of consecutive frames together "
                            "(docs/path.md)")

    def add_geomorph_arg(p):
        p.add_argument("--geomorph", type=_whole(0), default=0, metavar="N",
                       help="blend refinement changes over N frames instead of popping (default 0: off)")

    def add_normals_arg(p, what):
        p.add_argument("--stored-normals", action="store_true",
                       help=f"shade {what} with the normals stored in the file instead of normals fitted "
                            "on each mesh drawn, seen from its camera (docs/render.md)")

    def add_view_args(p):
        p.add_argument("--tau", type=TAU, default=1.0, help="screen-space tolerance in pixels (default 1)")
        p.add_argument("--no", action="append", choices=("frustum", "orientation", "screen"),
                       help="switch a test off (repeatable)")

    def add_method_arg(p, note=""):
        p.add_argument("--method", choices=("auto", "front", "dense"), default="auto",
                       help=f"refinement engine{note}, same results: front (output-sensitive), dense (every pcol), "
                            "auto (front where it is faster; docs/front.md)")

    def add_image_args(p, note="", defaults=True):
        # defaults=False: unset flags stay None, so that a command can tell
        # them from given ones (and fill in the defaults itself).
        p.add_argument("--fov", type=_real(0.0, 180.0, open_low=True, open_high=True),
                       default=DEFAULT_FOV if defaults else None,
                       help=f"vertical field of view, degrees{note} (default 45)")
        p.add_argument("--size", type=SIZE, nargs=2, default=DEFAULT_SIZE if defaults else None, metavar=("W", "H"),
                       help=f"image size in pixels{note} (default 800 600)")

    def add_look_at_args(p, required):
        p.add_argument("--eye", type=FINITE, nargs=3, metavar=("X", "Y", "Z"), required=required,
                       help="camera position (model units)")
        p.add_argument("--target", type=FINITE, nargs=3, metavar=("X", "Y", "Z"), required=required,
                       help="the point looked at")
        p.add_argument("--up", type=FINITE, nargs=3, metavar=("X", "Y", "Z"), default=DEFAULT_UP,
                       help="up direction (default 0 1 0)")

    p = sub.add_parser("refine", help="refine for one camera and write the mesh",
                       description="View-dependent refinement for one camera: the first of a camera file, "
                                   "or --eye/--target.")
    p.add_argument("pm", help=".pmz file")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--camera", help="camera file (.json, .csv, .npz or .parquet, see docs/cameras.md; the first camera is used; `pmjax camera` writes one)")
    g.add_argument("--eye", type=FINITE, nargs=3, metavar=("X", "Y", "Z"),
                   help="camera position, with --target (model units)")
    p.add_argument("--target", type=FINITE, nargs=3, metavar=("X", "Y", "Z"), help="the point looked at, with --eye")
    p.add_argument("--up", type=FINITE, nargs=3, metavar=("X", "Y", "Z"),
                   help="up direction with --eye (default 0 1 0)")
    add_image_args(p, note=" with --eye", defaults=False)
    p.add_argument("-o", "--output", required=True, help="output mesh (.ply, .obj, .off, .stl or .glb)")
    p.add_argument("--stats-json", help="write counts and timing as JSON")
    add_view_args(p)
    add_method_arg(p)
    p.set_defaults(func=cmd_refine)

    p = sub.add_parser("camera", help="write cameras: one look-at view, the standard orbit, a fly-through, "
                                      "random views",
                       description="Write cameras to .json or .csv (read by --camera and --path) or to a .npz "
                                   "or .parquet table (read by pmjax eval --cameras). The orbit, fly-through and "
                                   "random views are placed round a model: a mesh file or a .pmz.")
    kinds = p.add_subparsers(dest="kind", required=True)
    k = kinds.add_parser("look-at", help="one camera at --eye looking at --target")
    add_look_at_args(k, required=True)
    k.add_argument("--near", type=_real(0.0, open_low=True), help="near plane distance (default: from the eye)")
    k.add_argument("--far", type=_real(0.0, open_low=True), help="far plane distance")
    for name, text in (("orbit", "the standard orbit: round the bounding-box centre at r / sin 22.5°, r the "
                                 "half diagonal"),
                       ("fly", "a fly-through from far in front, close past the side and round the back"),
                       ("random", "random views round the model (directions uniform, distances log-uniform)")):
        k = kinds.add_parser(name, help=text, description=text)
        k.add_argument("model", help="mesh file or .pmz the cameras are placed round")
        k.add_argument("-n", type=FRAMES, default=240, help="number of cameras (default 240)")
        if name == "orbit":
            k.add_argument("--elevation", type=_real(-90.0, 90.0), default=20.0, help="degrees (default 20)")
        if name == "random":
            k.add_argument("--seed", type=_whole(0), default=0, help="seed (default 0)")
    for k in kinds.choices.values():
        add_image_args(k)
        k.add_argument("-o", "--output", required=True, help="output .json, .csv, .npz or .parquet")
        k.set_defaults(func=cmd_camera)

    p = sub.add_parser("path", help="refine along a camera path, one CSV row per camera",
                       description="Per-camera faces, vertices, executed pcols and milliseconds.")
    p.add_argument("pm", help=".pmz file")
    add_path_args(p)
    p.add_argument("--csv", help="output CSV")
    p.add_argument("--fidelity", action="store_true",
                   help="also render each frame and the original: differing-pixel share, PSNR, "
                        "the share due to geometry alone (silhouette), popping, NVIDIA's FLIP over the image "
                        "and over the model's pixels (needs flip-evaluator), and the measuring cost per frame")
    p.add_argument("--supersample", type=_whole(1, 16), default=None, metavar="S",
                   help="fidelity renders: S×S samples per pixel (default 2; popping wants 4, docs/soft.md)")
    add_normals_arg(p, "the fidelity renders' refinements")
    add_geomorph_arg(p)
    add_per_frame_arg(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_view_args(p)
    add_method_arg(p, note=" of --per-frame")
    p.set_defaults(func=cmd_path)

    p = sub.add_parser("eval", help="evaluate models x camera sets x tolerances into a Parquet dataset",
                       description="One row per (model, camera set, tau or budget, camera): faces, vertices, "
                                   "executed pcols, refine time. Parts are written atomically into the output "
                                   "folder as the work goes; re-running the same command resumes. "
                                   "Columns and camera files: docs/eval.md.")
    p.add_argument("models", nargs="*", help=".pmz files")
    p.add_argument("-o", "--output", help="dataset folder (Parquet part files and _job.parquet; required but with "
                                         "--compact)")
    p.add_argument("--compact", metavar="FOLDER",
                   help="rewrite the part files of the dataset FOLDER into few large files (same rows, still "
                        "resumable), instead of running a job")
    p.add_argument("--cameras", action="append", metavar="FILE",
                   help="camera table, .npz or .parquet (repeatable; schema in docs/eval.md)")
    p.add_argument("--orbit", type=COUNT, action="append", metavar="N",
                   help="the standard orbit with N frames round each model (repeatable; the default is 240)")
    p.add_argument("--fly", type=COUNT, action="append", metavar="N",
                   help="a fly-through of N frames past each model (repeatable)")
    p.add_argument("--random", type=COUNT, action="append", metavar="N", help="N random views of each model (repeatable)")
    p.add_argument("--seed", type=_whole(0), default=0, help="seed of the random views (default 0)")
    p.add_argument("--size", type=SIZE, nargs=2, default=DEFAULT_SIZE, metavar=("W", "H"),
                   help="image size of generated cameras (default 800 600)")
    p.add_argument("--fov", type=_real(0.0, 180.0, open_low=True, open_high=True), default=DEFAULT_FOV,
                   help="vertical field of view of generated cameras, degrees")
    p.add_argument("--tau", type=TAU, action="append", help="tolerance in pixels (repeatable; default 1)")
    p.add_argument("--budget", type=_whole(0), action="append",
                   help="face budget instead of tau (repeatable): the tolerance found is in the tau column")
    p.add_argument("--no", action="append", choices=("frustum", "orientation", "screen"),
                   help="switch a test off (repeatable)")
    add_method_arg(p)
    p.add_argument("--chunk", type=COUNT, default=2048, help="cameras per part file and per task (default 2048)")
    p.add_argument("--camera-columns", action="store_true",
                   help="also write each camera's eye, distance to the model (model units and bounding radii), "
                        "field of view and image size (part of the job: resume with the same setting)")
    p.add_argument("--fidelity", action="store_true",
                   help="also render each camera's refinement and the original (headless, EGL or OSMesa): "
                        "differing-pixel share, PSNR, the share due to geometry alone (silhouette), NVIDIA's FLIP "
                        "over the image and over the model's pixels, render and measuring times (part of the job: "
                        "resume with the same setting; docs/eval.md gives the cost per camera)")
    p.add_argument("--workers", type=_whole(0), default=0,
                   help="run on a local Dask cluster of N threads in this process (default 0: no cluster)")
    p.add_argument("--scheduler", help="run on a Dask cluster: scheduler address, tcp://HOST:PORT")
    p.add_argument("--slurm", type=_whole(1), metavar="JOBS",
                   help="run on a Dask cluster of JOBS SLURM batch jobs, one worker process each (needs "
                        "dask-jobqueue: pip install 'pmjax[cluster]'); each job's cores, memory, time, partition "
                        "and account from the --slurm-* options or dask's jobqueue.slurm configuration")
    p.add_argument("--slurm-cores", type=COUNT, metavar="N", help="cores per SLURM job (the worker's threads)")
    p.add_argument("--slurm-memory", metavar="SIZE", help="memory per SLURM job, e.g. 16GB")
    p.add_argument("--slurm-walltime", metavar="HH:MM:SS", help="time limit per SLURM job")
    p.add_argument("--slurm-queue", metavar="PARTITION", help="SLURM partition")
    p.add_argument("--slurm-account", metavar="ACCOUNT", help="SLURM account")
    p.add_argument("--compile-cache", metavar="DIR",
                   help="JAX's persistent compilation cache (default ~/.cache/pmjax/xla)")
    p.add_argument("--no-compile-cache", action="store_true", help="do not use the persistent compilation cache")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("render", help="render a camera path to .mp4, .gif or PNG frames (headless)",
                       description="Refine and render every camera of a path offscreen (EGL or OSMesa).")
    p.add_argument("pm", help=".pmz file")
    add_path_args(p)
    p.add_argument("-o", "--output", required=True, help="output .mp4, .gif, or a folder for PNG frames")
    p.add_argument("--wireframe", action="store_true", help="overlay the edges")
    p.add_argument("--levels", action="store_true", help="colour faces by batch level (blue fine, red coarse)")
    p.add_argument("--phantom", action="store_true",
                   help="watch from a fixed overview camera, with each path camera's frustum drawn")
    p.add_argument("--fps", type=_whole(1, 1000), default=30, help="frames per second of the video")
    add_normals_arg(p, "refinements")
    add_geomorph_arg(p)
    add_per_frame_arg(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_view_args(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("figures", help="the paper's figures as PNGs",
                       description="Frustum, orientation and screen-space effects and the phantom camera.")
    p.add_argument("pm", help=".pmz file")
    p.add_argument("-o", "--output", required=True, help="output folder")
    add_normals_arg(p, "refinements")
    p.set_defaults(func=cmd_figures)

    p = sub.add_parser("view", help="interactive viewer (needs a display)",
                       description="pyrender Viewer, re-refined as the camera moves. Keys: '=' / '-' raise / "
                                   "lower tau, 'p' freeze or release a phantom camera, '1' '2' '3' toggle the "
                                   "frustum / orientation / screen test, 'e' wireframe overlay, 'c' save the "
                                   "camera (--camera-file), 'q' quit.")
    p.add_argument("pm", help=".pmz file")
    p.add_argument("--tau", type=TAU, default=1.0, help="initial tolerance in pixels")
    p.add_argument("--size", type=SIZE, nargs=2, default=(800, 600), metavar=("W", "H"), help="window size")
    p.add_argument("--close-after", type=_real(0.0), default=0.0, help="close after this many seconds (0: never)")
    p.add_argument("--camera-file", default="view-camera.json",
                   help="where the 'c' key saves the current camera (default ./view-camera.json)")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("demo", help="build the bundled model and refine it along the standard orbit",
                       description="The main job on the bundled model (Spot, public domain) or --mesh.")
    p.add_argument("--mesh", help="use this mesh instead of the bundled one")
    p.add_argument("--out", default="pmjax-demo", help="output folder (default ./pmjax-demo)")
    p.set_defaults(func=cmd_demo)
    return parser


# Each command's outputs: (argument, is a folder). Checked before any work.
OUTPUTS = {
    "build": [("output", False)],
    "lod": [("output", False)],
    "refine": [("output", False), ("stats_json", False)],
    "camera": [("output", False)],
    "view": [("camera_file", False)],
    "path": [("csv", False)],
    "eval": [("output", True)],
    "figures": [("output", True)],
    "demo": [("out", True)],
}


# Each command's input files: (argument, what the message calls it). An
# output that is one of them, or another output, is refused before any work.
INPUTS = {
    "build": [("mesh", "input mesh")],
    "lod": [("pm", "input")],
    "refine": [("pm", "input"), ("camera", "--camera file")],
    "camera": [("model", "input")],
    "view": [("pm", "input")],
    "path": [("pm", "input"), ("path", "--path file")],
    "eval": [("models", "input"), ("cameras", "--cameras file")],
    "render": [("pm", "input"), ("path", "--path file")],
    "figures": [("pm", "input")],
}

# How messages name each output argument.
FLAGS = {"output": "-o", "stats_json": "--stats-json", "csv": "--csv", "camera_file": "--camera-file", "out": "--out"}


def _given(args, name):
    value = getattr(args, name, None)
    return [] if value is None else value if isinstance(value, list) else [value]


def check_outputs(args) -> None:
    """Refuse unusable output paths before any work (one rule for every
    command: see :func:`pmjax._atomic.check_output_path`), and outputs that
    would overwrite an input or each other (:func:`pmjax._atomic.check_distinct`)."""
    inputs = [(what, path) for name, what in INPUTS.get(args.command, []) for path in _given(args, name)]
    outputs = [(FLAGS[name], path) for name, _ in OUTPUTS.get(args.command, []) for path in _given(args, name)]
    if args.command == "render":
        outputs.append(("-o", args.output))
    check_distinct(inputs, outputs)
    if args.command == "render":
        from pmjax.render import check_frames_output

        check_frames_output(args.output, args.fps)
    for name, folder in OUTPUTS.get(args.command, []):
        path = getattr(args, name, None)
        if path is not None:
            check_output_path(path, folder=folder)
    if args.command == "camera":  # a camera file format, before any model is read
        from pmjax._camera_table import check_camera_output

        check_camera_output(args.output)
    if args.command in ("lod", "refine"):  # a mesh format pmjax writes, before any work
        from pmjax._meshfiles import check_mesh_output

        check_mesh_output(args.output)


def _parse(parser: argparse.ArgumentParser, argv):
    """Parse; an unknown flag is reported with its subcommand's usage and the
    closest known flag."""
    import difflib

    args, extra = parser.parse_known_args(argv)
    if extra:
        # The innermost subcommand named (``camera orbit`` is two levels).
        sub = parser
        while sub._subparsers is not None:
            group = sub._subparsers._group_actions[0]
            sub = group.choices[getattr(args, group.dest)]
        known = [o for a in sub._actions for o in a.option_strings]
        hints = [m for x in extra for m in difflib.get_close_matches(x.split("=")[0], known, n=1)]
        sub.error(f"unrecognized arguments: {' '.join(extra)}"
                  + (f" (did you mean {', '.join(hints)}?)" if hints else ""))
    if getattr(args, "command", None) == "path" and not args.fidelity:
        # These shape the fidelity renders only: without them they would be ignored.
        given = [flag for flag, on in (("--stored-normals", args.stored_normals), ("--geomorph", args.geomorph),
                                       ("--supersample", args.supersample is not None)) if on]
        if given:
            sub = parser._subparsers._group_actions[0].choices["path"]
            sub.error(f"{', '.join(given)} shape{'s' if len(given) == 1 else ''} the --fidelity renders: "
                      "add --fidelity, or leave it out")
    if getattr(args, "command", None) == "eval":
        # A job (models and -o) or a compaction (--compact FOLDER), not both.
        sub = parser._subparsers._group_actions[0].choices["eval"]
        if args.compact is not None and (args.models or args.output):
            sub.error("--compact takes the dataset folder alone: give no models and no -o")
        if args.compact is None and not (args.models and args.output):
            sub.error("give the models (.pmz files) and -o FOLDER, or --compact FOLDER")
    return args


def main(argv=None) -> int:
    # File names need not be valid text: one that is not (bytes undecodable
    # in the locale's encoding) is printed escaped rather than ending the
    # command with an encoding error.
    for stream in (sys.stdout, sys.stderr):
        if getattr(stream, "errors", None) == "strict" and hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")
    # Help and argument errors come from the parser alone, before JAX or the
    # engines are imported (the errors below import them).
    parser = build_parser()
    args = _parse(parser, argv)
    from pmjax import CameraError, MeshError, PMFormatError
    from pmjax.render import RenderError

    try:
        # Not the viewer: its window thread would keep the process alive past
        # an exit raised at the wrong moment; SIGTERM stays a plain kill there.
        with sigterm_exits() if args.command != "view" else contextlib.nullcontext():
            check_outputs(args)
            return args.func(args)
    except (MeshError, PMFormatError, CameraError, ValueError, OSError, RenderError) as exc:
        if isinstance(exc, BrokenPipeError):
            return _closed_pipe()
        print(f"pmjax {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: temporaries are gone (the writers' finally), no traceback
        print(f"pmjax {args.command}: interrupted", file=sys.stderr)
        return 130


def _closed_pipe() -> int:
    """The reader of our output went away (``pmjax info x | head``): stop
    quietly, as a shell tool would, with the SIGPIPE status."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    return 141


if __name__ == "__main__":
    sys.exit(main())
