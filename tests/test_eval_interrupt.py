"""Ctrl-C during ``pmjax eval``: one line saying how many parts are saved and
that the same command resumes, status 130, in this process or on a local
Dask cluster (whose workers get the Ctrl-C too)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest


pytestmark = pytest.mark.slow

pytest.importorskip("pyarrow")


def _parts(folder):
    return sorted(n for n in os.listdir(folder) if n.startswith("part-")) if os.path.isdir(folder) else []


def _group_gone(group, wait=30.0):
    """Whether every process of the process group ``group`` ended (exited
    ones not yet reaped by their new parent count as ended) within ``wait`` s."""
    psutil = pytest.importorskip("psutil")
    deadline = time.time() + wait
    while True:
        alive = []
        for p in psutil.process_iter():
            try:
                if os.getpgid(p.pid) == group and p.status() != psutil.STATUS_ZOMBIE:
                    alive.append(p.pid)
            except (ProcessLookupError, psutil.Error):
                pass
        if not alive or time.time() > deadline:
            return not alive
        time.sleep(0.1)


@pytest.mark.parametrize("workers", [0, 1])
def test_ctrl_c_prints_one_line_and_resumes(cow, tmp_path, workers):
    if workers:
        pytest.importorskip("dask.distributed")
    out = str(tmp_path / "out")
    command = [sys.executable, "-m", "pmjax", "eval", cow, "-o", out, "--random", "20000", "--chunk", "50", "-q",
               "--compile-cache", str(tmp_path / "xla"), "--workers", str(workers)]
    # A session of its own: Ctrl-C in a terminal signals the whole process group.
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None and not _parts(out):
        time.sleep(0.02)
    assert proc.poll() is None, proc.communicate()[0]
    os.killpg(proc.pid, signal.SIGINT)
    text = proc.communicate(timeout=120)[0]
    assert proc.returncode == 130, text
    match = re.fullmatch(r"pmjax eval: interrupted; (\d+) of 400 parts saved in (.+) \((\d+) of 20000 rows\); "
                         r"run the same command to resume\n", text)
    assert match, text
    saved = _parts(out)
    assert int(match[1]) == len(saved) >= 1 and match[2] == out and int(match[3]) == 50 * len(saved)
    # No process of the run is left running: the cluster's workers stopped with it.
    assert _group_gone(proc.pid), "processes of the interrupted run are still running"
    # The same command carries on from the saved parts, in this process.
    resumed = subprocess.run(command[:-2], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{len(saved)} parts found done" in resumed.stdout
