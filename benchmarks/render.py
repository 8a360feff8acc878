"""Image-space fidelity benchmark: refined vs original renders along the standard orbit.

Usage: python benchmarks/render.py [--models bunny,dragon] [--frames 240] [--taus 0.5,1,2,4]
       [--figures docs/figures] [--json OUT]

Per model and tau: median share of the model's pixels that differ from the
original mesh's render (a pixel differs when a channel differs by > 8/255),
median PSNR over the model's pixels, median popping share (pixels changed at a
frame only because the refinement changed), median faces and render ms.
"""

from __future__ import annotations

import argparse
import statistics
import sys

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import machine, write_json  # noqa: E402
from refine import pm_file  # noqa: E402

import pmjax  # noqa: E402
from pmjax.render import paper_figures, path_fidelity  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="bunny,dragon")
    ap.add_argument("--frames", default="240", help="frames per model, e.g. '240' or '240,48' per model")
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--figures", help="also write the paper's figures (first model) here")
    ap.add_argument("--json")
    args = ap.parse_args()
    print(f"machine: {machine()}\n")
    names = args.models.split(",")
    frames = [int(x) for x in args.frames.split(",")]
    frames += [frames[-1]] * (len(names) - len(frames))
    rows = []
    for name, n in zip(names, frames):
        path = pm_file(name)
        pm, data = pmjax.load(path), pmjax.read_pm(path)
        cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], n)
        for tau in [float(t) for t in args.taus.split(",")]:
            fid = path_fidelity(pm, cams, tau)
            med = lambda k, rows=fid: statistics.median(r[k] for r in rows)
            row = dict(model=name, frames=n, tau=tau, F=len(data.faces), faces=med("faces"),
                       face_share=med("faces") / len(data.faces), differing_share=med("differing_share"),
                       max_differing_share=max(r["differing_share"] for r in fid), psnr=med("psnr"),
                       popping_share=statistics.median(r["popping_share"] for r in fid[1:]),
                       render_ms=med("render_ms"))
            rows.append(row)
            print(f"{name:8s} {n:4d} frames tau {tau:4g}: faces {row['faces']:8.0f} ({row['face_share']:6.2%}) | "
                  f"differing {row['differing_share']:7.3%} (max {row['max_differing_share']:7.3%}) | "
                  f"PSNR {row['psnr']:5.1f} dB | popping {row['popping_share']:7.3%} | "
                  f"render {row['render_ms']:6.1f} ms", flush=True)
        if args.figures and name == names[0]:
            for fig, (p, faces) in paper_figures(pm, args.figures).items():
                print(f"  figure {p}: {faces} faces")
    if args.json:
        write_json(args.json, dict(machine=machine(), rows=rows))


if __name__ == "__main__":
    main()
