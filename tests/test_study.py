"""The worked study of docs/study runs end to end on the bundled model (small)."""

import importlib.util
import json
from pathlib import Path

import pytest

STUDY = Path(__file__).resolve().parents[1] / "docs" / "study" / "tau_schedule.py"


@pytest.mark.slow
def test_tau_schedule_study(tmp_path):
    spec = importlib.util.spec_from_file_location("tau_schedule", STUDY)
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    out = tmp_path / "figures"
    results = study.main(["--frames", "10", "--out", str(out), "--json", str(tmp_path / "r.json")])
    assert (out / "study_tau_schedule.png").stat().st_size > 10_000
    assert json.loads((tmp_path / "r.json").read_text())["frames"] == 10
    s = results["schedules"]
    total = results["total_budget"]
    for name in s:  # every schedule spends the same soft total
        assert abs(s[name]["soft_faces_total"] - total) <= 2e-3 * total, name
    # The optimiser starts from the constant schedule and improves its objective;
    # both beat giving every frame the same number of faces.
    assert s["optimised"]["soft_squared_error"] <= s["constant"]["soft_squared_error"] * (1 + 1e-4)
    assert s["constant"]["soft_squared_error"] < s["equal faces"]["soft_squared_error"]
    assert len(set(round(t, 4) for t in s["optimised"]["tau"])) > 1  # really per frame
