"""Shared benchmark helpers: data location, machine description, medians."""

from __future__ import annotations

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
    return (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {numpy.__version__}, "
            f"jax {jax.__version__} ({backend})")


def median_time(fn, repeats: int) -> tuple[float, list[float]]:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times
