"""Image-space fidelity benchmark: refined vs original renders along the standard orbit.

Usage: python benchmarks/render.py [--models bunny,dragon] [--frames 240] [--taus 0.5,1,2,4]
       [--figures docs/figures] [--parts orbit,frontier,normals,cost,fit] [--supersample 2] [--plot PNG] [--json OUT]

orbit: per model and tau, the median share of the model's pixels that differ
from the original mesh's render (a pixel differs when a channel differs by >
8/255), median PSNR over the model's pixels, the median share that differs
when both are drawn unlit (geometry alone: about the part no shading could remove),
median popping share (pixels changed at a frame only because the refinement
changed), median faces and render ms.

frontier: differing pixels against faces drawn, for pmjax's view-dependent
refinement at several tau and for a view-independent quadric simplifier
(fast-simplification, the ``bench`` extra) at several face shares (or, with
``--quadric-shares match``, at pmjax's median face count of each tau), on the same
frames: where each reaches a given fidelity, and how many faces it needs; with
the unlit (geometry-only) share for each row and mean FLIP over the model's pixels.

normals: the shading normals compared on the same refinements and frames (one
refinement and one original render per frame): the subtree means
(``pmjax.hierarchy_normals``), the fitted ones (``pmjax.fitted_normals``,
stored in the file) and those fitted again per view on the mesh drawn
(``pmjax.ViewNormals``, samples weighted by the area seen; what the renderer
draws): differing share,
silhouette share and mean FLIP over the model's pixels, medians and means over
the frames, at one tau.

cost: what ``path_fidelity`` (``pmjax path --fidelity``) spends per frame,
``fidelity_ms`` (every render and metric of a frame), without and with FLIP,
the two alternated over repeats on the same frames: medians over the frames,
then over the repeats, and their ratio.

fit: what ``pmjax.fitted_normals`` costs, its C loops (two threads) against the
NumPy steps (one thread, the same bits), alternated in one process on the
loaded hierarchy (``--fit-repeats`` each): medians and their ratio; and what
``pmjax.ViewNormals`` costs per drawn mesh (8 orbit frames at tau 1), C loops
(wall and CPU time) against NumPy, alternated per frame.
"""

from __future__ import annotations

import argparse
import statistics
import time
import sys

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import machine, write_json  # noqa: E402
from refine import pm_file  # noqa: E402

import pmjax  # noqa: E402
from pmjax._camera import index_camera  # noqa: E402
from pmjax.render import Renderer, image_difference, original_arrays, paper_figures, path_fidelity  # noqa: E402
from pmjax.render import flip_difference, refined_arrays, silhouette_difference, vertex_normals  # noqa: E402

PARTS = ("orbit", "frontier", "normals", "cost", "fit")


def per_model(counts: str, names: list) -> list:
    """``'240,48'`` -> one int per model, the last repeated for the rest."""
    values = [int(x) for x in counts.split(",")]
    return values + [values[-1]] * (len(names) - len(values))


def frontier(name, frames, taus, shares, supersample=2):
    """Fidelity against faces drawn, on ``frames`` frames of the standard orbit:
    pmjax refined per frame at each tau, and one view-independent quadric
    simplification (fast-simplification, shaded with its own area-weighted
    vertex normals) per face share. Medians over the frames."""
    data = pmjax.read_pm(pm_file(name))  # read and checked once
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], frames)
    ov, of, on = original_arrays(pm)
    F = len(of)
    rows = []
    views = [index_camera(cams, i) for i in range(frames)]
    # As path_fidelity measures: supersampled, unrounded colour.
    with Renderer(views[0].width, views[0].height, supersample=supersample, float_color=True) as r:
        originals = [r.render_mesh(ov, of, cam, normals=on) for cam in views]
        # The original drawn unlit, once per frame for every row (silhouette_difference's reference).
        flat_originals = [r.render_mesh(ov, of, cam, light=False) for cam in views]

        def row(method, setting, faces, meshes):
            # meshes: one (vertices, faces, vertex normals) per frame.
            share, flip = [], []
            for orig, cam, (v, f, n) in zip(originals, views, meshes):
                image = r.render_mesh(v, f, cam, normals=n)
                share.append(image_difference(*orig, *image)["differing_share"])
                flip.append(flip_difference(*orig, *image)["flip_model_mean"])
            # About the part no shading could remove: flat renders, geometry only,
            # as silhouette_difference compares them.
            flat = [image_difference(*orig, *r.render_mesh(v, f, cam, light=False))["differing_share"]
                    for orig, cam, (v, f, _) in zip(flat_originals, views, meshes)]
            out = dict(model=name, frames=frames, method=method, setting=setting, F=F, faces=statistics.median(faces),
                       face_share=statistics.median(faces) / F, differing_share=statistics.median(share),
                       max_differing_share=max(share), silhouette_share=statistics.median(flat),
                       flip_model_mean=statistics.median(flip))
            print(f"{name:8s} {method:9s} {setting:>11s}: faces {out['faces']:8.0f} ({out['face_share']:6.2%}) | "
                  f"differing {out['differing_share']:7.3%} (max {out['max_differing_share']:7.3%}) | "
                  f"silhouette {out['silhouette_share']:7.3%} | FLIP {out['flip_model_mean']:.4f}", flush=True)
            rows.append(out)

        for tau in taus:
            refined = [refined_arrays(pm, pmjax.refine(pm, cam, tau)) for cam in views]
            row("pmjax", f"tau {tau:g}", [len(f) for _, f, _, _ in refined],
                [(v, f, n) for v, f, _, n in refined])
        if shares is None:  # the quadric at pmjax's face counts, row by row
            shares = [out["face_share"] for out in rows if out["method"] == "pmjax"]
        try:
            import fast_simplification
        except ImportError:
            print("  (fast-simplification not installed: pip install -e '.[bench]' for the quadric rows)")
            return rows
        for share in shares:
            v, f = fast_simplification.simplify(ov.astype(np.float32), of.astype(np.int32), target_reduction=1 - share)
            row("quadric", f"{share:.1%} faces", [len(f)] * frames, [(v, f, vertex_normals(v, f))] * frames)
    return rows


def normals(name, frames, tau, supersample=2):
    """The subtree-mean, the fitted and the per-view fitted shading normals on
    the same refinements of ``frames`` frames of the standard orbit at
    ``tau``: per normals, the
    median and mean over the frames of the differing share, the silhouette
    share and FLIP over the model's pixels."""
    data = pmjax.read_pm(pm_file(name))
    pm = pmjax.ProgressiveMesh.from_data(data)
    V0 = data.n_original_vertices
    sets = {"hierarchy": pmjax.hierarchy_normals(pm), "fitted": pmjax.fitted_normals(data)}
    # Fitted again per view, on the mesh drawn (from the stored ones; the
    # samples weighted by the area seen from the eye).
    per_view = pmjax.ViewNormals(data, sets["fitted"])
    cams = pmjax.standard_orbit(data.vertices[:V0], frames)
    views = [index_camera(cams, i) for i in range(frames)]
    # The original is drawn with its own vertex normals, the same in every set.
    ov, of = data.vertices[:V0], data.faces
    measures = {key: dict(differing_share=[], silhouette_share=[], flip_model_mean=[]) for key in [*sets, "per view"]}
    faces = []
    t0 = time.perf_counter()
    with Renderer(views[0].width, views[0].height, supersample=supersample, float_color=True) as r:
        for cam in views:
            v, f, ids = pmjax.refine(pm, cam, tau).mesh(pm)
            ids = np.asarray(ids)
            faces.append(len(f))
            original = r.render_mesh(ov, of, cam, normals=sets["fitted"][:V0])
            silhouette = silhouette_difference(r, (ov, of), (v, f), cam)["differing_share"]
            drawn = {key: n[ids] for key, n in sets.items()}
            drawn["per view"] = per_view(ids, f, eye=np.asarray(cam.eye))
            for key, n in drawn.items():
                image = r.render_mesh(v, f, cam, normals=n)
                m = measures[key]
                m["differing_share"].append(image_difference(*original, *image)["differing_share"])
                m["silhouette_share"].append(silhouette)
                m["flip_model_mean"].append(flip_difference(*original, *image)["flip_model_mean"])
    rows = []
    for key, m in measures.items():
        out = dict(model=name, frames=frames, tau=tau, normals=key, F=len(of), faces=statistics.median(faces),
                   seconds=round(time.perf_counter() - t0, 1))
        for k, values in m.items():
            out[k] = statistics.median(values)
            out["mean_" + k] = statistics.fmean(values)
        rows.append(out)
        print(f"{name:8s} {frames:4d} frames tau {tau:g} {key:9s}: faces {out['faces']:8.0f} | differing "
              f"{out['differing_share']:7.3%} (mean {out['mean_differing_share']:7.3%}) | silhouette "
              f"{out['silhouette_share']:7.3%} | FLIP {out['flip_model_mean']:.4f} (mean "
              f"{out['mean_flip_model_mean']:.4f})", flush=True)
    return rows


def fit(name, repeats):
    """Seconds of ``pmjax.fitted_normals`` on ``name``'s hierarchy, C loops
    and NumPy alternated ``repeats`` times: medians and their ratio."""
    from pmjax import _normals

    data = pmjax.read_pm(pm_file(name))
    native = _normals.native
    times = {"C": [], "NumPy": []}
    try:
        for _ in range(repeats):
            for way in times:
                _normals.native = native if way == "C" else None
                t = time.perf_counter()
                pmjax.fitted_normals(data)
                times[way].append(time.perf_counter() - t)
    finally:
        _normals.native = native
    row = dict(model=name, c_s=statistics.median(times["C"]) if native is not None else float("nan"),
               numpy_s=statistics.median(times["NumPy"]))
    row["ratio"] = row["numpy_s"] / row["c_s"]
    print(f"{name:8s} fitted_normals: C {row['c_s']:.3f} s, NumPy {row['numpy_s']:.3f} s, "
          f"C {row['ratio']:.2f}x faster (medians of {repeats})", flush=True)
    return [row, view_fit(data, name, repeats)]


def view_fit(data, name, repeats, frames=8, tau=1.0):
    """Milliseconds of ``pmjax.ViewNormals`` per drawn mesh (the refinements of
    ``frames`` standard-orbit frames at ``tau``, seen from their eyes): the C
    loops (wall and the process's CPU time) and NumPy alternated ``repeats``
    times per frame; medians over the frames of the medians over the repeats."""
    from pmjax import _normals

    pm = pmjax.ProgressiveMesh.from_data(data)
    V0 = data.n_original_vertices
    view = pmjax.ViewNormals(data, data.shading_normals)
    cams = pmjax.standard_orbit(data.vertices[:V0], frames)
    native = _normals.native
    per_frame = {"C": [], "C_cpu": [], "NumPy": []}
    try:
        for i in range(frames):
            cam = index_camera(cams, i)
            _, f, ids = pmjax.refine(pm, cam, tau).mesh(pm)
            eye = np.asarray(cam.eye)
            view(ids, f, eye=eye)  # the C loops' leaf order and workspace, made once
            times = {key: [] for key in per_frame}
            for _ in range(repeats):
                for way in ("C", "NumPy"):
                    _normals.native = native if way == "C" else None
                    t, c = time.perf_counter(), time.process_time()
                    view(ids, f, eye=eye)
                    times[way].append(1e3 * (time.perf_counter() - t))
                    if way == "C":
                        times["C_cpu"].append(1e3 * (time.process_time() - c))
            for key in per_frame:
                per_frame[key].append(statistics.median(times[key]))
    finally:
        _normals.native = native
    row = dict(model=name, part="ViewNormals", frames=frames, tau=tau, threads=_normals.FIT_THREADS,
               c_ms=statistics.median(per_frame["C"]) if native is not None else float("nan"),
               c_cpu_ms=statistics.median(per_frame["C_cpu"]), numpy_ms=statistics.median(per_frame["NumPy"]))
    row["ratio"] = row["numpy_ms"] / row["c_ms"]
    print(f"{name:8s} ViewNormals per frame: C {row['c_ms']:.1f} ms (CPU {row['c_cpu_ms']:.1f} ms, "
          f"{row['threads']} threads), NumPy {row['numpy_ms']:.0f} ms, C {row['ratio']:.1f}x faster "
          f"(medians over {frames} frames of {repeats} alternated repeats)", flush=True)
    return row


def cost(name, frames, tau, repeats, supersample=2):
    """``fidelity_ms`` of ``path_fidelity`` without and with FLIP on ``frames``
    frames of the standard orbit at ``tau``, alternated ``repeats`` times:
    medians over the frames, then over the repeats."""
    pm = pmjax.load(pm_file(name))
    cams = pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], frames)
    path_fidelity(pm, index_camera(cams, np.arange(2)), tau, supersample=supersample)  # contexts, normals, compiles
    medians = {False: [], True: []}
    for _ in range(repeats):
        for flip in (False, True):
            rows = path_fidelity(pm, cams, tau, supersample=supersample, flip=flip)
            medians[flip].append(statistics.median(r["fidelity_ms"] for r in rows))
    out = dict(model=name, frames=frames, tau=tau, repeats=repeats,
               fidelity_ms=statistics.median(medians[False]), fidelity_flip_ms=statistics.median(medians[True]))
    out["flip_ratio"] = out["fidelity_flip_ms"] / out["fidelity_ms"]
    print(f"{name:8s} {frames:4d} frames tau {tau:g}: fidelity_ms median {out['fidelity_ms']:7.0f} without FLIP, "
          f"{out['fidelity_flip_ms']:7.0f} with (x{out['flip_ratio']:.3f}; {repeats} repeats)", flush=True)
    return [out]


def pareto_plot(rows, path):
    """Faces drawn against FLIP over the model's pixels and against the
    differing share, per model, pmjax and the quadric (``frontier`` rows); PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    from pmjax._atomic import atomic_path

    models = sorted({r["model"] for r in rows})
    fig, axes = plt.subplots(len(models), 2, figsize=(9, 3.4 * len(models)), squeeze=False)
    for axis_row, name in zip(axes, models):
        for ax, key, label in zip(axis_row, ("flip_model_mean", "differing_share"),
                                  ("mean FLIP over the model's pixels", "differing share of the model's pixels")):
            for method, style in (("pmjax", "o-"), ("quadric", "s--")):
                pts = sorted((r["faces"], r[key]) for r in rows if r["model"] == name and r["method"] == method)
                if pts:
                    ax.plot(*zip(*pts), style, label=method)
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # overlapping labels otherwise
            ax.set_xlabel(f"faces drawn ({name})")
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend()
    fig.tight_layout()
    with atomic_path(path, ".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="bunny,dragon")
    ap.add_argument("--frames", default="240", help="frames per model, e.g. '240' or '240,48' per model")
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--figures", help="also write the paper's figures (first model) here")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated subset of {','.join(PARTS)}")
    ap.add_argument("--frontier-frames", default="48,24", help="frames per model for the frontier part")
    ap.add_argument("--frontier-taus", default="0.125,0.25,0.5,1")
    ap.add_argument("--quadric-shares", default="0.1,0.2,0.4,0.7",
                    help="face shares of the quadric baseline, or 'match': pmjax's median face share at each tau")
    ap.add_argument("--normals-frames", default="24", help="frames per model for the normals part")
    ap.add_argument("--normals-tau", type=float, default=1.0, help="tau of the normals part")
    ap.add_argument("--cost-frames", default="24", help="frames per model for the cost part")
    ap.add_argument("--cost-repeats", type=int, default=3, help="alternated repeats of the cost part")
    ap.add_argument("--fit-repeats", type=int, default=5, help="alternated repeats of the fit part")
    ap.add_argument("--supersample", type=int, default=2, metavar="S",
                    help="S x S samples per pixel in every render (default 2, as `pmjax path --fidelity`)")
    ap.add_argument("--plot", help="frontier part: write the faces-against-fidelity plot (PNG) here")
    ap.add_argument("--json")
    args = ap.parse_args()
    parts = set(args.parts.split(","))
    if parts - set(PARTS):
        ap.error(f"unknown part(s) {sorted(parts - set(PARTS))}")
    print(f"machine: {machine()}\n")
    names = args.models.split(",")
    frames = per_model(args.frames, names)
    rows, frontier_rows, normals_rows = [], [], []
    for name, n in zip(names, frames if "orbit" in parts else []):
        data = pmjax.read_pm(pm_file(name))
        pm = pmjax.ProgressiveMesh.from_data(data)
        cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], n)
        for tau in [float(t) for t in args.taus.split(",")]:
            fid = path_fidelity(pm, cams, tau, supersample=args.supersample)
            med = lambda k, rows=fid: statistics.median(r[k] for r in rows)
            row = dict(model=name, frames=n, tau=tau, F=len(data.faces), faces=med("faces"),
                       face_share=med("faces") / len(data.faces), differing_share=med("differing_share"),
                       max_differing_share=max(r["differing_share"] for r in fid), psnr=med("psnr"),
                       silhouette_share=med("silhouette_share"),
                       popping_share=statistics.median(r["popping_share"] for r in fid[1:]),
                       render_ms=med("render_ms"))
            rows.append(row)
            print(f"{name:8s} {n:4d} frames tau {tau:4g}: faces {row['faces']:8.0f} ({row['face_share']:6.2%}) | "
                  f"differing {row['differing_share']:7.3%} (max {row['max_differing_share']:7.3%}) | "
                  f"PSNR {row['psnr']:5.1f} dB | silhouette {row['silhouette_share']:7.3%} | "
                  f"popping {row['popping_share']:7.3%} | "
                  f"render {row['render_ms']:6.1f} ms", flush=True)
        if args.figures and name == names[0]:
            for fig, (p, faces) in paper_figures(pm, args.figures).items():
                print(f"  figure {p}: {faces} faces")
    if "frontier" in parts:
        print("\nFidelity against faces (same frames for every row):")
        for name, n in zip(names, per_model(args.frontier_frames, names)):
            frontier_rows += frontier(name, n, [float(t) for t in args.frontier_taus.split(",")],
                                      None if args.quadric_shares == "match"
                                      else [float(s) for s in args.quadric_shares.split(",")], args.supersample)
    if args.plot and frontier_rows:
        pareto_plot(frontier_rows, args.plot)
    if "normals" in parts:
        print("\nShading normals (same refinements and frames for all):")
        for name, n in zip(names, per_model(args.normals_frames, names)):
            normals_rows += normals(name, n, args.normals_tau, args.supersample)
    cost_rows = []
    if "cost" in parts:
        print("\nMeasuring cost per frame (path_fidelity, tau 1):")
        for name, n in zip(names, per_model(args.cost_frames, names)):
            cost_rows += cost(name, n, 1.0, args.cost_repeats, args.supersample)
    fit_rows = []
    if "fit" in parts:
        print("\nThe shading normals' fit:")
        for name in names:
            fit_rows += fit(name, args.fit_repeats)
    if args.json:
        write_json(args.json, dict(machine=machine(), supersample=args.supersample, rows=rows,
                                   frontier=frontier_rows, normals=normals_rows, cost=cost_rows, fit=fit_rows))


if __name__ == "__main__":
    main()
