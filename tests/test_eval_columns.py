"""Evaluation columns: compilation is timed apart from refinement, camera
context on request, and the dataset folder read by name by the common
Parquet readers."""

from __future__ import annotations

import os

import numpy as np
import pytest

import pmjax
from pmjax._eval import evaluate

pa = pytest.importorskip("pyarrow")
ds = pytest.importorskip("pyarrow.dataset")

DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
                 "vertices", "executed"]


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


def test_camera_columns_on_request(cow, tmp_path):
    """With camera_columns, each row carries its camera's eye, distance to
    the model's box centre (model units and bounding radii), field of view
    and image size, equal to the cameras generated for the set; the setting
    is part of the job."""
    data = pmjax.read_pm(cow)
    v0 = np.asarray(data.vertices[: data.n_original_vertices], np.float64)
    lo, hi = v0.min(0), v0.max(0)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    out = str(tmp_path / "cams")
    evaluate([cow], ["orbit:40", pmjax.camera_set("random:50:3", width=320, height=200, fov_y_deg=60)], out,
             taus=[1.0], chunk=32, compile_cache=None, progress=False, camera_columns=True)
    got = table(out)
    assert got.schema.names[-8:] == ["eye_x", "eye_y", "eye_z", "distance", "distance_radii", "fov_y_deg", "width",
                                     "height"]
    eye = np.stack([got.column(c).to_numpy() for c in ("eye_x", "eye_y", "eye_z")], 1)
    expect = np.concatenate([np.asarray(pmjax.standard_orbit(v0, 40).eye),
                             np.asarray(pmjax.random_views(v0, 50, seed=3).eye)])
    assert np.allclose(eye, expect, rtol=1e-6, atol=1e-6 * radius)
    distance = got.column("distance").to_numpy()
    assert np.allclose(distance, np.linalg.norm(eye - centre, axis=1), rtol=1e-12)
    assert np.allclose(got.column("distance_radii").to_numpy(), distance / radius, rtol=1e-12)
    # The standard orbit is at r / sin 22.5 degrees; random views within [0.05, 4] r of a point near the centre.
    assert np.allclose(got.column("distance_radii").to_numpy()[:40], 1 / np.sin(np.radians(22.5)))
    assert got.column("fov_y_deg").to_pylist() == pytest.approx([45.0] * 40 + [60.0] * 50)
    assert got.column("width").to_pylist() == [800] * 40 + [320] * 50
    assert got.column("height").to_pylist() == [600] * 40 + [200] * 50
    # The setting defines the parts: without it, the folder's parts would change.
    with pytest.raises(pmjax.EvalError, match=f"{out} holds parts that this command defines otherwise "
                                              r"\(camera_columns: True there, False here\); a job can gain"):
        evaluate([cow], ["orbit:40", pmjax.camera_set("random:50:3", width=320, height=200, fov_y_deg=60)], out,
                 taus=[1.0], chunk=32, compile_cache=None, progress=False)
    with pytest.raises(pmjax.EvalError, match="camera_columns must be True or False, not 'yes'"):
        evaluate([cow], ["orbit:40"], out, taus=[1.0], camera_columns="yes", progress=False)
    # Orthographic cameras have no field of view: null there.
    from pmjax._eval import _camera_context

    t = pmjax._camera_table.CameraTable(
        eye=np.array([[0.0, 0.0, 5.0], [3.0, 4.0, 0.0]]), rotation=np.tile(np.eye(3), (2, 1, 1)),
        fov_y=np.radians([30.0, 45.0]), near=np.ones(2), far=np.full(2, 9.0), ortho_height=np.ones(2),
        width=np.array([640, 800], np.int32), height=np.array([480, 600], np.int32),
        orthographic=np.array([False, True]))
    context = _camera_context(t, (0.0, 0.0, 0.0), 2.5)
    assert context["fov_y_deg"].to_pylist()[0] == pytest.approx(30.0) and context["fov_y_deg"].to_pylist()[1] is None
    assert context["distance"].to_pylist() == [5.0, 5.0] and context["distance_radii"].to_pylist() == [2.0, 2.0]


@pytest.fixture(scope="module")
def two_models(cow, tmp_path_factory):
    """A finished job of two models and two tolerances in parts of 8
    cameras, one part damaged and computed again (its file set aside)."""
    import shutil

    from pmjax._eval import damaged_folder

    folder = tmp_path_factory.mktemp("readers")
    other = str(folder / "calf.pmz")
    shutil.copy(cow, other)
    out = str(folder / "results")
    job = dict(taus=[1.0, 4.0], chunk=8, compile_cache=None, progress=False)
    evaluate([cow, other], ["orbit:20", "random:12:1"], out, **job)
    first = sorted(n for n in os.listdir(out) if n.startswith("part-"))[0]
    with open(os.path.join(out, first), "r+b") as fh:
        fh.truncate(100)
    assert evaluate([cow, other], ["orbit:20", "random:12:1"], out, **job).parts_written == 1
    assert os.listdir(damaged_folder(out)) == [first]
    return out


# (model, tau) -> rows: 20 + 12 cameras per model and tolerance.
GROUPS = {(m, t): 32 for m in ("calf", "cow") for t in (1.0, 4.0)}


def _check(got, reference):
    for c in DETERMINISTIC:
        assert got[c] == reference[c], c


def test_pyarrow_reads_the_folder_by_name(two_models):
    pq = pytest.importorskip("pyarrow.parquet")
    reference = table(two_models)
    assert reference.num_rows == 128
    whole = pq.read_table(two_models)
    assert whole.equals(reference)
    # Group by on the string columns, no unify_dictionaries first.
    groups = whole.group_by(["model", "tau"]).aggregate([("faces", "count")])
    assert {(m, t): n for m, t, n in zip(*(groups.column(c).to_pylist() for c in ("model", "tau", "faces_count")))} \
        == GROUPS


def test_pandas_reads_the_folder_by_name(two_models):
    pd = pytest.importorskip("pandas")
    frame = pd.read_parquet(two_models)
    assert len(frame) == 128
    _check({c: [None if pd.isna(x) else x for x in frame[c].tolist()] for c in DETERMINISTIC},
           {c: table(two_models).column(c).to_pylist() for c in DETERMINISTIC})
    assert frame.groupby(["model", "tau"]).size().to_dict() == GROUPS


def test_polars_reads_the_folder_by_name(two_models):
    pl = pytest.importorskip("polars")
    frame = pl.read_parquet(two_models)
    assert frame.height == 128
    # The job description (no rows) and the set-aside part are not read as rows.
    _check({c: frame[c].to_list() for c in DETERMINISTIC},
           {c: table(two_models).column(c).to_pylist() for c in DETERMINISTIC})
    counts = frame.group_by(["model", "tau"]).len()
    assert dict(zip(zip(counts["model"].to_list(), counts["tau"].to_list()), counts["len"].to_list())) == GROUPS


def test_duckdb_reads_the_folder_by_name(two_models):
    duckdb = pytest.importorskip("duckdb")
    for source in (f"read_parquet('{two_models}')", f"read_parquet('{two_models}/**/*.parquet')"):
        got = duckdb.sql(f"select model, tau, count(*) from {source} group by model, tau").fetchall()
        assert {(m, t): n for m, t, n in got} == GROUPS, source
    rows_ = duckdb.sql(f"select {', '.join(DETERMINISTIC)} from read_parquet('{two_models}/*.parquet', "
                       "filename=true) order by filename, camera").fetchall()
    _check({c: [r[i] for r in rows_] for i, c in enumerate(DETERMINISTIC)},
           {c: table(two_models).column(c).to_pylist() for c in DETERMINISTIC})


def test_the_job_description_and_folders_of_format_1(cow, tmp_path, two_models):
    """The job is read back with read_job; a folder of format pmjax-eval/1
    (its job in _job.json) is refused with the reason, its files untouched."""
    import json

    from pmjax._eval import EvalError, read_job

    job = read_job(two_models)
    assert job["taus"] == [1.0, 4.0] and [os.path.basename(m) for m in job["models"]] == ["cow.pmz", "calf.pmz"]
    assert job["columns"] == table(two_models).schema.names
    old = tmp_path / "old"
    old.mkdir()
    (old / "_job.json").write_text(json.dumps(dict(format="pmjax-eval/1")))
    with pytest.raises(EvalError, match=f"{old} holds a job in format pmjax-eval/1 \\(described by _job.json\\), "
                                        "whose parts lack columns of format pmjax-eval/2; its rows stay readable, "
                                        "but it cannot be resumed: use another folder, or delete this one"):
        evaluate([cow], ["orbit:8"], str(old), taus=[1.0], compile_cache=None, progress=False)
    assert sorted(os.listdir(old)) == [".lock", "_job.json"]
    with pytest.raises(EvalError, match=f"{old}: no _job.parquet, not a pmjax eval dataset folder"):
        read_job(str(old))
