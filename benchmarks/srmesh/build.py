"""Build SrMesh's driver and the SR progressive meshes it reads.

Usage: python benchmarks/srmesh/build.py --mpl PATH [--models bunny,dragon] [--jobs 2] [--out DIR]

From a source folder of Hoppe's Mesh-processing-library (``--mpl``, left as it
is: the folders needed are copied under ``--out`` and built there with MPL's
own Makefiles, ``make CC=gcc`` in each folder), in order:

1. MPL's ``libHh`` and the three programs that make an SR progressive mesh
   (``MeshSimplify``, ``reverselines``, ``Filterprog``);
2. the driver ``srmesh_adapt`` (``srmesh_adapt.cpp`` beside this file, linked
   with ``libHh``, compiled with the flags MPL compiles ``libHh`` with);
3. per model, the SR progressive mesh of the same surface pmjax builds from
   (``pmjax.load_clean_mesh`` of ``<data>/<model>.ply`` written as MPL's
   ``.m``), made as MPL's ``bin/meshtopm.sh MESH.m -vsgeom`` makes it:
   ``MeshSimplify MESH.m -vsgeom -prog P -simplify`` (the base mesh),
   ``reverselines P`` (the vertex splits coarse to fine), ``Filterprog
   -fbase BASE -fprog RPROG -pm`` (the progressive mesh). ``-vsgeom`` keeps
   every vertex split's geometry SrMesh needs (``minii2``, no geometry fit).

One line of the copy is changed before the build: ``plane_of_triangle``
(``libHh/Geometry.h``) takes a zero-area triangle's normal as the zero vector
instead of stopping on an assertion. ``MeshSimplify -vsgeom`` meets such a
sliver while it reprojects the dragon's sample points along the vertex normal
(``reproject_locally``); with a zero normal the line meets no plane, which the
reprojection already handles (the point's residual falls back to its
projection). SrMesh itself never calls it.

Everything goes under ``--out`` (default ``benchmarks/.cache/srmesh``, ignored
by git): ``mpl/`` (the copy, built), ``bin/srmesh_adapt``, ``<model>.m``,
``<model>.sr.pm`` and a log per step. A mesh already made is kept (delete it
to remake it).

MPL's newest sources need C++23 (deducing ``this``); with g++ 12 build the
last C++20 revision (its commit "Minor" of 2026-08-08, just before "Change C++
language compilation from C++20 to C++23"), whose SrMesh has the same
refinement criteria.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE.parent / ".cache" / "srmesh"
# The flags of MPL's Makefile for g++ in release (make/Makefile_base_*).
MPL_CXXFLAGS = ["-std=c++20", "-O3", "-DNDEBUG", "-march=native", "-ffast-math", "-mfpmath=sse", "-m64"]
MPL_PROGRAMS = ["MeshSimplify", "reverselines", "Filterprog"]


def run(cmd, log: Path, *, cwd=None, stdout=None):
    """Run ``cmd`` (niced), its stderr (and stdout unless redirected) to ``log``;
    raise with the log's tail on failure."""
    with open(log, "ab") as err:
        err.write(("$ " + " ".join(map(str, cmd)) + "\n").encode())
        err.flush()
        result = subprocess.run(["nice", *map(str, cmd)], cwd=cwd, stdout=stdout or err, stderr=err)
    if result.returncode:
        tail = log.read_text(errors="replace")[-3000:]
        raise RuntimeError(f"{cmd[0]} failed (exit {result.returncode}); end of {log}:\n{tail}")


# The folders of MPL the build needs, and the one line changed in the copy.
MPL_FOLDERS = ["make", "bin", "libHh", *MPL_PROGRAMS]
PLANE_LINE = "  const Vector nor = normalized(get_normal_dir(triangle));\n"
PLANE_FIXED = "  const Vector nor = ok_normalized(get_normal_dir(triangle));\n"


def copy_mpl(mpl: Path, out: Path) -> Path:
    """MPL's needed folders copied to ``out/mpl`` (once; build products left
    behind), ``plane_of_triangle`` changed as the module's docstring says."""
    dest = out / "mpl"
    if not dest.exists():
        partial = out / "mpl.partial"
        shutil.rmtree(partial, ignore_errors=True)
        skip = shutil.ignore_patterns("*.o", "*.a", "*.gch", "Makefile.dep")
        for folder in MPL_FOLDERS:
            shutil.copytree(mpl / folder, partial / folder, ignore=skip)
        shutil.copy2(mpl / "LICENSE", partial / "LICENSE")
        os.replace(partial, dest)
    header = dest / "libHh" / "Geometry.h"
    lines = header.read_text().splitlines(keepends=True)
    start = next((i for i, line in enumerate(lines) if line.startswith("inline Plane plane_of_triangle(")), None)
    body = lines[start + 1:start + 3] if start is not None else []
    if PLANE_LINE in body:
        lines[lines.index(PLANE_LINE, start)] = PLANE_FIXED
        header.write_text("".join(lines))
    elif PLANE_FIXED not in body:
        raise RuntimeError(f"{header}: plane_of_triangle is not as expected; this MPL revision is not supported")
    return dest


def build_mpl(mpl: Path, jobs: int, out: Path) -> Path:
    """MPL's libHh and programs, built in the copy; returns its bin folder."""
    # Folder by folder, libHh first: the top-level targets would build the
    # X11 window library too, which none of these programs link.
    for folder in ["libHh", *MPL_PROGRAMS]:
        run(["make", "CC=gcc", f"-j{jobs}", "-C", folder], out / "make_mpl.log", cwd=mpl)
    bin_dir = mpl / "bin" / "unix"
    missing = [p for p in MPL_PROGRAMS if not (bin_dir / p).exists()]
    if missing:
        raise RuntimeError(f"MPL's make left no {', '.join(missing)} in {bin_dir}")
    return bin_dir


def build_driver(mpl: Path, out: Path) -> Path:
    """The driver, linked with MPL's libHh."""
    exe = out / "bin" / "srmesh_adapt"
    exe.parent.mkdir(parents=True, exist_ok=True)
    run(["g++", *MPL_CXXFLAGS, f"-I{mpl}", HERE / "srmesh_adapt.cpp", mpl / "libHh" / "libHh.a",
         "-ljpeg", "-lpng", "-lz", "-pthread", "-o", exe], out / "driver.log")
    return exe


def write_m(vertices, faces, path: Path) -> None:
    """A triangle mesh as MPL's ``.m`` (1-based ``Vertex`` and ``Face`` lines)."""
    with open(path, "w") as f:
        for i, p in enumerate(vertices, 1):
            f.write(f"Vertex {i}  {p[0]:.9g} {p[1]:.9g} {p[2]:.9g}\n")
        for j, t in enumerate(faces, 1):
            f.write(f"Face {j}  {t[0] + 1} {t[1] + 1} {t[2] + 1}\n")


def make_sr_pm(name: str, data: Path, bin_dir: Path, out: Path) -> Path:
    """The SR progressive mesh of model ``name`` (see the module's docstring)."""
    import pmjax

    pm_path = out / f"{name}.sr.pm"
    if pm_path.exists():
        return pm_path
    log = out / f"{name}.log"
    m_path, prog, base, rprog = (out / f"{name}{s}" for s in (".m", ".prog", ".base.m", ".rprog"))
    v, f, _, _ = pmjax.load_clean_mesh(data / f"{name}.ply")
    write_m(v, f, m_path)
    t = time.perf_counter()
    # The base mesh and the edge collapses fine to coarse.
    with open(base, "wb") as fo:
        run([bin_dir / "MeshSimplify", m_path, "-vsgeom", "-prog", prog, "-simplify"], log, stdout=fo)
    # The vertex splits coarse to fine.
    with open(rprog, "wb") as fo:
        run([bin_dir / "reverselines", prog], log, stdout=fo)
    # The progressive mesh; written aside and renamed, so a broken run leaves none.
    partial = out / f"{name}.sr.pm.partial"
    with open(partial, "wb") as fo:
        run([bin_dir / "Filterprog", "-fbase", base, "-fprog", rprog, "-pm"], log, stdout=fo)
    os.replace(partial, pm_path)
    for p in (prog, rprog):
        p.unlink()
    print(f"{name}: {len(f)} faces -> {pm_path} in {time.perf_counter() - t:.0f} s", flush=True)
    return pm_path


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mpl", required=True, type=Path, help="source folder of the Mesh-processing-library")
    ap.add_argument("--models", default="bunny,dragon", help="models to make SR meshes of ('' for none)")
    ap.add_argument("--jobs", type=int, default=2, help="make's parallel jobs")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args()
    if not (args.mpl / "libHh" / "SrMesh.cpp").exists():
        sys.exit(f"--mpl {args.mpl}: no libHh/SrMesh.cpp there (not a Mesh-processing-library source folder)")
    args.out.mkdir(parents=True, exist_ok=True)
    mpl = copy_mpl(args.mpl.resolve(), args.out.resolve())
    bin_dir = build_mpl(mpl, args.jobs, args.out)
    exe = build_driver(mpl, args.out)
    print(f"driver: {exe}", flush=True)
    sys.path.insert(0, str(HERE.parent))
    from _common import DATA

    for name in filter(None, args.models.split(",")):
        make_sr_pm(name, DATA, bin_dir, args.out)


if __name__ == "__main__":
    main()
