"""Atomic file writes: a temporary file in the target's folder, then rename.

A write to ``dir/name.ext`` goes through ``dir/.name.ext.pmjax-tmp-<pid>-<random>.ext``
and is renamed over the target only when complete, so the target is never
half-written. A process killed mid-write (``kill -9``) leaves its temporary
file; the next write to the same target removes every such file whose
process is gone (:func:`remove_stale_temporaries`). A target that exists and
is not a regular file (a device such as ``/dev/null``, a named pipe) is
written in place: a rename would replace the node itself. A symbolic link is
followed: the file it names is replaced, the link stays.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import stat
import tempfile

TEMP_MARK = ".pmjax-tmp-"
# Errors only a write can cause: whatever file they came from, it was the output.
_WRITE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


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
    if not path:
        raise ValueError("the output path is empty: give a file name")
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise FileNotFoundError(f"{path}: folder {parent} does not exist (create it first)")
    if folder:
        if os.path.exists(path) and not os.path.isdir(path):
            raise NotADirectoryError(f"{path}: exists and is not a folder")
    elif os.path.isdir(path):
        raise IsADirectoryError(f"{path}: is a folder; give a file name")
    return path


def same_file(a, b) -> bool:
    """Whether two paths name one file: the same resolved path, or (both
    existing) the same device and inode (hard links, bind mounts)."""
    a, b = os.fspath(a), os.fspath(b)
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        sa, sb = os.stat(a), os.stat(b)
    except OSError:
        return False
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def is_special(path) -> bool:
    """An existing path that is neither a regular file nor a folder (a
    device, a named pipe, a socket): written in place, never renamed over."""
    try:
        mode = os.stat(os.fspath(path)).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def check_distinct(inputs, outputs) -> None:
    """Refuse, before any work, an output that is one of the inputs or
    another output (compared by resolved path and inode).

    Args:
        inputs, outputs: ``(what, path)`` pairs; ``what`` names the argument
            in the message (``"input mesh"``, ``"--csv"``).

    Raises:
        ValueError: naming both arguments and the remedy.
    """
    outputs = [(what, os.fspath(path)) for what, path in outputs if path is not None]
    inputs = [(what, os.fspath(path)) for what, path in inputs if path is not None]
    for i, (what, path) in enumerate(outputs):
        for other, source in inputs:
            if same_file(path, source):
                raise ValueError(f"{path}: the output ({what}) is the {other} {source}; writing it would destroy "
                                 f"the input: choose another output name")
        if is_special(path):  # /dev/null twice is fine
            continue
        for other, earlier in outputs[:i]:
            if same_file(path, earlier):
                raise ValueError(f"{path}: the outputs {other} and {what} are the same file; one would overwrite "
                                 f"the other: give them different names")


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
            stale = os.path.join(folder, name)
            with contextlib.suppress(FileNotFoundError):
                if os.path.isdir(stale) and not os.path.islink(stale):  # an atomic_folder's
                    shutil.rmtree(stale)
                else:
                    os.unlink(stale)
                removed.append(stale)
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
    on any error it is removed, so ``path`` is never left half-written. A
    device or a pipe is yielded itself (written in place).

    Raises:
        FileNotFoundError: the folder of ``path`` does not exist (checked
            before anything is written).
    """
    path = check_output_path(path)
    if is_special(path):
        # A device or a pipe (``-o /dev/null``): write into it.
        yield path
        return
    if os.path.islink(path):  # replace the file the link names, keep the link
        path = os.path.realpath(path)
    remove_stale_temporaries(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{temporary_prefix(path)}{os.getpid()}-", suffix=suffix,
                                   dir=os.path.dirname(os.path.abspath(path)))
    except OSError as exc:  # a read-only or full file system, no permission
        raise _naming(exc, path) from None
    os.close(fd)
    # mkstemp creates 0600: a file written over keeps its permissions, a new
    # one gets those a plain open() would.
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    os.chmod(tmp, mode)
    try:
        yield tmp
        # On disk before the rename: a crash must leave the old file or the
        # whole new one, never an empty file under the target's name.
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as exc:
        # Errors of the temporary file, and a full disk, name the user's path.
        if tmp in (exc.filename, exc.filename2) or tmp in str(exc) or exc.errno in _WRITE_ERRORS:
            raise _naming(exc, path) from exc
        raise
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _naming(exc: OSError, path: str) -> OSError:
    """``exc`` as an error of writing ``path`` (not of its temporary file)."""
    reason = exc.strerror or str(exc)
    return type(exc)(exc.errno, f"cannot write {path}: {reason}") if exc.errno else OSError(
        f"cannot write {path}: {reason}")


@contextlib.contextmanager
def atomic_folder(folder):
    """Yield a temporary folder inside ``folder`` (created if missing); on
    success its files are moved into ``folder`` (other files kept), on any
    error (or SIGTERM, see :func:`pmjax._cli.main`) it is removed, and
    ``folder`` too where this call created it, so ``folder`` never holds part
    of a set of files (a killed render's frames). The temporary lies inside
    ``folder``, not beside it: the moves stay renames within one file system
    where ``folder`` is a mount point, and its parent need not be writable.
    """
    folder = check_output_path(folder, folder=True)
    created = not os.path.isdir(folder)
    # Names the temporaries inside the folder: .files.pmjax-tmp-<pid>-<random>.
    inner = os.path.join(folder, "files")
    moved = False
    try:
        os.makedirs(folder, exist_ok=True)
        remove_stale_temporaries(inner)
        tmp = tempfile.mkdtemp(prefix=f"{temporary_prefix(inner)}{os.getpid()}-", dir=folder)
    except OSError as exc:
        _remove_if_created(folder, created)
        raise _naming(exc, folder) from None
    try:
        yield tmp
        # On disk before they are moved in (one sync for the whole set, not a
        # flush per file).
        os.sync()
        for name in sorted(os.listdir(tmp)):
            os.replace(os.path.join(tmp, name), os.path.join(folder, name))
        moved = True
    except OSError as exc:
        if tmp in (exc.filename, exc.filename2) or tmp in str(exc) or exc.errno in _WRITE_ERRORS:
            raise _naming(exc, folder) from exc
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if not moved:
            _remove_if_created(folder, created)


def _remove_if_created(folder: str, created: bool) -> None:
    """Remove ``folder`` if this write created it and it is still empty."""
    if created:
        with contextlib.suppress(OSError):
            os.rmdir(folder)
