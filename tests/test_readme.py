"""The README's Use lines run as written, from a checkout with ../shared beside it.

The lines are taken from the README's first ``bash`` block under "## Use" and
run in order in a scratch folder laid out like a checkout (``../shared``
linked beside it), each checked for exit status 0 and for the files it names
with ``-o``/``--csv``/``--stats-json``. ``pmjax view`` needs a display and
runs until closed: it is run under Xvfb with ``--close-after`` appended when
Xvfb is installed, and skipped otherwise. Then the README's Python block runs in the same folder, as a reader would
continue. Durations are printed (``-s -n 0``: in this process).
"""

import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def use_lines() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## Use.*?```bash\n(.*?)```", text, re.S).group(1)
    return [line.split("  #")[0].strip() for line in block.splitlines() if line.strip().startswith("pmjax ")]


def python_block() -> str:
    """The README's first ``python`` block under "## Use" (it follows the bash block)."""
    text = (ROOT / "README.md").read_text()
    return re.search(r"## Use.*?```python\n(.*?)```", text, re.S).group(1)


def outputs(argv: list[str]) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv[:-1]) if a in ("-o", "--output", "--csv", "--stats-json")]


@pytest.mark.skipif(not (SHARED / "data" / "bunny.ply").exists(), reason="needs ../shared/data")
@pytest.mark.slow
def test_every_use_line_runs_as_written(tmp_path):
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    (tmp_path / "shared").symlink_to(SHARED)
    lines = use_lines()
    assert len(lines) >= 10
    env = dict(os.environ, PMJAX_KNOWN_STRUCTURES=str(tmp_path / "known"))
    times = {}
    for line in lines:
        argv = shlex.split(line)
        if argv[1] == "view":
            if not shutil.which("xvfb-run"):
                continue
            command = ["xvfb-run", "-a", sys.executable, "-m", *argv, "--close-after", "3"]
            view_env = {k: v for k, v in env.items() if k != "PYOPENGL_PLATFORM"}
        else:
            command, view_env = [sys.executable, "-m", *argv], env
        t = time.perf_counter()
        r = subprocess.run(command, cwd=checkout, capture_output=True, text=True, env=view_env, timeout=900)
        times[line] = time.perf_counter() - t
        assert r.returncode == 0, f"{line}\n{r.stderr[-2000:]}"
        assert "Traceback" not in r.stderr and "Warning" not in r.stderr, f"{line}\n{r.stderr[-2000:]}"
        for out in outputs(argv):
            assert (checkout / out).exists(), f"{line}: {out} was not written"
    # Then the Python block, in the same folder, as a reader continues.
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", python_block()], cwd=checkout, capture_output=True, text=True, env=env,
                       timeout=900)
    times["the Python block"] = time.perf_counter() - t
    assert r.returncode == 0, f"the README's Python block\n{r.stderr[-2000:]}"
    assert (checkout / "results-api").is_dir()
    for line, seconds in times.items():
        print(f"{seconds:7.1f} s  {line}")
