"""Dask clusters on a batch system for evaluation jobs: SLURM through
dask-jobqueue (the ``cluster`` extra).

Each batch job runs one Dask worker process with one thread per core: a
process loads each model once and compiles (or loads from its persistent
cache) each kernel once for all its threads, where one process per core
would pay that per core (docs/eval.md measures both). The worker imports
pmjax when it starts (``--preload pmjax._eval``), before its first task.
Workers need no shared file system: a model file they cannot read comes
from the client (:func:`pmjax.evaluate` ships its bytes), and the compile
cache is each node's own.
"""

from __future__ import annotations

from typing import Optional, Sequence

# The worker's options added to the job script: pmjax imported at start.
WORKER_PRELOAD = ("--preload", "pmjax._eval")


def slurm_cluster(jobs: int = 0, *, cores: Optional[int] = None, memory: Optional[str] = None,
                  walltime: Optional[str] = None, queue: Optional[str] = None, account: Optional[str] = None,
                  job_directives: Sequence[str] = (), **options):
    """A dask-jobqueue ``SLURMCluster`` for :func:`pmjax.evaluate`, scaled to
    ``jobs`` batch jobs of one worker process each.

    Args:
        jobs: SLURM jobs to submit now (0: none; ``cluster.scale(jobs=N)`` or
            ``cluster.adapt(...)`` later).
        cores: cores per job, the worker's threads (``None``: dask's
            ``jobqueue.slurm.cores`` setting).
        memory: memory per job, e.g. ``"16GB"`` (``None``: ``jobqueue.slurm.memory``).
        walltime: ``HH:MM:SS`` per job (``None``: dask's setting).
        queue, account: SLURM partition and account (``None``: dask's setting).
        job_directives: extra ``#SBATCH`` lines, e.g. ``["--gres=gpu:1"]``.
        **options: passed to ``SLURMCluster`` (``job_script_prologue``,
            ``local_directory``, ``python``, ``interface``, ...).

    Returns:
        The cluster; ``pmjax.evaluate(..., scheduler=cluster.scheduler_address)``
        runs a job on it, ``cluster.close()`` cancels its batch jobs.

    Raises:
        RuntimeError: dask-jobqueue is not installed (``pip install pmjax[cluster]``).
        ValueError: ``jobs`` below 0, or no cores or memory given nor configured.
    """
    SLURMCluster = _slurm_cluster_class()
    import dask

    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 0:
        raise ValueError(f"jobs must be a whole number >= 0, not {jobs!r}")
    cores = cores if cores is not None else dask.config.get("jobqueue.slurm.cores", None)
    memory = memory if memory is not None else dask.config.get("jobqueue.slurm.memory", None)
    if cores is None or memory is None:
        raise ValueError("a SLURM cluster needs the cores and memory of each job: pass cores= and memory= "
                         "(pmjax eval: --slurm-cores, --slurm-memory), or set jobqueue.slurm.cores and "
                         "jobqueue.slurm.memory in dask's configuration (~/.config/dask/jobqueue.yaml)")
    extra = list(options.pop("worker_extra_args", None) or dask.config.get("jobqueue.slurm.worker-extra-args", [])
                 or [])
    given = dict(walltime=walltime, queue=queue, account=account)
    cluster = SLURMCluster(cores=int(cores), processes=1, memory=memory,
                           job_extra_directives=list(job_directives) or None,
                           worker_extra_args=extra + list(WORKER_PRELOAD),
                           **{k: v for k, v in given.items() if v is not None}, **options)
    if jobs:
        cluster.scale(jobs=jobs)
    return cluster


def _slurm_cluster_class():
    """dask-jobqueue's ``SLURMCluster``, imported with the caller's Ctrl-C kept.

    dask-jobqueue sets a SIGINT handler that exits the process when it is
    imported; pmjax keeps the handler the process had, so Ctrl-C during a job
    stays a ``KeyboardInterrupt`` (``pmjax eval`` then says how many parts
    are saved and exits with status 130)."""
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGINT) if main else None
    try:
        from dask_jobqueue import SLURMCluster
    except ImportError as exc:
        raise RuntimeError("a SLURM cluster needs dask-jobqueue: pip install 'pmjax[cluster]' "
                           "(or pip install dask-jobqueue)") from exc
    finally:
        if main and previous is not None:
            signal.signal(signal.SIGINT, previous)
    return SLURMCluster
