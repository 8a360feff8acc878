"""The camera file of SrMesh's benchmark driver (benchmarks/srmesh/cameras.py):
read back as the driver reads it, it gives the pmjax cameras it was written from."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import pmjax

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # after the installed packages
from srmesh.cameras import write_cameras  # noqa: E402


def _read(path):
    rows = [line.split() for line in open(path) if not line.startswith("#")]
    floats = np.asarray([[float(x) for x in r[:12]] for r in rows])
    sizes = np.asarray([[int(x) for x in r[12:]] for r in rows])
    return floats, sizes


def test_orbit_reads_back(tmp_path):
    rng = np.random.default_rng(3)
    cams = pmjax.standard_orbit(rng.normal(size=(50, 3)).astype(np.float32), 24, width=640, height=480)
    path = tmp_path / "orbit.txt"
    assert write_cameras(cams, path) == 24
    floats, sizes = _read(path)
    assert floats.shape == (24, 12)
    eye, look, up = floats[:, 0:3], floats[:, 3:6], floats[:, 6:9]
    rot = np.asarray(cams.rotation, np.float64)
    # float32 values written with 9 digits read back to the same float32.
    np.testing.assert_array_equal(eye.astype(np.float32), np.asarray(cams.eye))
    np.testing.assert_array_equal(up.astype(np.float32), np.asarray(cams.rotation)[:, :, 1])
    # The driver's frame: forward from eye to look-at, up the camera's up column.
    forward = look - eye
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    np.testing.assert_allclose(forward, -rot[:, :, 2], atol=1e-6)
    np.testing.assert_allclose(np.radians(floats[:, 9]).astype(np.float32), np.asarray(cams.fov_y))
    np.testing.assert_array_equal(floats[:, 10:12].astype(np.float32),
                                  np.stack([np.asarray(cams.near), np.asarray(cams.far)], 1))
    np.testing.assert_array_equal(sizes, np.tile([640, 480], (24, 1)))


def test_orthographic_refused(tmp_path):
    cams = pmjax.standard_orbit(np.eye(3, dtype=np.float32), 2)
    ortho = pmjax.Camera(cams.eye, cams.rotation, cams.fov_y, cams.near, cams.far, np.ones(2, np.float32),
                         orthographic=True)
    with pytest.raises(ValueError, match="perspective"):
        write_cameras(ortho, tmp_path / "o.txt")
