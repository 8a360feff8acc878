"""Shared benchmark helpers: data location, machine description, medians, reports."""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path

DATA = Path(os.environ.get("PMJAX_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def machine() -> str:
    import jax
    import numpy

    cpu = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    backend = jax.default_backend()
    if backend != "cpu":
        backend += ": " + jax.devices()[0].device_kind
    cores = f"{os.cpu_count()} cores"
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    if usable < os.cpu_count():
        cores += f" (pinned to {usable})"
    import pmjax

    if not pmjax.native_available():
        loops = "front engine as JAX kernels"
    elif hasattr(pmjax, "engines"):  # the core behind XLA FFI calls, at the SIMD level in use
        loops = f"front engine as the C core (XLA FFI, {pmjax.engines.simd()})"
    else:  # an older checkout measured for comparison
        loops = "front engine as C loops"
    return (f"{cpu}, {cores}, Python {platform.python_version()}, numpy {numpy.__version__}, "
            f"jax {jax.__version__} ({backend}), {loops}")


def pin_cores(n: int) -> None:
    """Run on the first ``n`` CPUs only (``taskset`` from inside). Must come
    before the first JAX computation: XLA sizes its CPU thread pool and its
    loop partitions from the CPUs the process may use when the backend starts."""
    import jax._src.xla_bridge as xb

    if xb.backends_are_initialized():
        raise RuntimeError("pin_cores must run before the first JAX computation")
    cpus = sorted(os.sched_getaffinity(0))
    if not 1 <= n <= len(cpus):
        raise ValueError(f"--cores must be in 1..{len(cpus)}, got {n}")
    os.sched_setaffinity(0, cpus[:n])


def median_time(fn, repeats: int) -> tuple[float, list[float]]:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times


def alternating_medians(variants: dict, repeats: int, per: int = 1) -> dict:
    """Median milliseconds per item (``per`` items per call) of each variant,
    the variants run in turn within each repeat, so that a slow moment of a
    shared machine falls on all of them alike."""
    times = {k: [] for k in variants}
    for _ in range(repeats):
        for key, fn in variants.items():
            t = time.perf_counter()
            fn()
            times[key].append(1e3 * (time.perf_counter() - t) / per)
    return {k: statistics.median(v) for k, v in times.items()}


def write_json(path, report) -> None:
    """Write a benchmark report as JSON, atomically (never a half-written file)."""
    from pmjax._atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        json.dump(report, fh, indent=1)
