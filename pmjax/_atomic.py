"""Atomic file writes: a temporary file in the target's folder, then rename.

A write to ``dir/name.ext`` goes through ``dir/.name.ext.pmjax-tmp-<pid>-<random>.ext``
and is renamed over the target only when complete, so the target is never
half-written. A process killed mid-write (``kill -9``) leaves its temporary
file; the next write to the same target removes every such file whose
process is gone (:func:`remove_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import os
import tempfile

TEMP_MARK = ".pmjax-tmp-"


def temporary_prefix(path) -> str:
    """Name prefix of the temporary files of writes to ``path``."""
    return f".{os.path.basename(os.fspath(path))}{TEMP_MARK}"


def check_output_path(path, *, folder: bool = False) -> str:
    """Refuse an output path before any work is done; return it.

    The rule for every output: the folder it goes into must exist (nothing
    creates missing parents), and a file output must not name a folder. An
    output that is itself a folder (``folder=True``) may exist or is created,
    but its parent must exist.

    Raises:
        FileNotFoundError: the containing folder does not exist.
        IsADirectoryError / NotADirectoryError: a file where a folder is
            expected, or the reverse.
    """
    path = os.fspath(path)
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise FileNotFoundError(f"{path}: folder {parent} does not exist (create it first)")
    if folder:
        if os.path.exists(path) and not os.path.isdir(path):
            raise NotADirectoryError(f"{path}: exists and is not a folder")
    elif os.path.isdir(path):
        raise IsADirectoryError(f"{path}: is a folder; give a file name")
    return path


def remove_stale_temporaries(path) -> list[str]:
    """Remove the temporary files of earlier writes to ``path`` whose writing
    process no longer runs; return their paths."""
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    prefix = temporary_prefix(path)
    removed = []
    for name in os.listdir(folder):
        if not name.startswith(prefix):
            continue
        pid = name[len(prefix):].split("-", 1)[0]
        if pid.isdigit() and not _running(int(pid)):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(os.path.join(folder, name))
                removed.append(os.path.join(folder, name))
    return removed


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


@contextlib.contextmanager
def atomic_path(path, suffix: str = ""):
    """Yield a temporary path beside ``path``; on success it replaces ``path``,
    on any error it is removed, so ``path`` is never left half-written.

    Raises:
        FileNotFoundError: the folder of ``path`` does not exist (checked
            before anything is written).
    """
    path = check_output_path(path)
    remove_stale_temporaries(path)
    fd, tmp = tempfile.mkstemp(prefix=f"{temporary_prefix(path)}{os.getpid()}-", suffix=suffix,
                               dir=os.path.dirname(os.path.abspath(path)))
    os.close(fd)
    # mkstemp creates 0600; give the result the permissions a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
