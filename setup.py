"""Build of the compiled parts: the front engine's C core (as XLA FFI targets),
the builder's C loops, the .pmz version 2 decoder's loops and the shading
normals' fit.

Everything else is in pyproject.toml. All four are optional: where they
cannot be compiled (no C compiler), pmjax installs without them, refinement
runs on the dense engine (and the front engine as JAX kernels), the
builder chooses its batches with NumPy (the same hierarchies, slower), the
.pmz reader decodes with NumPy (the same arrays, slower) and the shading
normals are fitted with NumPy (the same bits, slower).
``pmjax info --engines`` says which are active; CI sets PMJAX_REQUIRE_CORE=1,
under which a missing core fails the tests.

PMJAX_SANITIZE=address,undefined builds all four with those sanitizers
(docs/front.md: how to run the tests under them).
"""

import glob
import os

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

CORE = "pmjax/engines/core"

# The core's C: IEEE float32 arithmetic, no fast math. Multiply-adds may be
# fused: the certified decisions bound any evaluation of their formulas with
# at most 16 roundings on a path, fused or not, and the bounds' margins
# dominate either rounding. No FP exceptions are enabled, so square roots
# and selects may be evaluated speculatively, and "omp simd" loops vectorize
# (no OpenMP runtime is used). Each SIMD level's loops carry their own target
# (pmjax/engines/core/kernels.c); the rest is built for the baseline.
CORE_CFLAGS = ["-O3", "-std=c99", "-fno-math-errno", "-fno-trapping-math", "-ffp-contract=fast", "-fopenmp-simd",
               "-Wall", "-Wextra", "-fvisibility=hidden"]
FFI_CXXFLAGS = ["-O2", "-std=c++17", "-Wall", "-Wextra", "-fvisibility=hidden"]
SANITIZE = [s for s in os.environ.get("PMJAX_SANITIZE", "").split(",") if s]
SANITIZE_FLAGS = [f"-fsanitize={','.join(SANITIZE)}", "-fno-omit-frame-pointer", "-g"] if SANITIZE else []


def source_digest(path: str) -> list:
    """The macro that names the text a ctypes extension is built from: pmjax
    compares it with the source beside the library when it loads one, and
    falls back to its NumPy steps on a stale build (pmjax/_clib.py)."""
    import hashlib

    with open(path, "rb") as fh:
        return [("PMJAX_SOURCE_DIGEST", '"%s"' % hashlib.sha256(fh.read()).hexdigest())]


def ffi_include() -> str:
    """XLA's FFI headers, shipped with jaxlib (a build requirement)."""
    import jax.ffi

    return jax.ffi.include_dir()


class BuildExt(build_ext):
    """Compiles an extension's C sources (``c_sources``) with C flags and its
    C++ sources with C++ flags, then links them (setuptools passes one set of
    flags to every source of an extension)."""

    def build_extension(self, ext):
        c_sources = getattr(ext, "c_sources", [])
        if c_sources:
            objects = self.compiler.compile(c_sources, output_dir=self.build_temp, include_dirs=ext.include_dirs,
                                            extra_postargs=CORE_CFLAGS + SANITIZE_FLAGS, depends=ext.depends)
            ext.extra_objects = list(ext.extra_objects or []) + objects
        if ext.name == "pmjax.engines._pmx":  # XLA's headers as system headers: their warnings are not ours
            ext.extra_compile_args = list(ext.extra_compile_args) + ["-isystem", ffi_include()]
        super().build_extension(ext)


def main():
    core = Extension(
        "pmjax.engines._pmx",
        sources=[f"{CORE}/ffi.cc"],
        include_dirs=[CORE],
        depends=sorted(glob.glob(f"{CORE}/*.h")),
        language="c++",
        extra_compile_args=FFI_CXXFLAGS + SANITIZE_FLAGS,
        extra_link_args=SANITIZE_FLAGS,
        optional=True,
    )
    core.c_sources = sorted(glob.glob(f"{CORE}/*.c"))

    setup(
        cmdclass={"build_ext": BuildExt},
        ext_modules=[
            core,
            # The builder's batch choice (builders/_build_native.c): the NumPy
            # builder's arithmetic in its order, so no contraction either.
            Extension(
                "pmjax.builders._build_native",
                sources=["builders/_build_native.c"],
                define_macros=source_digest("builders/_build_native.c"),
                extra_compile_args=["-O3", "-std=c99", "-ffp-contract=off"] + SANITIZE_FLAGS,
                extra_link_args=SANITIZE_FLAGS,
                optional=True,
            ),
            # The .pmz version 2 decoder (pmjax/_pmz_native.c): the NumPy
            # reader's arithmetic in its order, so no contraction either.
            Extension(
                "pmjax._pmz_native",
                sources=["pmjax/_pmz_native.c"],
                define_macros=source_digest("pmjax/_pmz_native.c"),
                extra_compile_args=["-O3", "-std=c99", "-ffp-contract=off", "-Wall"] + SANITIZE_FLAGS,
                extra_link_args=SANITIZE_FLAGS,
                optional=True,
            ),
            # The shading normals' fit (pmjax/_normals_native.c): the NumPy
            # fit's arithmetic in its order, so no contraction either; its
            # parts on two threads. No FP exceptions are enabled, so its
            # selects may be evaluated on vector lanes (the same bits).
            Extension(
                "pmjax._normals_native",
                sources=["pmjax/_normals_native.c"],
                define_macros=source_digest("pmjax/_normals_native.c"),
                extra_compile_args=["-O3", "-std=c99", "-ffp-contract=off", "-fno-trapping-math", "-fno-math-errno",
                                    "-Wall", "-pthread"] + SANITIZE_FLAGS,
                extra_link_args=["-pthread"] + SANITIZE_FLAGS,
                optional=True,
            ),
        ],
    )


# Imported for its flags by tests/test_build.py; run by pip's build backend as __main__.
if __name__ == "__main__":
    main()
