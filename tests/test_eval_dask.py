"""Evaluation on Dask workers that run in another folder than the client:
model paths travel absolute, and an error on a worker names the worker."""

from __future__ import annotations

import os

import pytest

import pmjax
from pmjax._eval import EvalError, evaluate, run_part_on_worker

pytestmark = pytest.mark.slow

pytest.importorskip("pyarrow")
ds = pytest.importorskip("pyarrow.dataset")
distributed = pytest.importorskip("dask.distributed")


def test_workers_in_another_folder(built, tmp_path, monkeypatch):
    models = tmp_path / "models"
    models.mkdir()
    pmjax.save_pm(built("cow.ply"), str(models / "cow.pmz"))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    job = dict(taus=[1.0], chunk=16, compile_cache=None, progress=False)
    reference = str(tmp_path / "reference")
    evaluate([str(models / "cow.pmz")], ["random:48:2"], reference, **job)
    # Worker processes start in `elsewhere` (they keep the folder they were
    # started in); the client then names the model relative to its own folder.
    monkeypatch.chdir(elsewhere)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster, set_as_default=False) as client:
        monkeypatch.chdir(models)
        assert client.run(os.getcwd) == {w: str(elsewhere) for w in client.scheduler_info()["workers"]}
        out = str(tmp_path / "dask")
        summary = evaluate(["cow.pmz"], ["random:48:2"], out, scheduler=cluster.scheduler_address, **job)
        assert summary.parts_written == 3
        columns = ["model", "camera", "faces", "vertices", "executed"]
        assert ds.dataset(out).to_table(columns).equals(ds.dataset(reference).to_table(columns))
        # An error on a worker comes back naming the worker, the part and the model.
        (worker,) = client.scheduler_info()["workers"]
        task = dict(model_path="gone.pmz", model_sha256="0" * 64, part="part-m0000-c0000-v0000-0000000.parquet",
                    compile_cache=None)
        with pytest.raises(EvalError) as info:
            client.submit(run_part_on_worker, task, pure=False).result()
        assert str(info.value) == (f"Dask worker {worker}: part part-m0000-c0000-v0000-0000000.parquet of model "
                                   "gone.pmz: FileNotFoundError: [Errno 2] No such file or directory: 'gone.pmz'")


@pytest.mark.parametrize("values", [dict(taus=[1.0, 0.5]), dict(budgets=[600])])
def test_local_cluster_threads_give_the_rows_of_one_process(built, tmp_path, values):
    """workers=N runs N threads of this process, parts in flight at once on
    one loaded model: the rows of an in-process run, each kernel warmed up
    once (compile_ms on one part's first row per kernel at most)."""
    model = str(tmp_path / "cow.pmz")
    pmjax.save_pm(built("cow.ply"), model)
    small = "budgets" in values
    sets = ["random:12:4"] if small else ["random:200:4", "orbit:96"]
    job = dict(chunk=4 if small else 32, compile_cache=None, progress=False, **values)
    columns = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
               "vertices", "executed"]
    here, threads = str(tmp_path / "here"), str(tmp_path / "threads")
    evaluate([model], sets, here, **job)
    summary = evaluate([model], sets, threads, workers=2, **job)
    assert summary.parts_written == len(ds.dataset(here).files)
    assert ds.dataset(threads).to_table(columns).equals(ds.dataset(here).to_table(columns))
    # The in-process run warmed every kernel this process needs: the threads compile none.
    assert ds.dataset(threads).to_table(["compile_ms"]).column(0).to_pylist() == [0.0] * summary.rows
