"""Two checkouts of pmjax measured in the same run: alternating processes, medians, ratios.

Runs ``benchmarks/engines.py`` (this checkout's) under each checkout in turn
(``PYTHONPATH`` set to the checkout, whose compiled parts must be built in
place: ``python setup.py build_ext --inplace``), ``--runs`` times each,
alternating the order, on the same prebuilt ``.pmz`` file; prints the median
of each measurement per checkout and their ratio (second / first). Absolute
times move by 2-3x between machines of this kind and by up to 50 % within a
session: only ratios from one such run count.

Example: ``python benchmarks/compare.py ../before . --pm dragon.pmz --runs 6``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def run(checkout: str, pm: str, cores: int | None) -> dict:
    env = dict(os.environ, PYTHONPATH=os.path.abspath(checkout))
    cmd = [sys.executable, str(HERE / "engines.py"), "--pm", pm] + (["--cores", str(cores)] if cores else [])
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=HERE)
    if out.returncode != 0:
        raise SystemExit(f"{checkout}: engines.py failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("first", help="a checkout (the reference)")
    ap.add_argument("second", help="another checkout")
    ap.add_argument("--pm", required=True, help="the .pmz file both measure")
    ap.add_argument("--runs", type=int, default=4, help="processes per checkout (default 4)")
    ap.add_argument("--cores", type=int, help="pin each process to this many CPUs")
    args = ap.parse_args()
    pm = os.path.abspath(args.pm)
    results = {args.first: [], args.second: []}
    for i in range(args.runs):
        order = (args.first, args.second) if i % 2 == 0 else (args.second, args.first)
        for checkout in order:
            results[checkout].append(run(checkout, pm, args.cores))
            print(f"run {i + 1}/{args.runs}: {checkout} done", file=sys.stderr, flush=True)
    print(f"machine: {results[args.second][0]['machine']}")
    print(f"{'measure':32s} {'first':>12s} {'second':>12s} {'second/first':>13s}")
    for key, value in results[args.second][0].items():
        if not isinstance(value, (int, float)):
            continue
        second = statistics.median(r[key] for r in results[args.second])
        firsts = [r[key] for r in results[args.first] if key in r]
        first = statistics.median(firsts) if firsts else float("nan")
        print(f"{key:32s} {first:12.4f} {second:12.4f} {second / first if firsts else float('nan'):13.3f}")


if __name__ == "__main__":
    main()
