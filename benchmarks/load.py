"""What the structure check adds to ``pmjax.load``, per model, same run.

Three loads of each cached hierarchy, medians over repeats:

- ``unchecked``: every check but the structure check (checksums, dtypes,
  shapes, ranges), then the device copy: ``pmjax.load`` as it was without it;
- ``first``: ``pmjax.load`` of content this machine has not checked before
  (the structure check runs beside the device copy);
- ``repeat``: ``pmjax.load`` of content that passed before (its fingerprint
  is remembered, so the check is skipped).

Usage::

    python benchmarks/load.py [--repeats 7] [--models bunny dragon] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, median_time, write_json  # noqa: E402

import pmjax  # noqa: E402
from pmjax._model import ProgressiveMesh  # noqa: E402

CACHE = Path(__file__).resolve().parent / ".cache"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--models", nargs="*", help="model names (default: every cached build)")
    parser.add_argument("--json", help="also write the table as JSON")
    args = parser.parse_args(argv)
    paths = sorted(p for p in CACHE.glob("*.pmz") if not args.models or p.name.split("-")[0] in args.models)
    if not paths:
        print(f"no cached builds in {CACHE}: run benchmarks/refine.py first", file=sys.stderr)
        return 2
    print(machine())
    record = tempfile.mkdtemp(prefix="pmjax-known-")
    os.environ["PMJAX_KNOWN_STRUCTURES"] = record
    pmjax.load(paths[0])  # JAX start-up outside the timings

    def first(path):
        shutil.rmtree(record, ignore_errors=True)  # forget: the check runs
        pmjax.load(path)

    rows = []
    print(f"{'model':18s} {'faces':>9s} {'pcols':>8s} {'unchecked ms':>13s} {'first ms':>9s} {'added':>7s} "
          f"{'repeat ms':>10s} {'added':>7s}")
    for path in paths:
        data, _ = pmjax.read_arrays(path)
        unchecked, _ = median_time(lambda: ProgressiveMesh.from_data(pmjax.read_arrays(path)[0]), args.repeats)
        checked, _ = median_time(lambda: first(path), args.repeats)
        pmjax.load(path)
        repeat, _ = median_time(lambda: pmjax.load(path), args.repeats)
        row = dict(model=path.name.split("-")[0], faces=len(data.faces), pcols=data.n_pcols,
                   unchecked_ms=1e3 * unchecked, first_ms=1e3 * checked, repeat_ms=1e3 * repeat,
                   first_added=checked / unchecked - 1, repeat_added=repeat / unchecked - 1)
        rows.append(row)
        print(f"{row['model']:18s} {row['faces']:9d} {row['pcols']:8d} {row['unchecked_ms']:13.1f} "
              f"{row['first_ms']:9.1f} {row['first_added']:+7.0%} {row['repeat_ms']:10.1f} {row['repeat_added']:+7.0%}")
    shutil.rmtree(record, ignore_errors=True)
    if args.json:
        write_json(args.json, dict(machine=machine(), repeats=args.repeats, rows=rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
