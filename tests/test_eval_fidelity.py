"""Image metrics per camera in evaluation jobs (``fidelity``): the values of
``path_fidelity`` for the same cameras and tolerance, part of the job's
definition, and the same rows when resumed or run on Dask."""

from __future__ import annotations

import numpy as np
import pytest

import pmjax
from pmjax._eval import FIDELITY_COLUMNS, EvalError, camera_set, evaluate

pytest.importorskip("pyarrow")
ds = pytest.importorskip("pyarrow.dataset")
render = pytest.importorskip("pmjax.render")

# Small images keep the renders cheap; the metrics do not depend on the size's scale.
IMAGE = dict(width=96, height=72)
# The columns a camera defines (the others are measured times).
METRICS = ("differing_share", "psnr", "silhouette_share", "flip_mean", "flip_model_mean")
DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
                 "vertices", "executed", *METRICS]


def _renders():
    try:
        with render.Renderer(8, 8):
            pass
    except Exception as exc:  # no headless OpenGL here
        pytest.skip(f"no offscreen rendering: {exc}")


@pytest.fixture(scope="module")
def cow(built, tmp_path_factory):
    _renders()
    path = str(tmp_path_factory.mktemp("models") / "cow.pmz")
    pmjax.save_pm(built("cow.ply"), path)
    return path


def table(folder, columns=None):
    return ds.dataset(folder, format="parquet").to_table(columns)


def _cameras(model, spec, n):
    data = pmjax.read_pm(model)
    return camera_set(spec, **IMAGE).rows(data.vertices[: data.n_original_vertices], 0, n, None).camera()


@pytest.mark.parametrize("spec", ["orbit:5", "random:4:3"])
def test_rows_equal_path_fidelity(cow, tmp_path, spec):
    """Each row's metrics are path_fidelity's for that camera and tau, bit for
    bit (a path set goes through the coherent engine, a random one through
    refine_batch: both give the refinement path_fidelity draws)."""
    n = int(spec.split(":")[1])
    out = str(tmp_path / "out")
    evaluate([cow], [camera_set(spec, **IMAGE)], out, taus=[0.5], chunk=3, compile_cache=None, progress=False,
             fidelity=True)
    rows = table(out)
    assert rows.schema.names[-len(FIDELITY_COLUMNS):] == list(FIDELITY_COLUMNS)
    reference = render.path_fidelity(pmjax.load(cow), _cameras(cow, spec, n), 0.5)
    assert rows.column("faces").to_pylist() == [r["faces"] for r in reference]
    for name in METRICS:
        assert rows.column(name).to_pylist() == [r[name] for r in reference], name
    # Metrics that can fail: the refinement differs from the original on screen
    # (a random view may show the model at a few pixels, or none).
    share = rows.column("differing_share").to_pylist()
    assert all(0 <= x <= 1 for x in share) and max(share) > 0
    assert all(x > 0 for x in rows.column("fidelity_ms").to_pylist() + rows.column("render_ms").to_pylist())


def test_budget_rows_measure_the_refinement_at_their_tau(cow, tmp_path):
    """A budget job's metrics are those of each camera's refinement at the
    tolerance found (its row's tau)."""
    out = str(tmp_path / "out")
    evaluate([cow], [camera_set("random:3:5", **IMAGE)], out, budgets=[800], chunk=3, compile_cache=None,
             progress=False, fidelity=True)
    rows = table(out).to_pylist()
    pm, cams = pmjax.load(cow), _cameras(cow, "random:3:5", 3)
    for i, row in enumerate(rows):
        (reference,) = render.path_fidelity(pm, pmjax.index_camera(cams, np.array([i])), float(row["tau"]))
        assert row["faces"] == reference["faces"] <= 800
        assert [row[k] for k in METRICS] == [reference[k] for k in METRICS]


def test_resume_gives_identical_rows_and_fidelity_defines_the_job(cow, tmp_path):
    """A job stopped after one part and resumed has the rows of an
    uninterrupted one; the same job without the metrics (or with them, into a
    folder without) is refused, naming the setting, and the folder is left as
    it was."""
    job = dict(taus=[1.0], chunk=2, compile_cache=None, progress=False)
    sets = [camera_set("random:5:1", **IMAGE)]
    whole, parts = str(tmp_path / "whole"), str(tmp_path / "parts")
    evaluate([cow], sets, whole, fidelity=True, **job)
    first = evaluate([cow], sets, parts, fidelity=True, max_parts=1, **job)
    rest = evaluate([cow], sets, parts, fidelity=True, **job)
    assert (first.parts_written, rest.parts_written, rest.parts_skipped) == (1, 2, 1)
    assert table(parts, DETERMINISTIC).equals(table(whole, DETERMINISTIC))
    for folder, setting in ((parts, False), (str(tmp_path / "plain"), True)):
        if not setting:
            before = sorted(p.name for p in (tmp_path / "parts").iterdir())
        else:
            evaluate([cow], sets, folder, **job)
        with pytest.raises(EvalError, match=f"fidelity: {not setting} there, {setting} here"):
            evaluate([cow], sets, folder, fidelity=setting, **job)
        if not setting:
            assert sorted(p.name for p in (tmp_path / "parts").iterdir()) == before
    with pytest.raises(EvalError, match="fidelity must be True or False"):
        evaluate([cow], sets, str(tmp_path / "bad"), fidelity="yes", **job)


def test_metrics_of_stored_normals_are_not_resumed_with_view_normals(cow, tmp_path):
    """A folder whose image metrics were written before refinements were
    shaded with normals fitted per view (its job names no normals) is not
    extended by rows shaded the new way: refused, naming both, the folder
    left as it was."""
    import json
    import os

    import pyarrow.parquet as pq

    from pmjax._eval import JOB_FILE, JOB_KEY, read_job

    job = dict(taus=[1.0], chunk=2, compile_cache=None, progress=False)
    sets = [camera_set("random:3:1", **IMAGE)]
    out = str(tmp_path / "out")
    evaluate([cow], sets, out, fidelity=True, max_parts=1, **job)
    described = read_job(out)
    assert described["fidelity_normals"] == "view"
    old = {k: v for k, v in described.items() if k != "fidelity_normals"}
    schema = pq.read_schema(os.path.join(out, JOB_FILE))
    pq.write_table(schema.empty_table().replace_schema_metadata({JOB_KEY: json.dumps(old)}),
                   os.path.join(out, JOB_FILE))
    before = sorted(os.listdir(out))
    with pytest.raises(EvalError, match="fidelity_normals: 'stored' there, 'view' here"):
        evaluate([cow], sets, out, fidelity=True, **job)
    assert sorted(os.listdir(out)) == before


@pytest.mark.slow
def test_dask_gives_identical_rows(cow, tmp_path):
    """Parts rendered on Dask worker processes, or on a local cluster's
    threads (rendering one at a time), give the rows of one process."""
    distributed = pytest.importorskip("dask.distributed")
    job = dict(taus=[1.0], chunk=2, compile_cache=None, progress=False, fidelity=True)
    sets = [camera_set("orbit:4", **IMAGE)]
    here, there = str(tmp_path / "here"), str(tmp_path / "there")
    evaluate([cow], sets, here, **job)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        evaluate([cow], sets, there, scheduler=cluster.scheduler_address, **job)
    assert table(there, DETERMINISTIC).equals(table(here, DETERMINISTIC))
    threads = str(tmp_path / "threads")
    evaluate([cow], sets, threads, workers=2, **job)
    assert table(threads, DETERMINISTIC).equals(table(here, DETERMINISTIC))
