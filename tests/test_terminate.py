"""SIGTERM while a command runs: an exit raised where the main thread is,
recorded so that a loop raises it again when Python swallowed the first
(inside a finalizer or a garbage collector's callback)."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from pmjax._terminate import check_terminated, sigterm_exits


def _swallowed_sigterm():
    """SIGTERM delivered and its exit caught, as an 'Exception ignored' would."""
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        signal.getsignal(signal.SIGTERM)  # a bytecode boundary: the handler runs
    except SystemExit as exc:
        return exc.code
    return None


def test_a_swallowed_exit_is_raised_again_and_forgotten_after_the_command():
    before = signal.getsignal(signal.SIGTERM)
    with sigterm_exits():
        check_terminated()  # no signal yet: nothing
        assert _swallowed_sigterm() == 143
        with pytest.raises(SystemExit) as exc:
            check_terminated()
        assert exc.value.code == 143
    assert signal.getsignal(signal.SIGTERM) is before
    check_terminated()  # outside the command: nothing


def test_frames_stop_at_the_frame_after_a_swallowed_exit(tmp_path):
    """write_frames raises the exit before the next frame and leaves no
    output and no temporary."""
    render = pytest.importorskip("pmjax.render")
    written = []

    def frames():
        for i in range(5):
            if i == 2:
                assert _swallowed_sigterm() == 143
            written.append(i)
            yield np.zeros((4, 4, 3), np.uint8)

    out = tmp_path / "frames"
    with sigterm_exits(), pytest.raises(SystemExit):
        render.write_frames(frames(), str(out))
    assert written == [0, 1, 2] and not out.exists() and list(tmp_path.iterdir()) == []
