"""Build of the compiled parts: the C loops of the output-sensitive engine and of the builder.

Everything else is in pyproject.toml. The extensions are optional: where they
cannot be compiled (no C compiler), pmjax installs without them, its front
engine runs as JAX kernels instead (``pmjax.native_available()``) and the
builder chooses its batches with NumPy (the same hierarchies, slower).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "pmjax._front_native",
            sources=["pmjax/_front_native.c"],
            # IEEE float32 arithmetic, no fast math. Multiply-adds may be
            # fused: the certified decisions bound any evaluation of their
            # formulas with at most 16 roundings on a path, fused or not, and
            # the subtree bounds' margins dominate either rounding. No FP
            # exceptions are enabled, so square roots and selects may be
            # evaluated speculatively, and "omp simd" loops vectorize (no
            # OpenMP runtime is used).
            extra_compile_args=["-O3", "-std=c99", "-fno-math-errno", "-fno-trapping-math", "-ffp-contract=fast",
                                "-fopenmp-simd"],
            optional=True,
        ),
        # The builder's batch choice (builders/_build_native.c): the NumPy
        # builder's arithmetic in its order, so no contraction either.
        Extension(
            "pmjax.builders._build_native",
            sources=["builders/_build_native.c"],
            extra_compile_args=["-O3", "-std=c99", "-ffp-contract=off"],
            optional=True,
        ),
    ]
)
