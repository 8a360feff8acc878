"""No command destroys a user's file: an output that is an input (by any
spelling, hard link or symbolic link) or another output is refused before any
work; devices and pipes are written in place, never replaced."""

import os
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time

import pytest

import pmjax
from pmjax._atomic import TEMP_MARK, atomic_path
from pmjax._cli import main


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A folder with a mesh, a .pmz built from it and a camera file."""
    folder = tmp_path_factory.mktemp("outputs")
    shutil.copy(pmjax.default_model_path(), folder / "spot.ply")
    assert main(["build", str(folder / "spot.ply"), "-o", str(folder / "spot.pmz"), "-q"]) == 0
    assert main(["camera", "orbit", str(folder / "spot.pmz"), "-n", "4", "-o", str(folder / "cams.json")]) == 0
    assert main(["camera", "look-at", "--eye", "0", "0.5", "3", "--target", "0", "0.5", "0",
                 "-o", str(folder / "cam.json")]) == 0
    return folder


def _snapshot(folder):
    return {p.name: (p.read_bytes(), p.stat().st_ino) for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.mark.parametrize("argv, culprit", [
    (["build", "{d}/spot.ply", "-o", "{d}/spot.ply", "-q"], "input mesh"),
    (["build", "{d}/spot.ply", "-o", "{d}/./spot.ply", "-q"], "input mesh"),
    (["build", "{d}/spot.ply", "-o", "{d}/hard.ply", "-q"], "input mesh"),  # a hard link to the input
    (["build", "{d}/spot.ply", "-o", "{d}/soft.ply", "-q"], "input mesh"),  # a symbolic link to the input
    (["camera", "orbit", "{d}/spot.pmz", "-n", "4", "-o", "{d}/spot.pmz"], "input"),
    (["path", "{d}/spot.pmz", "--orbit", "4", "--csv", "{d}/spot.pmz"], "input"),
    (["path", "{d}/spot.pmz", "--path", "{d}/cams.json", "--csv", "{d}/cams.json"], "--path file"),
    (["refine", "{d}/spot.pmz", "--camera", "{d}/cam.json", "-o", "{d}/v.ply", "--stats-json", "{d}/cam.json"],
     "--camera file"),
    (["refine", "{d}/spot.pmz", "--camera", "{d}/cam.json", "-o", "{d}/v.ply", "--stats-json", "{d}/v.ply"],
     "-o and --stats-json"),
    (["lod", "{d}/spot.pmz", "--batch", "2", "-o", "{d}/spot.pmz"], "input"),
    (["render", "{d}/spot.pmz", "--orbit", "4", "-o", "{d}/spot.pmz"], "input"),
])
def test_an_output_that_is_an_input_or_another_output_is_refused(workspace, argv, culprit, capsys):
    d = workspace
    for name, link in (("hard.ply", os.link), ("soft.ply", os.symlink)):
        if not (d / name).exists():
            link(d / "spot.ply", d / name)
    before = _snapshot(d)
    assert main([a.format(d=d) for a in argv]) == 2
    err = capsys.readouterr().err
    assert culprit in err and ("destroy" in err or "overwrite" in err), err
    assert _snapshot(d) == before  # nothing written, nothing replaced


def test_a_pipe_is_written_in_place(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(open(fifo, "rb").read()))
    reader.start()
    with atomic_path(fifo) as path, open(path, "wb") as fh:
        fh.write(b"frames")
    reader.join(timeout=30)
    assert got == [b"frames"] and stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert os.listdir(tmp_path) == ["pipe"]  # no temporary left beside it


def test_a_symbolic_link_keeps_pointing_at_the_rewritten_file(tmp_path):
    target = tmp_path / "real.json"
    target.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    with atomic_path(link) as path, open(path, "w") as fh:
        fh.write("new")
    assert link.is_symlink() and target.read_text() == "new"


def test_writing_to_dev_null_keeps_the_device(workspace):
    # Only where /dev/null is the character device it should be.
    if not stat.S_ISCHR(os.stat("/dev/null").st_mode):
        pytest.skip("no /dev/null device here")
    assert main(["camera", "orbit", str(workspace / "spot.pmz"), "-n", "4", "-o", "/dev/null"]) in (0, 2)
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def _until(predicate, seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.01)
    return False


def test_sigterm_during_a_frames_render_leaves_nothing(workspace, tmp_path):
    """A PNG-frames render is written into a temporary folder inside the
    frames folder and moved in at the end; SIGTERM mid-render removes the
    temporary, and the folder the render made, and leaves no frames."""
    out = tmp_path / "frames"
    proc = subprocess.Popen([sys.executable, "-m", "pmjax", "render", str(workspace / "spot.pmz"), "--orbit", "400",
                             "-o", str(out), "-q"], stderr=subprocess.PIPE, text=True)
    try:
        # The temporary folder exists as soon as frames are being written.
        started = _until(lambda: out.is_dir() and any(TEMP_MARK in p.name for p in out.iterdir()), 120)
        if not started:
            pytest.skip(f"the render did not start writing: {proc.stderr.read()[-500:] if proc.poll() is not None else ''}")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 143
    finally:
        if proc.poll() is None:
            proc.kill()
    assert list(tmp_path.iterdir()) == []  # no frames folder, no temporary


def test_frames_are_moved_into_an_existing_folder_beside_other_files(workspace, tmp_path):
    out = tmp_path / "frames"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["render", str(workspace / "spot.pmz"), "--orbit", "3", "-o", str(out), "-q"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["frame_00000.png", "frame_00001.png", "frame_00002.png",
                                                     "notes.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["frames"]
