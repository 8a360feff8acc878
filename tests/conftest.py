"""Shared fixtures: the real models of ../shared/data and cached builds."""

from __future__ import annotations

import functools
import importlib.util
import os
from pathlib import Path

import pytest

DATA = Path(os.environ.get("PMJAX_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def _data_path(name: str) -> str:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} not found (set PMJAX_DATA or put shared/ beside the repository)")
    return str(path)


@functools.lru_cache(maxsize=None)
def _built(name: str, pair_distance: float, metric: str, target_faces: int):
    import pmjax
    from pmjax.builders import BuildOptions, build_pm

    v, f, _, _ = pmjax.load_clean_mesh(_data_path(name))
    options = BuildOptions(pair_distance=pair_distance, metric=metric, target_faces=target_faces)
    return build_pm(v, f, options)


@pytest.fixture(scope="session", autouse=True)
def known_records(tmp_path_factory):
    """The folder of structure and decoding records for the whole session
    (``$PMJAX_KNOWN_STRUCTURES``): the tests write none into the user's
    cache, and none recorded there by another pmjax skips a test's checks.
    Tests of the records themselves set a folder of their own."""
    folder = tmp_path_factory.mktemp("known")
    with pytest.MonkeyPatch.context() as m:
        m.setenv("PMJAX_KNOWN_STRUCTURES", str(folder))
        yield folder


@pytest.fixture(scope="session")
def built():
    """``built(name, pair_distance=0, metric='quadric', target_faces=0)`` -> PMData (cached)."""

    def get(name, pair_distance=0.0, metric="quadric", target_faces=0):
        return _built(name, pair_distance, metric, target_faces)

    return get


@pytest.fixture
def xvfb_display():
    """A virtual X display of the test's own: Xvfb picks a free display number
    and writes it once it accepts connections (``-displayfd``), so neither a
    display left by another run nor a slow start can break the test."""
    import shutil
    import subprocess

    if not shutil.which("Xvfb"):
        pytest.skip("needs Xvfb")
    read, write = os.pipe()
    xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", "640x480x24", "-nolisten", "tcp"],
                            pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    os.close(write)
    with os.fdopen(read) as ready:
        number = ready.readline().strip()
    try:
        if not number:
            xvfb.wait(10)
            pytest.fail(f"Xvfb did not start: {xvfb.stderr.read().decode(errors='replace')[-2000:]}")
        yield f":{number}"
    finally:
        xvfb.terminate()
        xvfb.wait(10)
        xvfb.stderr.close()


@pytest.fixture(scope="module")
def cow(built, tmp_path_factory) -> str:
    """The cow's hierarchy saved as a ``.pmz`` file: its path (the
    evaluation tests' model; files that need another cow define their own)."""
    import pmjax

    path = str(tmp_path_factory.mktemp("models") / "cow.pmz")
    pmjax.save_pm(built("cow.ply"), path)
    return path


def _simd_levels():
    from pmjax import engines

    if not engines.core_built():
        return ["plain"]
    best = engines.simd_best()
    levels = ("plain", "avx2", "avx512")
    return [pytest.param(level, marks=pytest.mark.skipif(levels.index(level) > levels.index(best),
                                                         reason=f"no {level} on this processor"))
            for level in levels]


@pytest.fixture(params=_simd_levels())
def simd(request):
    """Each test that takes it runs with every SIMD level of the front
    engine's core the processor has (the same bits from each)."""
    from pmjax import engines

    was = engines.simd(request.param)
    assert engines.simd() == request.param
    yield request.param
    engines.simd(was)


def _missing_compiled_parts() -> list[str]:
    """The compiled parts that are not built here, and why."""
    from pmjax import engines
    from pmjax.builders import _native as builder
    from pmjax.engines import _core

    missing = []
    if not engines.core_built():
        missing.append(f"the front engine's C core ({_core.LOAD_ERROR})")
    if builder._LIB is None:
        missing.append("the builder's C loops (pmjax.builders._build_native)")
    if importlib.util.find_spec("pmjax._pmz_native") is None:
        missing.append("the .pmz version 2 decoder's C loops (pmjax._pmz_native)")
    if importlib.util.find_spec("pmjax._normals_native") is None:
        missing.append("the shading normals' fit as C loops (pmjax._normals_native)")
    return missing


def pytest_collection_modifyitems(config, items):
    """Tests of the compiled parts (marker ``core``: the front engine's C
    core, the builder's C loops, the .pmz decoder's C loops, the shading
    normals' fit) skip where they are not built, but under
    PMJAX_REQUIRE_CORE=1 (CI sets it) a part that does not compile or load is
    an error: CI cannot go green without them."""
    missing = _missing_compiled_parts()
    if not missing:
        return
    why = "not built: " + "; ".join(missing)
    if os.environ.get("PMJAX_REQUIRE_CORE") == "1":
        raise pytest.UsageError(f"PMJAX_REQUIRE_CORE=1 but {why}")
    for item in items:
        if "core" in item.keywords:
            item.add_marker(pytest.mark.skip(reason=why))


@pytest.fixture(scope="session")
def data_path():
    """``data_path(name)``: path of a model in ../shared/data (skips if absent)."""
    return _data_path


def _same_bits(a, b) -> bool:
    """Equal dtype, shape and bytes (NaN payloads and signed zeros included)."""
    import numpy as np

    return a.dtype == b.dtype and a.shape == b.shape and np.ascontiguousarray(a).tobytes() == \
        np.ascontiguousarray(b).tobytes()


def _assert_same_pm(a, b) -> None:
    """Two progressive meshes with the same arrays, each bit for bit (names the first that differs)."""
    assert set(a.arrays()) == set(b.arrays())
    for name, x in a.arrays().items():
        assert _same_bits(x, getattr(b, name)), name


@pytest.fixture(scope="session")
def same_bits():
    """``same_bits(a, b)``: equal dtype, shape and bytes (NaN payloads and signed zeros included)."""
    return _same_bits


@pytest.fixture(scope="session")
def assert_same_pm():
    """``assert_same_pm(a, b)``: the same arrays, each bit for bit."""
    return _assert_same_pm
