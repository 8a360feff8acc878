"""The .pmz format: exact round trip, atomic writes, and a specific error per defect."""

import io
import json
import os
import zipfile

import numpy as np
import pytest

from pmjax._atomic import TEMP_MARK

import pmjax
from pmjax import PMFormatError, read_pm, save_pm


@pytest.fixture
def saved(built, tmp_path):
    pm = built("cow.ply")
    path = tmp_path / "cow.pmz"
    save_pm(pm, path, version=1)  # the zip layout rewrite() edits
    return pm, path


def rewrite(src, dst, *, header=None, arrays=None, drop=()):
    """Copy a .pmz, replacing header fields or arrays (checksums untouched)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for name in zin.namelist():
            if name in drop:
                continue
            data = zin.read(name)
            if name == "header.json" and header:
                h = json.loads(data)
                h.update(header)
                data = json.dumps(h).encode()
            stem = name[:-4]
            if arrays and stem in arrays:
                buf = io.BytesIO()
                np.save(buf, arrays[stem])
                data = buf.getvalue()
            zout.writestr(name, data)


def test_round_trip_is_exact(saved):
    pm, path = saved
    back = read_pm(path)
    for name, a in pm.arrays().items():
        assert np.array_equal(a, getattr(back, name)), name
        assert a.dtype == getattr(back, name).dtype
    assert back.header["build"]["metric"] == "quadric"
    assert not [p for p in os.listdir(path.parent) if TEMP_MARK in p]


def test_truncated_file(saved, tmp_path):
    _, path = saved
    data = path.read_bytes()
    bad = tmp_path / "trunc.pmz"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(PMFormatError, match="trunc.pmz"):
        read_pm(bad)


def test_flipped_byte_fails_the_checksum(saved, tmp_path):
    pm, path = saved
    arrays = {"v1": pm.v1.copy()}
    arrays["v1"][5] ^= 1
    bad = tmp_path / "flip.pmz"
    rewrite(path, bad, arrays=arrays)
    with pytest.raises(PMFormatError, match="checksum mismatch in array 'v1'"):
        read_pm(bad)


def test_forged_file_with_valid_checksums_is_caught_by_validation(saved, tmp_path):
    pm, path = saved
    faces = pm.faces.copy()
    faces[7, 1] = pm.n_original_vertices + 3  # points at a created vertex
    forged = pmjax.PMData(**{**pm.arrays(), "faces": faces}, header=pm.header)
    with pytest.raises(PMFormatError, match="face index out of range"):
        save_pm(forged, tmp_path / "forged.pmz")
    assert not (tmp_path / "forged.pmz").exists()
    # Same forgery written by hand with a matching checksum: read_pm refuses it.
    sums = dict(json.loads(zipfile.ZipFile(path).read("header.json"))["array_sha256"])
    import hashlib

    sums["faces"] = hashlib.sha256(faces.tobytes()).hexdigest()
    rewrite(path, tmp_path / "forged2.pmz", arrays={"faces": faces}, header={"array_sha256": sums})
    with pytest.raises(PMFormatError, match=r"face index out of range \[0, V0\) \(first at index 7\)"):
        read_pm(tmp_path / "forged2.pmz")


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(header={"magic": "something-else"}), "bad magic"),
        (dict(header={"version": 99}), "unsupported format version 99"),
        (dict(drop=("killer.npy",)), "array 'killer' is missing"),
        (dict(drop=("header.json",)), "no header.json"),
        (dict(header={"counts": {"V0": 1, "F": 1, "P": 1, "B": 1}}), "header count"),
    ],
)
def test_each_defect_has_its_own_error(saved, tmp_path, change, message):
    _, path = saved
    bad = tmp_path / "bad.pmz"
    rewrite(path, bad, **change)
    with pytest.raises(PMFormatError, match=message):
        read_pm(bad)


def test_wrong_dtype_and_shape_are_named(built):
    pm = built("cow.ply")
    with pytest.raises(PMFormatError, match="radius has dtype float64"):
        pmjax.validate_pm(pmjax.PMData(**{**pm.arrays(), "radius": pm.radius.astype(np.float64)}))
    with pytest.raises(PMFormatError, match="killer has shape"):
        pmjax.validate_pm(pmjax.PMData(**{**pm.arrays(), "killer": pm.killer[:-1]}))
    v1 = pm.v1.copy()
    v1[3] = v1[4]
    with pytest.raises(PMFormatError, match="consumed by more than one pcol"):
        pmjax.validate_pm(pmjax.PMData(**{**pm.arrays(), "v1": v1}))


def test_not_a_pm_file(tmp_path):
    p = tmp_path / "x.pmz"
    p.write_text("hello")
    with pytest.raises(PMFormatError, match="not a zip archive"):
        read_pm(p)
    with pytest.raises(PMFormatError, match="no such file"):
        read_pm(tmp_path / "none.pmz")
    # A mesh where a .pmz is needed: say so, and how to make one.
    mesh = tmp_path / "mesh.ply"
    mesh.write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(PMFormatError, match=r"is a PLY mesh, not a \.pmz progressive mesh; make one with `pmjax build"):
        read_pm(mesh)
    named = tmp_path / "model.pmz"
    named.write_bytes(b"solid cube\nendsolid\n")  # an ASCII STL, whatever its name
    with pytest.raises(PMFormatError, match="is an STL mesh"):
        read_pm(named)


def test_failed_write_leaves_the_old_file(saved):
    pm, path = saved
    before = path.read_bytes()
    broken = pmjax.PMData(**{**pm.arrays(), "alpha": -pm.alpha - 1}, header=pm.header)
    with pytest.raises(PMFormatError, match="alpha negative"):
        save_pm(broken, path)
    assert path.read_bytes() == before


def test_atomic_writes_get_normal_permissions(tmp_path):
    import os

    from pmjax._atomic import atomic_path

    umask = os.umask(0o022)
    try:
        target = tmp_path / "out.txt"
        with atomic_path(target) as tmp:
            open(tmp, "w").write("x")
        assert (os.stat(target).st_mode & 0o777) == 0o644
    finally:
        os.umask(umask)
