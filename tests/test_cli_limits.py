"""The command line's own edges: help without JAX, bounded camera counts,
output errors that name the user's path, file names that are not text."""

import errno
import os
import subprocess
import sys
import tempfile

import pytest

from pmjax import _atomic


def _imports_after(argv) -> set:
    """The heavy modules imported by ``pmjax ARGV`` before it exits."""
    code = ("import sys\nfrom pmjax._cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            "print('MODULES', *(m for m in ('jax', 'jaxlib', 'equinox', 'trimesh', 'pyarrow') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120)
    line = [x for x in r.stdout.splitlines() if x.startswith("MODULES")][-1]
    return set(line.split()[1:])


@pytest.mark.parametrize("argv", [["--help"], ["refine", "--help"], ["refine"], ["build", "x.ply", "--pair-distance",
                                                                               "-1", "-o", "x.pmz"]])
def test_help_and_argument_errors_import_no_jax(argv):
    """They come from the parser alone: no JAX start-up before them."""
    assert _imports_after(argv) == set()


def test_import_pmjax_is_light_until_a_name_is_used():
    code = ("import sys, pmjax\nbefore = 'jax' in sys.modules\npmjax.refine\n"
            "print(before, 'jax' in sys.modules, sorted(set(pmjax.__all__) - set(dir(pmjax))))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.stdout.split("\n")[0] == "False True []", r.stderr


def test_camera_counts_are_bounded_with_the_remedy():
    r = subprocess.run([sys.executable, "-m", "pmjax", "path", "m.pmz", "--orbit", "1000000000", "--csv", "p.csv"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "--orbit: 1000000000 is out of range (must be >= 1 and <= 1,000,000); pmjax eval streams" in r.stderr


def test_an_empty_output_path_is_refused():
    with pytest.raises(ValueError, match="the output path is empty"):
        _atomic.check_output_path("")


def test_a_full_disk_names_the_users_file_and_leaves_nothing(tmp_path):
    target = tmp_path / "out.ply"
    with pytest.raises(OSError, match=rf"cannot write {target}: No space left on device") as info:
        with _atomic.atomic_path(target) as tmp:
            with open(tmp, "w") as fh:
                fh.write("partial")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert info.value.errno == errno.ENOSPC
    assert os.listdir(tmp_path) == []


def test_a_read_only_folder_names_the_users_file(tmp_path, monkeypatch):
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", os.path.join(str(tmp_path), ".out.ply.pmjax-tmp-1"))

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    target = tmp_path / "out.ply"
    with pytest.raises(OSError, match=rf"cannot write {target}: Read-only file system") as info:
        with _atomic.atomic_path(target):
            pass
    assert ".pmjax-tmp-" not in str(info.value)


def test_a_file_name_that_is_not_text(tmp_path):
    """Bytes that do not decode in the locale: written, and printed escaped."""
    name = os.path.join(os.fsencode(tmp_path), b"cam\xff.json")
    env = dict(os.environ, LC_ALL="C")
    r = subprocess.run([sys.executable, "-m", "pmjax", "camera", "look-at", "--eye", "0", "0", "1", "--target", "0",
                        "0", "0", "-o", name], capture_output=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr.decode(errors="replace")
    assert os.path.exists(name)
    assert b"Traceback" not in r.stderr
