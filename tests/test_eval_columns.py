"""Evaluation columns: compilation is timed apart from refinement, camera
context on request, and the dataset folder read by name by the common
Parquet readers."""

from __future__ import annotations

import numpy as np
import pytest

import pmjax
from pmjax._eval import evaluate

pa = pytest.importorskip("pyarrow")
ds = pytest.importorskip("pyarrow.dataset")

DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
                 "vertices", "executed"]


@pytest.fixture(scope="module")
def cow(built, tmp_path_factory):
    path = str(tmp_path_factory.mktemp("models") / "cow.pmz")
    pmjax.save_pm(built("cow.ply"), path)
    return path


def table(folder):
    return ds.dataset(folder, format="parquet").to_table()


@pytest.mark.parametrize("kind", ["tau", "budget"])
def test_compilation_is_timed_apart_from_refinement(cow, tmp_path, kind):
    """A cold process compiles on its first part: that time goes to
    compile_ms on the part's first row, not into refine_ms; a warm process
    compiles nothing (compile_ms 0) and gives the same rows."""
    import jax

    # A random set (no paths: batched calls) in parts of `chunk` cameras.
    chunk = 4 if kind == "budget" else 100
    job = dict(taus=[1.0]) if kind == "tau" else dict(budgets=[500])
    n = 8 if kind == "budget" else 300
    pmjax._eval._LOADED.clear()
    jax.clear_caches()
    got = {}
    for run in ("cold", "warm"):
        evaluate([cow], [f"random:{n}:1"], str(tmp_path / run), chunk=chunk, compile_cache=None, progress=False,
                 **job)
        got[run] = table(str(tmp_path / run))
    cold, warm = (got[r].column("compile_ms").to_numpy() for r in ("cold", "warm"))
    refine = got["cold"].column("refine_ms").to_numpy()
    # Only a part's first row carries its warm-up; the first part compiles, the others reuse its kernels.
    assert np.all(cold[1:] == 0) and np.all(warm == 0)
    # Compilation takes far longer than refining a part's cameras: none of it is in refine_ms.
    assert cold[0] > 10 * refine[:chunk].sum(), (cold[0], refine[:chunk])
    for c in DETERMINISTIC:
        assert got["cold"].column(c).to_pylist() == got["warm"].column(c).to_pylist(), c
