"""Budget jobs of several budgets: a chunk's budgets answered together (one
guess traversal per camera for all of them) give the rows of the budgets
run one job at a time, on random views and on paths, and resume."""

from __future__ import annotations

import numpy as np
import pytest

import pmjax

pytestmark = pytest.mark.core

COLUMNS = ("tau", "faces", "vertices", "executed", "budget_met")


def _rows(folder):
    import pyarrow.dataset as ds

    table = ds.dataset(folder, format="parquet").to_table()
    key = np.lexsort((table.column("camera").to_numpy(), table.column("camera_set").to_numpy(),
                      table.column("budget").to_numpy()))
    return {c: table.column(c).to_numpy()[key] for c in COLUMNS + ("budget", "camera")}


@pytest.mark.slow
def test_budgets_together_equal_one_job_per_budget(built, tmp_path):
    pytest.importorskip("pyarrow")
    data = built("cow.ply")
    model = str(tmp_path / "cow.pmz")
    pmjax.save_pm(data, model)
    sets = ["orbit:40", "random:70:3"]
    budgets = [0, 400, 900, 2500, 10 ** 7]  # below the base mesh ... beyond the full mesh
    pmjax.evaluate([model], sets, str(tmp_path / "all"), budgets=budgets, chunk=32, compile_cache=None,
                   progress=False)
    for b in budgets:
        pmjax.evaluate([model], sets, str(tmp_path / f"one-{b}"), budgets=[b], chunk=32, compile_cache=None,
                       progress=False)
    together = _rows(str(tmp_path / "all"))
    alone = [_rows(str(tmp_path / f"one-{b}")) for b in budgets]
    for c in COLUMNS + ("budget", "camera"):
        want = np.concatenate([a[c] for a in alone])
        assert want.tobytes() == together[c].tobytes(), c


def test_a_grown_budget_job_answers_only_the_new_budgets(built, tmp_path, monkeypatch):
    """A job grown by budgets computes the new budgets' parts (their
    cameras together), and its rows equal a fresh job's."""
    pytest.importorskip("pyarrow")
    from pmjax import _refine

    data = built("cow.ply")
    model = str(tmp_path / "cow.pmz")
    pmjax.save_pm(data, model)
    folder = str(tmp_path / "grown")
    pmjax.evaluate([model], ["random:40:5"], folder, budgets=[600], compile_cache=None, progress=False)
    asked = []
    original = _refine.faces_for_budget_batch
    monkeypatch.setattr(_refine, "faces_for_budget_batch", lambda pm, cams, budget, **kw: asked.append(
        sorted(set(np.ravel(budget).tolist()))) or original(pm, cams, budget, **kw))
    pmjax.evaluate([model], ["random:40:5"], folder, budgets=[600, 300, 1500], compile_cache=None,
                   progress=False)
    assert asked and all(a == [300, 1500] for a in asked)
    monkeypatch.setattr(_refine, "faces_for_budget_batch", original)
    fresh = str(tmp_path / "fresh")
    pmjax.evaluate([model], ["random:40:5"], fresh, budgets=[600, 300, 1500], compile_cache=None, progress=False)
    a, b = _rows(folder), _rows(fresh)
    for c in COLUMNS:
        assert a[c].tobytes() == b[c].tobytes(), c
