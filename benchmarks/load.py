"""What the structure check adds to ``pmjax.load``, per model, same run.

Three loads of each cached hierarchy, medians over repeats:

- ``unchecked``: every check but the structure check (checksums, dtypes,
  shapes, ranges), then the device copy: ``pmjax.load`` as it was without it;
- ``first``: ``pmjax.load`` of content this machine has not checked before
  (the structure check runs beside the device copy);
- ``repeat``: ``pmjax.load`` of content that passed before (its fingerprint
  is remembered, so the check is skipped).

With ``--format FILE.pmz ...``: the file versions instead, per hierarchy,
same run: sizes of version 1, version 2, version 2 with its chunks in
encoding 1 (no predictions) and the source mesh (given as
``FILE.pmz=MESH``); ``pmjax.load`` of each, alternating, medians over
repeats, with the structure check skipped (its content known; version 2's
decoding known too, docs/format.md "Known decodings") and run (with an
empty record), the processor time of the former (all threads), and
version 2 decoded by the NumPy steps instead of the C
loops (structure known); where version 2's bytes go (each part of each chunk
compressed alone); and the coarse-first prefixes: the bytes needed for 1 % of
the faces, and the faces a prefix of 10 % of the file holds.

Usage::

    python benchmarks/load.py [--repeats 7] [--models bunny dragon] [--json out.json]
    python benchmarks/load.py --format dragon.pmz=dragon.ply bunny.pmz=bunny.ply [--repeats 7] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, median_time, write_json  # noqa: E402

import pmjax  # noqa: E402
from pmjax import _codec  # noqa: E402
from pmjax._model import ProgressiveMesh  # noqa: E402
from pmjax._pmfile import numpy_steps  # noqa: E402

CACHE = Path(__file__).resolve().parent / ".cache"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--models", nargs="*", help="model names (default: every cached build)")
    parser.add_argument("--json", help="also write the table as JSON")
    parser.add_argument("--format", nargs="+", metavar="PMZ[=MESH]",
                        help="compare the file versions of these hierarchies (and the size of their source meshes)")
    args = parser.parse_args(argv)
    if args.format:
        return formats(args)
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


def chunk_ends(path) -> tuple[list[int], list[int]]:
    """Byte offset where each chunk of a version 2 file ends, and the faces
    the hierarchy read up to there holds (its original mesh's)."""
    import json

    with open(path, "rb") as fh:
        fh.read(8)
        length = int.from_bytes(fh.read(4), "little")
        header = json.loads(fh.read(length))
    at, ends = 12 + length, []
    for _, size, _ in header["chunks"]:
        at += 32 + size
        ends.append(at)
    return ends, list(np.cumsum(header["group_faces"]))


def part_sizes(pm) -> dict:
    """Compressed bytes of each part of version 2's chunks (``positions``,
    ``faces``, ...), each part of each chunk compressed alone, summed over the
    chunks, largest first."""
    _, table = _codec.chunk_arrays(pm)
    codec = "zstd" if _codec.zstd_available() else "zlib"
    out = {}
    for _, parts in table:
        labels = dict.fromkeys(part for part, _ in parts)
        for label in labels:
            raw = b"".join(_codec.planes(a) for part, a in parts if part == label)
            out[label] = out.get(label, 0) + len(_codec.compress(raw, codec))
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def formats(args) -> int:
    print(machine())
    record = tempfile.mkdtemp(prefix="pmjax-known-")
    os.environ["PMJAX_KNOWN_STRUCTURES"] = record
    work = tempfile.mkdtemp(prefix="pmjax-format-")
    rows = []
    print(f"{'model':10s} {'faces':>8s} {'v1 MB':>7s} {'v2 MB':>7s} {'enc1 MB':>7s} {'mesh MB':>8s} {'save s':>7s} "
          f"{'v1 load':>8s} {'v2 load':>8s} {'enc1 ld':>8s} {'v2 NumPy':>9s} {'v1 first':>9s} {'v2 first':>9s} "
          f"{'1% faces at':>12s} {'10% file holds':>15s} {'v1 cpu':>7s} {'v2 cpu':>7s} {'enc1 cpu':>8s}")
    for item in args.format:
        given, _, source = item.partition("=")
        pm = pmjax.read_pm(given)
        name = Path(given).stem
        v1, v2 = os.path.join(work, name + "-v1.pmz"), os.path.join(work, name + "-v2.pmz")
        pmjax.save_pm(pm, v1, version=1)
        t = time.perf_counter()
        pmjax.save_pm(pm, v2)
        save = time.perf_counter() - t
        enc1 = os.path.join(work, name + "-v2-encoding1.pmz")
        encoding, _codec.ENCODING = _codec.ENCODING, 1
        try:
            pmjax.save_pm(pm, enc1)
        finally:
            _codec.ENCODING = encoding
        parts = part_sizes(pm)
        # JAX start-up and first-call costs outside the timings; the version 2
        # files' decodings recorded (by the C loops and by the NumPy steps).
        for path in (v1, v2, enc1):
            pmjax.load(path)
        with numpy_steps():
            pmjax.load(v2)
        times = {"v1": [], "v2": [], "v2 enc1": [], "v2 numpy": [], "v1 first": [], "v2 first": []}
        # Processor time of the load, all threads: what it costs a machine
        # whose cores are busy with other work (the wall time then follows it).
        cpu = {"v1": [], "v2": [], "v2 enc1": []}
        for _ in range(args.repeats):  # alternating, so a slow phase of the machine hits each
            for key, path in (("v1", v1), ("v2", v2), ("v2 enc1", enc1)):
                start = time.process_time()
                times[key].append(median_time(lambda: pmjax.load(path), 1)[0])
                cpu[key].append(time.process_time() - start)
            # Version 2 decoded by the NumPy steps (where the C loops are not built).
            with numpy_steps():
                times["v2 numpy"].append(median_time(lambda: pmjax.load(v2), 1)[0])
            # Each first load with an empty record of its own: the record of
            # the loads above (structures and decodings) stays as it is.
            for key, path in (("v1 first", v1), ("v2 first", v2)):
                os.environ["PMJAX_KNOWN_STRUCTURES"] = tempfile.mkdtemp(prefix="pmjax-first-", dir=work)
                try:
                    times[key].append(median_time(lambda: pmjax.load(path), 1)[0])
                finally:
                    os.environ["PMJAX_KNOWN_STRUCTURES"] = record
        med = {k: float(np.median(v)) for k, v in times.items()}
        med_cpu = {k: float(np.median(v)) for k, v in cpu.items()}
        ends, faces = chunk_ends(v2)
        F = len(pm.faces)
        size = os.path.getsize(v2)
        # Prefixes end after the base chunk and after each batch chunk.
        first = next(i for i, f in enumerate(faces) if f >= 0.01 * F)
        within = [i for i in range(len(faces)) if ends[i] <= 0.10 * size]
        mesh = os.path.getsize(source) if source else None
        row = dict(model=name, faces=F, v1_bytes=os.path.getsize(v1), v2_bytes=size,
                   v2_encoding1_bytes=os.path.getsize(enc1), mesh_bytes=mesh, save_s=save, part_bytes=parts,
                   **{k.replace(" ", "_") + "_load_s": v for k, v in med.items()},
                   **{k.replace(" ", "_") + "_load_cpu_s": v for k, v in med_cpu.items()},
                   one_percent_prefix_bytes=ends[first], one_percent_prefix_batches=first,
                   one_percent_prefix_faces=int(faces[first]),
                   ten_percent_prefix_faces=int(faces[within[-1]]) if within else 0,
                   ten_percent_prefix_batches=within[-1] if within else None)
        rows.append(row)
        mb = lambda b: f"{b / 1e6:7.2f}" if b else "      -"
        print(f"{name:10s} {F:8d} {mb(row['v1_bytes'])} {mb(size)} {mb(row['v2_encoding1_bytes'])} {mb(mesh):>8s} "
              f"{save:7.2f} {med['v1']:8.3f} {med['v2']:8.3f} {med['v2 enc1']:8.3f} {med['v2 numpy']:9.3f} "
              f"{med['v1 first']:9.3f} {med['v2 first']:9.3f} {ends[first] / size:11.1%} "
              f"{row['ten_percent_prefix_faces'] / F:14.1%} {med_cpu['v1']:7.3f} {med_cpu['v2']:7.3f} "
              f"{med_cpu['v2 enc1']:8.3f}")
        print("  " + ", ".join(f"{part} {b / 1e6:.2f} MB" for part, b in parts.items()))
    shutil.rmtree(record, ignore_errors=True)
    shutil.rmtree(work, ignore_errors=True)
    if args.json:
        write_json(args.json, dict(machine=machine(), repeats=args.repeats, rows=rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
