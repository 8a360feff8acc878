"""Forged .pmz files: checksums recomputed, so only the structure check stands
between them and a wrong mesh. Every forgery must be refused on load with an
error naming the file and the element, and the fast check must agree with the
slow replay of check_invariants."""

import hashlib
import io
import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest

import pmjax
from pmjax import PMFormatError, check_structure, read_pm, save_pm


@pytest.fixture(scope="module")
def cow(built, tmp_path_factory):
    pm = built("cow.ply")
    path = tmp_path_factory.mktemp("forged") / "cow.pmz"
    save_pm(pm, path, version=1)  # the zip layout these forgeries edit
    return pm, path


def forge(src, dst, **arrays):
    """Copy a .pmz replacing arrays, with the header's checksums recomputed."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        header = json.loads(zin.read("header.json"))
        for name, a in arrays.items():
            header["array_sha256"][name] = hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()
        for name in zin.namelist():
            data = zin.read(name)
            if name == "header.json":
                data = json.dumps(header).encode()
            elif name[:-4] in arrays:
                buf = io.BytesIO()
                np.save(buf, arrays[name[:-4]])
                data = buf.getvalue()
            zout.writestr(name, data)
    return dst


def _batch_of(pm, p):
    return int(np.searchsorted(pm.batch_offsets, p, side="right") - 1)


def _forgeries(pm):
    """name -> (replaced arrays, expected message)."""
    V0, P = pm.n_original_vertices, pm.n_pcols
    rng = np.random.default_rng(7)
    out = {}
    out["every killer -1"] = (dict(killer=np.full_like(pm.killer, -1)), "killer -1 but two of its corners merge")
    out["every killer 0"] = (dict(killer=np.zeros_like(pm.killer)), "killer's subtree does not hold exactly two")
    killed = np.flatnonzero(pm.killer >= 0)
    k = pm.killer.copy()
    f = int(killed[len(killed) // 2])
    k[f] = (k[f] + 1) % P
    out["one killer off by one"] = (dict(killer=k), f"face {f}")
    # Swap v1 between two pcols of one batch (ranges and consumption stay valid).
    lo, hi = int(pm.batch_offsets[3]), int(pm.batch_offsets[4])
    v1 = pm.v1.copy()
    v1[lo], v1[lo + 1] = v1[lo + 1], v1[lo]
    out["swapped v1 in a batch"] = (dict(v1=v1), "cow.pmz")
    faces = pm.faces.copy()
    faces[11] = faces[4][[2, 0, 1]]
    out["duplicated face"] = (dict(faces=faces), "faces 4 and 11 have the same three vertices")
    faces = pm.faces.copy()
    faces[9, 2] = faces[9, 0]
    out["repeated corner"] = (dict(faces=faces), "face 9 repeats a vertex")
    out["zero radii"] = (dict(radius=np.zeros_like(pm.radius)), "sphere does not contain")
    normals = pm.normals.copy()
    normals[V0 + 5] = 0.0
    out["zero normal"] = (dict(normals=normals), f"vertex {V0 + 5}: normal is not of unit length")
    top = int(np.flatnonzero(pm.v1 >= V0)[-1])  # a pcol with a created child
    for attr in ("delta", "mu"):
        a = getattr(pm, attr).copy()
        a[top] = 0.0
        child = int(pm.v1[top]) - V0
        if getattr(pm, attr)[child] > 0:
            out[f"{attr} below its child"] = ({attr: a}, f"{attr} smaller than its v1 child's")
    alpha = pm.alpha.copy()
    alpha[top] = 0.0
    out["cone narrower than its child"] = (dict(alpha=alpha), f"pcol {top}")
    radius = pm.radius.copy()
    radius[top] *= 0.5
    out["sphere shrunk"] = (dict(radius=radius), f"pcol {top}: sphere does not contain")
    verts = pm.vertices.copy()
    verts[V0 + top] += 0.5 * pm.radius[top]
    out["moved pcol vertex"] = (dict(vertices=verts), "sphere does not contain")
    # A random killer rewrite of many faces.
    k = pm.killer.copy()
    pick = rng.choice(len(k), 50, replace=False)
    k[pick] = rng.integers(-1, P, 50)
    out["random killers"] = (dict(killer=k), "killer")
    return out


def test_every_forgery_is_refused_on_load(cow, tmp_path):
    pm, path = cow
    for name, (arrays, message) in _forgeries(pm).items():
        bad = forge(path, tmp_path / "cow.pmz", **arrays)
        with pytest.raises(PMFormatError) as info:
            pmjax.load(bad)
        assert "cow.pmz" in str(info.value) and message in str(info.value), (name, str(info.value))
        with pytest.raises(PMFormatError):
            read_pm(bad)
        # The slow replay agrees that the forgery is broken.
        forged = pmjax.PMData(**{**pm.arrays(), **arrays})
        with pytest.raises(PMFormatError):
            pmjax.check_invariants(forged)
        # save_pm refuses to write it, and leaves nothing behind.
        with pytest.raises(PMFormatError):
            save_pm(forged, tmp_path / "out.pmz")
        assert not (tmp_path / "out.pmz").exists()


def test_batch_independence_is_checked():
    # Two triangles sharing an edge; one batch of two pcols that both touch
    # triangle 0: (0, 1) and (2, 3).
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0, 0], [0.5, 1, 0]], np.float32)
    normals = np.tile(np.float32([0, 0, 1]), (6, 1))
    pm = pmjax.PMData(
        vertices=vertices, normals=normals, faces=np.array([[0, 1, 2], [1, 3, 2]], np.int32),
        v1=np.array([0, 2], np.int32), v2=np.array([1, 3], np.int32),
        radius=np.full(2, 0.5, np.float32), alpha=np.zeros(2, np.float32),
        delta=np.zeros(2, np.float32), mu=np.zeros(2, np.float32), cost=np.zeros(2),
        metric=np.zeros(2, np.uint8), batch_offsets=np.array([0, 2]), killer=np.array([0, 1], np.int32),
    )
    with pytest.raises(PMFormatError, match="face 0: .*batches not independent"):
        check_structure(pm)
    with pytest.raises(PMFormatError, match="batch 0: pcols 0 and 1 share a face"):
        pmjax.check_invariants(pm)
    # The same two pcols in two batches are a valid hierarchy.
    ok = pmjax.PMData(**{**pm.arrays(), "batch_offsets": np.array([0, 1, 2])})
    check_structure(ok)
    pmjax.check_invariants(ok)


def test_fast_and_slow_checks_agree_on_random_structural_forgeries(built):
    """Single-entry rewrites of killer, v1, v2: the linear check refuses
    exactly the ones the batch-by-batch replay refuses."""
    pm = built("cow.ply")
    rng = np.random.default_rng(3)
    V0, P = pm.n_original_vertices, pm.n_pcols
    refused = accepted = 0
    for trial in range(60):
        arrays = pm.arrays()
        name = ("killer", "v1", "v2")[trial % 3]
        a = arrays[name].copy()
        i = int(rng.integers(len(a)))
        a[i] = rng.integers(-1, P) if name == "killer" else rng.integers(0, V0 + P)
        forged = pmjax.PMData(**{**arrays, name: a})
        try:
            pmjax.validate_pm(forged)
        except PMFormatError:
            continue
        fast = slow = True
        try:
            check_structure(forged)
        except PMFormatError:
            fast = False
        try:
            pmjax.check_invariants(forged)
        except PMFormatError:
            slow = False
        assert fast == slow, (name, i, int(a[i]))
        refused += not fast
        accepted += fast
    assert refused >= 10


@pytest.mark.slow
def test_a_forged_file_fails_the_cli_with_its_name(cow, tmp_path):
    pm, path = cow
    bad = forge(path, tmp_path / "forged.pmz", killer=np.full_like(pm.killer, -1))
    out = subprocess.run([sys.executable, "-m", "pmjax", "lod", str(bad), "--batch", "3", "-o",
                          str(tmp_path / "o.ply")], capture_output=True, text=True)
    assert out.returncode != 0
    assert "forged.pmz" in out.stderr and "killer -1" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr
    assert not (tmp_path / "o.ply").exists()


def test_unknown_compression_method_is_a_format_error(cow, tmp_path):
    _, path = cow
    data = bytearray(path.read_bytes())
    # The compression method of the first central-directory entry (offset 10).
    central = bytes(data).index(b"PK\x01\x02")
    data[central + 10] = 99
    bad = tmp_path / "method.pmz"
    bad.write_bytes(bytes(data))
    with pytest.raises(PMFormatError, match="method.pmz"):
        read_pm(bad)


def test_a_passed_structure_is_remembered_by_content(cow, tmp_path, monkeypatch):
    pm, path = cow
    monkeypatch.setenv("PMJAX_KNOWN_STRUCTURES", str(tmp_path / "known"))
    _, fingerprint = pmjax.read_arrays(path)
    assert not pmjax.structure_known(fingerprint)
    pmjax.load(path)
    assert pmjax.structure_known(fingerprint)
    # A forgery has other bytes, so another fingerprint: still checked.
    bad = forge(path, tmp_path / "cow.pmz", killer=np.zeros_like(pm.killer))
    _, other = pmjax.read_arrays(bad)
    assert other != fingerprint and not pmjax.structure_known(other)
    with pytest.raises(PMFormatError):
        pmjax.load(bad)
    # save_pm checks before writing, so what it wrote is known at once.
    monkeypatch.setenv("PMJAX_KNOWN_STRUCTURES", str(tmp_path / "known2"))
    save_pm(pm, tmp_path / "again.pmz")
    assert pmjax.structure_known(pmjax.read_arrays(tmp_path / "again.pmz")[1])
    monkeypatch.setenv("PMJAX_KNOWN_STRUCTURES", "")
    assert not pmjax.structure_known(fingerprint)


# -- zip bombs: nothing is expanded beyond what the header's counts allow ------


def _bomb(src, dst, name, head, zeros, *, declare=None):
    """Copy a .pmz replacing entry ``name`` by ``head`` followed by ``zeros``
    zero bytes, deflated (a small entry that expands to ``len(head) + zeros``),
    streamed so the test itself never holds the expanded bytes. ``declare``:
    the uncompressed size to write into the zip's headers instead of the true one."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for entry in zin.namelist():
            if entry != name:
                zout.writestr(entry, zin.read(entry))
                continue
            info = zipfile.ZipInfo(name)
            info.compress_type = zipfile.ZIP_DEFLATED
            with zout.open(info, "w") as fh:
                fh.write(head)
                block = bytes(1 << 20)
                for lo in range(0, zeros, len(block)):
                    fh.write(block[: min(len(block), zeros - lo)])
    if declare is not None:
        import struct

        data = bytearray(open(dst, "rb").read())
        with zipfile.ZipFile(dst) as zf:
            local = zf.getinfo(name).header_offset
        struct.pack_into("<I", data, local + 22, declare)  # the local header's uncompressed size
        at = 0
        while (at := data.find(b"PK\x01\x02", at + 1)) >= 0:  # the central directory's
            length = struct.unpack_from("<H", data, at + 28)[0]
            if data[at + 46: at + 46 + length] == name.encode():
                struct.pack_into("<I", data, at + 24, declare)
        open(dst, "wb").write(bytes(data))
    with zipfile.ZipFile(dst) as zf:
        info = zf.getinfo(name)
        assert info.compress_size < 1 << 20 and info.file_size == (declare or len(head) + zeros)
    return dst


def _npy(a):
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def _npy_head(shape, dtype):
    """A .npy header (magic string included) for an array of ``shape`` and ``dtype`` (no data)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, dict(descr=np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                                   fortran_order=False, shape=shape))
    return buf.getvalue()


def _peak_bytes(fn):
    """(the exception ``fn`` raised, the peak of Python allocations during it)."""
    import tracemalloc

    tracemalloc.start()
    try:
        fn()
    except Exception as exc:  # returned for the caller to check
        raised = exc
    else:
        raised = None
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return raised, peak


BOMB = 200 << 20  # bytes an entry expands to


def test_an_entry_declaring_more_than_its_npy_header_needs_is_refused_unread(cow, tmp_path):
    pm, path = cow
    # The true vertices, then 200 MB of zeros; the declared size is the true one.
    head = _npy(pm.vertices)
    bad = _bomb(path, tmp_path / "bomb.pmz", "vertices.npy", head, BOMB)
    raised, peak = _peak_bytes(lambda: read_pm(bad))
    assert isinstance(raised, PMFormatError)
    assert str(raised) == (f"{bad}: array 'vertices' (entry vertices.npy) declares {len(head) + BOMB} bytes "
                           f"uncompressed, but its .npy header (shape {pm.vertices.shape}, float32) needs "
                           f"{len(head)}; the file is damaged or forged")
    assert peak < 32 << 20, peak


def test_an_entry_expanding_past_its_declared_size_is_read_only_to_it(cow, tmp_path):
    pm, path = cow
    head = _npy(pm.normals)
    # Declares the size the .npy header needs; holds 200 MB more.
    bad = _bomb(path, tmp_path / "liar.pmz", "normals.npy", head, BOMB, declare=len(head))
    raised, peak = _peak_bytes(lambda: read_pm(bad))
    assert isinstance(raised, PMFormatError)
    # Read to the declared size, where the entry's CRC (of all its bytes) fails.
    assert str(raised).startswith(f"{bad}: array 'normals' is unreadable (BadZipFile: Bad CRC-32 for file "
                                  "'normals.npy'"), str(raised)
    assert peak < 32 << 20, peak


@pytest.mark.slow
def test_an_honest_but_absurd_array_size_is_refused_by_the_header_counts(cow, tmp_path):
    pm, path = cow
    rows = BOMB // 12  # float32 rows of 3
    head = _npy_head((rows, 3), np.float32)
    bad = _bomb(path, tmp_path / "absurd.pmz", "normals.npy", head, rows * 12)
    raised, peak = _peak_bytes(lambda: read_pm(bad))
    assert isinstance(raised, PMFormatError)
    counts = f"V0={pm.n_original_vertices}, F={len(pm.faces)}, P={pm.n_pcols}, B={pm.n_batches}"
    assert str(raised) == (f"{bad}: array 'normals' (entry normals.npy) has shape ({rows}, 3), but the header "
                           f"counts {counts} give {pm.normals.shape}; the file is damaged or forged")
    assert peak < 32 << 20, peak
    # Header counts forged to match: then the honest arrays disagree with them.
    with zipfile.ZipFile(path) as zin:
        header = json.loads(zin.read("header.json"))
        header["counts"]["V0"] = rows - pm.n_pcols
        counted = tmp_path / "counted.pmz"
        with zipfile.ZipFile(counted, "w") as zout:
            for entry in zin.namelist():
                zout.writestr(entry, json.dumps(header) if entry == "header.json" else zin.read(entry))
    forged = _bomb(counted, tmp_path / "counts.pmz", "normals.npy", head, rows * 12)
    raised, peak = _peak_bytes(lambda: read_pm(forged))
    assert isinstance(raised, PMFormatError)
    counts = f"V0={rows - pm.n_pcols}, F={len(pm.faces)}, P={pm.n_pcols}, B={pm.n_batches}"
    assert str(raised) == (f"{forged}: array 'vertices' (entry vertices.npy) has shape {pm.vertices.shape}, but "
                           f"the header counts {counts} give ({rows}, 3); the file is damaged or forged")
    assert peak < 32 << 20, peak


def test_a_header_json_bomb_and_a_huge_npy_header_are_refused(cow, tmp_path):
    _, path = cow
    with zipfile.ZipFile(path) as zf:
        text = zf.read("header.json")
    bad = _bomb(path, tmp_path / "header.pmz", "header.json", text, 8 << 20)
    with pytest.raises(PMFormatError) as info:
        read_pm(bad)
    assert str(info.value) == (f"{bad}: header.json declares {len(text) + (8 << 20)} bytes, more than the "
                               f"{1 << 20} a header can need; the file is damaged or forged")
    # A .npy header length field of 4 GB (version 2.0) is refused before reading it.
    bad = _bomb(path, tmp_path / "npyhead.pmz", "killer.npy", b"\x93NUMPY\x02\x00\xff\xff\xff\xff", 1 << 20)
    with pytest.raises(PMFormatError, match=r"npyhead.pmz: array 'killer' is unreadable \(ValueError: \.npy header "
                                            r"of 4294967295 bytes \(at most 10000\)\)"):
        read_pm(bad)


def test_fortran_order_arrays_still_load(cow, tmp_path):
    pm, path = cow
    good = forge(path, tmp_path / "fortran.pmz", vertices=np.asfortranarray(pm.vertices),
                 faces=np.asfortranarray(pm.faces))
    back = read_pm(good)
    assert np.array_equal(back.vertices, pm.vertices) and np.array_equal(back.faces, pm.faces)
    assert back.vertices.flags.writeable
