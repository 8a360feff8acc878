"""Evaluation on a Dask cluster started by hand (``dask scheduler`` and
``dask worker`` as separate processes, in other folders), a worker that
cannot read the model files (the client ships the model's bytes), and the
SLURM cluster that ``pmjax.slurm_cluster`` builds (its job script; no SLURM
here to run it)."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

import pmjax
from pmjax._eval import evaluate

pytest.importorskip("pyarrow")
ds = pytest.importorskip("pyarrow.dataset")
distributed = pytest.importorskip("dask.distributed")

DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
                 "vertices", "executed"]


def _hiding(folder) -> list:
    """A command prefix that runs its command with ``folder`` hidden (an
    empty file system mounted over it in a mount namespace of its own): a
    worker machine that does not share the client's files. Empty where
    ``unshare`` cannot do that here."""
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs none {folder} && ls -A {folder}"],
                           capture_output=True, text=True) if shutil.which("unshare") else None
    if probe is None or probe.returncode != 0 or probe.stdout.strip():
        return []
    return ["unshare", "-rm", "sh", "-c", f'mount -t tmpfs none {folder} && exec "$@"', "worker"]


@pytest.mark.slow
def test_scheduler_and_worker_started_by_hand(built, tmp_path):
    """A scheduler and a worker started as their own processes, in folders of
    their own, the worker (where the system allows) unable to see the model
    files: the job's rows equal those of one process, and the worker read
    the model from the bytes the client shipped."""
    models = tmp_path / "models"
    models.mkdir()
    model = str(models / "cow.pmz")
    pmjax.save_pm(built("cow.ply"), model)
    job = dict(taus=[1.0, 0.5], chunk=16, compile_cache=None, progress=False)
    sets = ["random:40:2", "orbit:40"]
    reference = str(tmp_path / "reference")
    evaluate([model], sets, reference, **job)
    for name in ("scheduler-home", "worker-home", "worker-tmp"):
        (tmp_path / name).mkdir()
    scheduler_file = str(tmp_path / "scheduler.json")
    env = dict(os.environ, TMPDIR=str(tmp_path / "worker-tmp"))
    hide = _hiding(str(models))
    procs = []
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                                       "--no-dashboard", "--scheduler-file", scheduler_file],
                                      cwd=tmp_path / "scheduler-home", stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
        for _ in range(600):
            if os.path.exists(scheduler_file):
                break
            time.sleep(0.05)
        procs.append(subprocess.Popen(hide + [sys.executable, "-m", "dask", "worker", "--scheduler-file",
                                              scheduler_file, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                                              "--preload", "pmjax._eval"],
                                      cwd=tmp_path / "worker-home", env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
        with open(scheduler_file) as fh:
            address = json.load(fh)["address"]
        with distributed.Client(address, set_as_default=False, timeout=60) as client:
            client.wait_for_workers(1, timeout=120)
            seen = client.run(os.path.exists, model)
            assert list(seen.values()) == [not hide]
            assert list(client.run(os.getcwd).values()) == [str(tmp_path / "worker-home")]
            out = str(tmp_path / "by-hand")
            summary = evaluate([model], sets, out, scheduler=address, **job)
            assert summary.parts_written == 2 * 2 * 3
            # The model's bytes left the cluster with the job.
            assert list(client.list_datasets()) == []
            assert ds.dataset(out).to_table(DETERMINISTIC).equals(ds.dataset(reference).to_table(DETERMINISTIC))
            if hide:
                # The worker wrote the shipped model into its own temporary folder, by content.
                digest = pmjax._eval.file_sha256(model)
                assert list(client.run(lambda: sorted(os.listdir(
                    os.path.join(os.environ["TMPDIR"], f"pmjax-models-{os.getuid()}")))).values()) == \
                    [[f"{digest}.pmz"]]
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in reversed(procs):
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()


def needs_dask_jobqueue():
    """Skip where dask-jobqueue is not installed, without importing it here
    (importing it sets a SIGINT handler that exits the process)."""
    if importlib.util.find_spec("dask_jobqueue") is None:
        pytest.skip("dask-jobqueue is not installed (pip install 'pmjax[cluster]')")


def test_slurm_cluster_keeps_the_ctrl_c_handler():
    """Building a SLURM cluster leaves the process's SIGINT handler as it was
    (Ctrl-C stays a KeyboardInterrupt)."""
    needs_dask_jobqueue()
    before = signal.getsignal(signal.SIGINT)
    cluster = pmjax.slurm_cluster(cores=1, memory="1GB", scheduler_options=dict(dashboard_address=":0"))
    cluster.close()
    assert signal.getsignal(signal.SIGINT) is before


def test_slurm_cluster_job_script():
    """The batch job that pmjax.slurm_cluster builds: the resources given,
    one worker process with a thread per core, pmjax imported at start; no
    job is submitted (jobs=0)."""
    needs_dask_jobqueue()
    cluster = pmjax.slurm_cluster(cores=8, memory="16GB", walltime="01:30:00", queue="short", account="lab",
                                  job_directives=["--gres=gpu:1"], scheduler_options=dict(dashboard_address=":0"))
    try:
        script = cluster.job_script()
        assert len(cluster.workers) == 0
    finally:
        cluster.close()
    lines = script.splitlines()
    for line in ("#SBATCH -p short", "#SBATCH -A lab", "#SBATCH --cpus-per-task=8", "#SBATCH -t 01:30:00",
                 "#SBATCH --gres=gpu:1", "#SBATCH -n 1"):
        assert line in lines, line
    assert any(line.startswith("#SBATCH --mem=") for line in lines)
    (command,) = [line for line in lines if "dask_worker" in line or "dask worker" in line]
    words = command.split()
    assert words[words.index("--nthreads") + 1] == "8"
    assert "--nworkers" not in words  # one worker process per job
    assert words[words.index("--preload") + 1] == "pmjax._eval"


def test_slurm_needs_cores_and_memory(tmp_path, capsys):
    """Without cores and memory (given or configured) the command is refused
    before any batch job, saying what to give."""
    needs_dask_jobqueue()
    import dask

    from pmjax._cli import main

    with dask.config.set({"jobqueue.slurm.cores": None, "jobqueue.slurm.memory": None}):
        assert main(["eval", "model.pmz", "-o", str(tmp_path / "out"), "--slurm", "2"]) != 0
        with pytest.raises(ValueError, match="cores= and memory="):
            pmjax.slurm_cluster(1, cores=4)
    err = capsys.readouterr().err
    assert "--slurm: a SLURM cluster needs the cores and memory of each job" in err and "--slurm-cores" in err
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="jobs must be a whole number"):
        pmjax.slurm_cluster(-1, cores=1, memory="1GB")
