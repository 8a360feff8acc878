"""Build of the one compiled part: the C loops of the output-sensitive engine.

Everything else is in pyproject.toml. The extension is optional: where it
cannot be compiled (no C compiler), pmjax installs without it and its
front engine runs as JAX kernels instead (``pmjax.native_available()``).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "pmjax._front_native",
            sources=["pmjax/_front_native.c"],
            # IEEE arithmetic as written (no contraction, no fast math: the
            # certified decisions bound float32 rounding of the written
            # formulas). No FP exceptions are enabled, so square roots and
            # selects may be evaluated speculatively, and "omp simd" loops
            # vectorize (no OpenMP runtime is used).
            extra_compile_args=["-O3", "-std=c99", "-fno-math-errno", "-fno-trapping-math", "-ffp-contract=off",
                                "-fopenmp-simd"],
            optional=True,
        )
    ]
)
