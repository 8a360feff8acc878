"""What each line of the README's Python block costs: first call and warm call.

Usage: python benchmarks/first_call.py [--model bunny] [--repeats 10] [--json OUT]

Each line runs in a fresh process (the persistent compilation cache off, as on a
first run), after the lines it needs (load the model, make the cameras). The
first call includes tracing and compilation; the warm call is the median of
``--repeats`` further calls. Peak memory is the process's maximum resident set.
To measure another checkout, run with ``PYTHONPATH=path/to/checkout``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from _common import machine
from refine import pm_file

SETUP = """
import jax, jax.numpy as jnp, numpy as np, pmjax
pm = pmjax.load(MODEL)
cams = pmjax.standard_orbit(pm.vertices[: pm.n_original_vertices], 240)
v = np.asarray(pm.vertices[: pm.n_original_vertices]); c = 0.5 * (v.min(0) + v.max(0)); r = float(np.linalg.norm(v.max(0) - v.min(0)))
camera = pmjax.look_at(eye=c + np.array([0.0, 0.2, 1.2]) * r, target=c)
"""

# (name, code run before timing, expression timed)
LINES = [
    ("refine(pm, camera, tau=1.0)", "", "pmjax.refine(pm, camera, tau=1.0).n_faces"),
    ("r.mesh(pm)", "r = pmjax.refine(pm, camera, tau=1.0)", "r.mesh(pm)[1]"),
    ("jax.jit(... refine ...)(camera)", "f = jax.jit(lambda c: pmjax.refine(pm, c, 1.0).n_faces)", "f(camera)"),
    ("jax.vmap(... refine ...)(cams)", "f = jax.vmap(lambda c: pmjax.refine(pm, c, 1.0).n_faces)", "f(cams)"),
    ("refine_batch(pm, cams, tau=1.0)", "", "pmjax.refine_batch(pm, cams, tau=1.0)[\"faces\"]"),
    ("refine_path(pm, cams, tau=1.0)", "", "[r.n_faces for r in pmjax.refine_path(pm, cams, tau=1.0)][-1]"),
    ("path_counts(pm, cams, tau=1.0)", "", "pmjax.path_counts(pm, cams, tau=1.0)[\"faces\"]"),
    ("faces_for_budget(pm, camera, 5000)", "", "pmjax.faces_for_budget(pm, camera, 5000)[1]"),
    ("soft_refine(pm, camera, 1.0, 0.1)", "", "pmjax.soft_refine(pm, camera, tau=1.0, temperature=0.1).faces"),
    ("jax.grad(... soft_refine ...)(1.0)", "",
     "jax.grad(lambda t: pmjax.soft_refine(pm, camera, t, 0.1).faces)(1.0)"),
    ("jax.jit(jax.grad(... soft_refine ...))(1.0)",
     "g = jax.jit(jax.grad(lambda t: pmjax.soft_refine(pm, camera, t, 0.1).faces))", "g(1.0)"),
    ("soft_tau_for_budget(pm, cams, 5000)", "", "pmjax.soft_tau_for_budget(pm, cams, 5000).tau"),
]

DRIVER = """
import json, resource, statistics, sys, time
import jax
jax.config.update("jax_enable_compilation_cache", False)
MODEL = sys.argv[1]
{setup}
{before}
def run():
    out = {call}
    jax.block_until_ready(out)
t0 = time.perf_counter(); run(); first = time.perf_counter() - t0
warm = []
for _ in range(int(sys.argv[2])):
    t0 = time.perf_counter(); run(); warm.append(time.perf_counter() - t0)
print(json.dumps(dict(first_s=first, warm_s=statistics.median(warm),
                      peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)))
"""


def measure(model: str, before: str, call: str, repeats: int) -> dict:
    code = DRIVER.format(setup=SETUP, before=before, call=call)
    env = dict(os.environ, JAX_ENABLE_COMPILATION_CACHE="false")
    # Run outside the repository, so that ``import pmjax`` is the installed
    # package or the checkout named by PYTHONPATH, not the current folder.
    out = subprocess.run([sys.executable, "-c", code, os.path.abspath(model), str(repeats)], capture_output=True,
                         text=True, env=env, cwd=tempfile.gettempdir())
    if out.returncode != 0:
        raise RuntimeError(f"{call}: {out.stderr.strip().splitlines()[-1] if out.stderr else out.returncode}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="bunny", help="model name in the shared data, or a .pmz path (default: bunny)")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--only", help="run only the lines whose name contains this text")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    model = args.model if args.model.endswith(".pmz") else pm_file(args.model)
    print(machine())
    print(f"model {model}; fresh process per line, compilation cache off; warm = median of {args.repeats}")
    print(f"| line | first call | warm call | peak memory |\n|---|---:|---:|---:|")
    rows = []
    for name, before, call in LINES:
        if args.only and args.only not in name:
            continue
        m = measure(model, before, call, args.repeats)
        rows.append(dict(line=name, **m))
        warm = m["warm_s"]
        warm_text = f"{warm * 1e3:.1f} ms" if warm < 1 else f"{warm:.2f} s"
        print(f"| `{name}` | {m['first_s']:.2f} s | {warm_text} | {m['peak_mb']:.0f} MB |", flush=True)
    if args.json:
        from pmjax._atomic import atomic_path

        with atomic_path(args.json) as tmp, open(tmp, "w") as fh:
            json.dump(dict(model=model, rows=rows), fh, indent=1)


if __name__ == "__main__":
    main()
