"""The front engine's C core builds clean: -Wall -Wextra -Werror, for this processor and, where a cross
compiler is installed, for aarch64 (the plain kernels alone)."""

import concurrent.futures
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[1] / "pmjax" / "engines" / "core"
sys.path.insert(0, str(CORE.parents[2]))
from setup import CORE_CFLAGS, FFI_CXXFLAGS  # noqa: E402  (the flags the package is built with)

pytestmark = pytest.mark.core


def compile_all(compiler: str, flags: list) -> list:
    """Errors of compiling every core source with ``compiler`` (empty: clean)."""
    def one(source):
        out = subprocess.run([compiler, *flags, "-Werror", "-c", str(source), "-o", "/dev/null"],
                             capture_output=True, text=True)
        return f"{source.name}: {out.stderr}" if out.returncode or out.stderr else None

    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        return [e for e in pool.map(one, sorted(CORE.glob("*.c"))) if e]


@pytest.mark.parametrize("compiler", ["gcc", "aarch64-linux-gnu-gcc"])
@pytest.mark.slow
def test_core_compiles_without_warnings(compiler):
    if shutil.which(compiler) is None:
        pytest.skip(f"{compiler} is not installed")
    assert compile_all(compiler, CORE_CFLAGS) == []


@pytest.mark.slow
def test_binding_compiles_without_warnings():
    import jax.ffi

    flags = [*FFI_CXXFLAGS, "-fsyntax-only", "-isystem", jax.ffi.include_dir(), "-I", str(CORE), "-isystem",
             sysconfig.get_paths()["include"], "-Werror"]
    out = subprocess.run(["g++", *flags, str(CORE / "ffi.cc")], capture_output=True, text=True)
    assert out.returncode == 0 and not out.stderr, out.stderr
