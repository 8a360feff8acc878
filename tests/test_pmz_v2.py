"""The version 2 .pmz: exact round trips, coarse-first prefixes, streaming, and damage refused."""

import io
import json
import os
from pathlib import Path

import numpy as np
import pytest

import pmjax
from pmjax import PMFormatError, read_arrays, read_pm, save_pm
from pmjax._replay import lod_mesh

V1_FIXTURE = Path(__file__).parent / "data" / "cow_v1.pmz"


def chunk_table(path):
    """``[(name, start, end)]`` of a version 2 file's chunks (bytes)."""
    with open(path, "rb") as fh:
        fh.read(8)
        length = int.from_bytes(fh.read(4), "little")
        header = json.loads(fh.read(length))
    at, out = 12 + length, []
    for name, size, _ in header["chunks"]:
        out.append((name, at, at + 32 + size))
        at += 32 + size
    return out


@pytest.fixture(scope="module")
def cow(built, tmp_path_factory):
    pm = built("cow.ply")
    path = tmp_path_factory.mktemp("v2") / "cow.pmz"
    save_pm(pm, path)
    return pm, path


@pytest.mark.parametrize("codec", ["zstd", "zlib"])
def test_round_trip_is_bit_identical_and_smaller(built, tmp_path, codec, assert_same_pm):
    if codec == "zstd":
        pytest.importorskip("zstandard")
    pm = built("cow.ply")
    v1, v2 = tmp_path / "v1.pmz", tmp_path / "v2.pmz"
    save_pm(pm, v1, version=1)
    save_pm(pm, v2, codec=codec)
    assert v2.read_bytes()[:8] == b"\x89PMZ\r\n\x1a\n"
    assert_same_pm(read_pm(v2), pm)
    assert_same_pm(read_pm(v2), read_pm(v1))
    assert pm.shading_normals is not None and "shading_normals" in read_pm(v2).arrays()
    assert os.path.getsize(v2) < 0.7 * os.path.getsize(v1)
    # Same content, same fingerprint, whatever the version.
    assert read_arrays(v1)[1] == read_arrays(v2)[1]


def test_version_1_fixture_reads_and_re_saves_exactly(tmp_path, assert_same_pm):
    old = read_pm(V1_FIXTURE)
    assert old.header["version"] == 1
    path = tmp_path / "cow.pmz"
    save_pm(old, path)
    assert_same_pm(read_pm(path), old)
    # Prefixes of a version 1 file: the same hierarchy as the version 2 file's.
    for k in (0, 1, old.n_batches // 2, old.n_batches):
        assert_same_pm(read_pm(V1_FIXTURE, batches=k), read_pm(path, batches=k))


def oriented(vertices, faces):
    """A mesh's triangles as a sorted array of their corners' coordinates,
    each triangle rotated to start at its smallest corner (orientation kept)."""
    tri = vertices[faces]  # [m, 3, 3]
    keys = [tuple(map(tuple, t)) for t in tri]
    out = []
    for t in keys:
        i = min(range(3), key=lambda j: t[j])
        out.append(t[i:] + t[:i])
    return sorted(out)


def test_every_batch_boundary_gives_the_lod_there(cow, same_bits):
    pm, path = cow
    B = pm.n_batches
    for k in range(B + 1):
        prefix = read_pm(path, batches=k)  # validated and structure-checked
        full = dict(V0=pm.n_original_vertices, F=len(pm.faces), P=pm.n_pcols, B=B)
        assert prefix.n_batches == k and prefix.header["prefix"] == dict(batches=k, of=B, full_counts=full)
        lo = int(pm.batch_offsets[B - k])
        # Its pcols are the full hierarchy's last k batches, attributes bit for bit.
        for name in ("radius", "alpha", "delta", "mu", "cost", "metric"):
            assert same_bits(getattr(prefix, name), getattr(pm, name)[lo:]), name
        assert same_bits(prefix.vertices[prefix.n_original_vertices:], pm.vertices[pm.n_original_vertices + lo:])
        assert same_bits(prefix.normals[prefix.n_original_vertices:], pm.normals[pm.n_original_vertices + lo:])
        np.testing.assert_array_equal(prefix.batch_offsets, pm.batch_offsets[B - k:] - lo)
        # Its original mesh is the full hierarchy's LOD after batches 0 .. B-1-k,
        # and each of its LODs is the full one's at the same batch.
        for j in sorted({-1, k // 2 - 1, k - 1}):
            if j < -1 or j >= k:
                continue
            pv, pf, _ = lod_mesh(prefix, j)
            fv, ff, _ = lod_mesh(pm, B - k + j)
            assert oriented(pv, pf) == oriented(fv, ff), (k, j)


def test_a_prefix_refines(cow):
    pm, path = cow
    full = pmjax.load(path)
    centre = pm.vertices.mean(axis=0)
    cam = pmjax.look_at(centre + [0, 0, 3.0], centre)
    everything = pmjax.Tests(frustum=False, orientation=False)
    B = pm.n_batches
    for k in (0, 1, B // 2, B):
        prefix = pmjax.load(path, batches=k)
        lod = lod_mesh(pm, B - 1 - k)[1] if k < B else pm.faces
        # Fully refined: the prefix's finest mesh; not refined: the base mesh.
        assert int(pmjax.refine(prefix, cam, 0.0, tests=everything).n_faces) == len(lod)
        assert int(pmjax.refine(prefix, cam, 1e30).n_faces) == int(pmjax.refine(full, cam, 1e30).n_faces)


def test_a_stream_is_read_to_the_batch_asked(cow, assert_same_pm):
    pm, path = cow
    table = chunk_table(path)
    data = path.read_bytes()
    B = pm.n_batches
    for k in range(B + 1):
        # Exactly the bytes of the base chunk and k batch chunks suffice.
        prefix = io.BytesIO(data[:table[k][2]])
        assert_same_pm(read_pm(prefix, batches=k), read_pm(path, batches=k))
    assert_same_pm(read_pm(io.BytesIO(data)), pm)
    with open(path, "rb") as fh:
        assert_same_pm(read_pm(fh), pm)


def test_a_truncated_file_is_refused_or_read_as_its_whole_prefix(cow, tmp_path, assert_same_pm):
    pm, path = cow
    table = chunk_table(path)
    data = path.read_bytes()
    name, start, end = table[3]  # the third batch chunk
    cut = tmp_path / "cut.pmz"
    cut.write_bytes(data[:(start + end) // 2])
    with pytest.raises(PMFormatError, match=rf"cut.pmz: truncated in chunk '{name}' \(bytes {start} to {end}; the "
                                            rf"file ends at byte {(start + end) // 2}\): its base mesh and 2 coarsest "
                                            r"batches are whole; pmjax.load\(path, batches=2\) reads them"):
        read_pm(cut)
    assert_same_pm(read_pm(cut, batches=2), read_pm(path, batches=2))
    cut.write_bytes(data[:table[0][2] - 1])
    with pytest.raises(PMFormatError, match="truncated in chunk 'base'.*not even its base mesh is whole"):
        read_pm(cut, batches=0)
    cut.write_bytes(data[:20])
    with pytest.raises(PMFormatError, match="truncated in its header"):
        read_pm(cut)
    with pytest.raises(PMFormatError, match=f"batches=99, but the file has {pm.n_batches} batches"):
        read_pm(path, batches=99)


def test_a_damaged_chunk_is_named(cow, tmp_path, assert_same_pm):
    pm, path = cow
    table = chunk_table(path)
    data = bytearray(path.read_bytes())
    name, start, end = table[-2]  # batch 0, the finest
    data[(start + end) // 2] ^= 0x10
    bad = tmp_path / "bad.pmz"
    bad.write_bytes(bytes(data))
    with pytest.raises(PMFormatError, match=rf"bad.pmz: chunk '{name}' \(bytes {start} to {end}\) fails its SHA-256"):
        read_pm(bad)
    # A prefix that stops before the damage still reads.
    assert_same_pm(read_pm(bad, batches=pm.n_batches - 1), read_pm(path, batches=pm.n_batches - 1))


def test_forged_header_sizes_are_refused_before_reading(cow, tmp_path):
    _, path = cow
    data = path.read_bytes()
    length = int.from_bytes(data[8:12], "little")
    header = json.loads(data[12:12 + length])
    header["chunks"][1][2] = 1 << 40  # a chunk that would expand to a terabyte
    text = json.dumps(header).encode()
    bad = tmp_path / "bomb.pmz"
    bad.write_bytes(data[:8] + len(text).to_bytes(4, "little") + text + data[12 + length:])
    with pytest.raises(PMFormatError, match=r"bomb.pmz: header chunk 'batch \d+' declares 1099511627776 bytes "
                                            "expanded, more than the"):
        read_pm(bad)


def test_bad_arguments():
    with pytest.raises(ValueError, match="save_pm: version must be one of"):
        save_pm(None, "x.pmz", version=3)
    with pytest.raises(ValueError, match="^read_pm: batches must be a whole number >= 0"):
        read_pm(V1_FIXTURE, batches=-1)
    with pytest.raises(ValueError, match="^load: batches must be a whole number >= 0"):
        pmjax.load(V1_FIXTURE, batches=-1)


def test_a_prefix_without_faces_is_refused_with_the_first_that_has_some(tmp_path):
    # A hierarchy whose base mesh has no faces: a terrain collapses to nothing.
    from pmjax.builders import build_pm

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float64)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    pm = build_pm(v, f)
    assert (pm.killer >= 0).all()
    path = tmp_path / "square.pmz"
    save_pm(pm, path)
    total = np.cumsum([0, *np.bincount(np.searchsorted(pm.batch_offsets, pm.killer, side="right") - 1,
                                       minlength=pm.n_batches)[::-1]])
    first = int(np.argmax(total > 0))
    for source in (path, io.BytesIO(path.read_bytes())):
        with pytest.raises(PMFormatError, match=rf"batches=0 gives a mesh with no faces \(the base mesh has none\); "
                                                rf"batches={first} is the first prefix with faces"):
            read_pm(source, batches=0)
    assert read_pm(path, batches=first).n_batches == first


class Trickle(io.RawIOBase):
    """A stream that returns at most ``step`` bytes a read, as a pipe or a
    socket returns what has arrived."""

    def __init__(self, data, step):
        self.data, self.at, self.step = data, 0, step

    def readable(self):
        return True

    def readinto(self, out):
        n = min(len(out), self.step, len(self.data) - self.at)
        out[:n] = self.data[self.at:self.at + n]
        self.at += n
        return n


def test_a_stream_returning_short_reads_is_read_whole(cow, assert_same_pm):
    # Each read of the header and of the chunks is repeated until it has
    # its bytes or the stream ends: a short read is not a truncation.
    pm, path = cow
    data = path.read_bytes()
    assert_same_pm(read_pm(Trickle(data, 1000)), pm)
    assert_same_pm(read_pm(Trickle(data, 7), batches=2), read_pm(path, batches=2))
    table = chunk_table(path)
    name, start, end = table[3]
    with pytest.raises(PMFormatError, match=rf"truncated in chunk '{name}' \(bytes {start} to {end}; the file ends at "
                                            rf"byte {start + 40}\)"):
        read_pm(Trickle(data[:start + 40], 1000))


def test_a_path_and_its_file_object_read_the_same(cow, assert_same_pm):
    # A path is read by position (each chunk on the thread that expands it),
    # a file object by its read(): the same arrays.
    pm, path = cow
    assert_same_pm(read_pm(path), pm)
    with open(path, "rb") as fh:
        assert_same_pm(read_pm(fh), pm)
    assert_same_pm(read_pm(path, batches=2), read_pm(io.BytesIO(path.read_bytes()), batches=2))


def _forge_chunk(path, out, index, payload):
    """A copy of version 2 file ``path`` at ``out`` with chunk ``index``'s
    compressed bytes replaced by ``payload`` (its SHA-256 and size updated)."""
    data = path.read_bytes()
    length = int.from_bytes(data[8:12], "little")
    header = json.loads(data[12:12 + length])
    at, chunks = 12 + length, []
    for _, size, _ in header["chunks"]:
        chunks.append(data[at + 32:at + 32 + size])
        at += 32 + size
    chunks[index] = payload
    header["chunks"][index][1] = len(payload)
    text = json.dumps(header).encode()
    out.write_bytes(data[:8] + len(text).to_bytes(4, "little") + text
                    + b"".join(pmjax._codec.chunk_sha(c) + c for c in chunks))
    return header


@pytest.mark.parametrize("codec", ["zstd", "zlib"])
def test_a_chunk_the_decompressor_refuses_is_named(cow, tmp_path, codec):
    # Bytes with a right SHA-256 that the decompressor cannot expand (a zstd
    # frame asking for a dictionary, a zlib stream with a bad header check).
    if codec == "zstd":
        pytest.importorskip("zstandard")
    pm, path = cow
    own = tmp_path / "own.pmz"
    save_pm(pm, own, codec=codec)
    garbage = b"\x28\xb5\x2f\xfd" + b"garbage-garbage" if codec == "zstd" else b"\x78\x9d" + b"garbage-garbage"
    bad = tmp_path / "forged.pmz"
    header = _forge_chunk(own, bad, 1, garbage)
    name = header["chunks"][1][0]
    with pytest.raises(PMFormatError, match=rf"forged.pmz: chunk '{name}' \(bytes \d+ to \d+\) is damaged: its "
                                            rf"{codec} stream is damaged"):
        read_pm(bad)


@pytest.mark.parametrize("field, value, words", [
    ("encoding", 2.0, "header encoding=2.0 is not one this pmjax reads"),
    ("shading_normals", None, "header shading_normals=None is not true or false"),
    ("shading_normals", 1, "header shading_normals=1 is not true or false"),
    ("codec", ["zstd"], "header codec \\['zstd'\\] is not zstd or zlib"),
    ("roots", 3.0, "header roots=3.0 is not a vertex count"),
    ("group_faces", "many", "header group_faces is not"),
    ("batch_offsets", None, "header batch_offsets is not"),
])
def test_a_header_field_of_the_wrong_type_is_named(cow, tmp_path, field, value, words):
    _, path = cow
    bad = tmp_path / "field.pmz"
    if value is None:
        data = path.read_bytes()
        length = int.from_bytes(data[8:12], "little")
        header = json.loads(data[12:12 + length])
        del header[field]
        text = json.dumps(header).encode()
        bad.write_bytes(data[:8] + len(text).to_bytes(4, "little") + text + data[12 + length:])
    else:
        _with_header(path, bad, **{field: value})
    for batches in (None, 1):
        with pytest.raises(PMFormatError, match=f"field.pmz: {words}"):
            read_pm(bad, batches=batches)


def _huge_header(V0, chunks):
    header = dict(magic="pmjax.progressive-mesh", version=2, counts=dict(V0=V0, F=1, P=0, B=0), array_sha256={},
                  codec="zlib", encoding=2, roots=V0, batch_offsets=[0], group_faces=[1], shading_normals=False,
                  chunks=chunks)
    text = json.dumps(header).encode()
    return pmjax._codec.MAGIC2 + len(text).to_bytes(4, "little") + text


def test_counts_the_file_cannot_hold_are_refused_before_allocating(tmp_path, monkeypatch):
    # A header of a few hundred bytes claiming 2**36 original vertices: its
    # arrays would take a terabyte.
    def allocate(*args, **kwargs):
        raise AssertionError("allocated the arrays of a forged header's counts")

    monkeypatch.setattr(pmjax._codec, "new_stream", allocate)
    V0 = 1 << 36
    bad = tmp_path / "huge.pmz"
    # The chunks declare too few bytes for the counts: refused from a file or a stream.
    bad.write_bytes(_huge_header(V0, [["base", 10, 100], ["tail", 10, 100]]))
    for source in (bad, io.BytesIO(bad.read_bytes())):
        with pytest.raises(PMFormatError, match=r"header chunks declare 200 bytes expanded, fewer than the "
                                                rf"{12 + 12 * V0} its counts V0={V0}, F=1, P=0 store"):
            read_pm(source)
    # Sizes consistent with the counts, but the file lacks the chunks.
    head = _huge_header(V0, [["base", 10, 20 * V0 + 12], ["tail", 10, 13 * V0 + 1]])
    bad.write_bytes(head + bytes(50))
    with pytest.raises(PMFormatError, match=rf"huge.pmz: truncated in chunk 'tail' \(bytes {len(head) + 42} to "
                                            rf"{len(head) + 84}; the file ends at byte {len(head) + 50}\)"):
        read_pm(bad)


def test_counts_beyond_the_memory_free_name_the_file(cow, monkeypatch):
    _, path = cow

    def allocate(*args, **kwargs):
        raise MemoryError("Unable to allocate")

    monkeypatch.setattr(pmjax._codec, "new_stream", allocate)
    with pytest.raises(MemoryError, match=r"cow.pmz: its counts V0=\d+, P=\d+ need more memory than is free here"):
        read_pm(path)


def test_a_file_without_faces_is_refused_in_plain_words():
    from pmjax._pmfile import _check_batches

    for batches, B, groups in ((0, 0, [0]), (1, 2, [0, 0, 0])):
        with pytest.raises(PMFormatError, match=r"x.pmz: the file holds no faces \(F=0\): no prefix of it is a mesh"):
            _check_batches("x.pmz", batches, B, groups)


def _with_header(path, out, **changes):
    """A copy of version 2 file ``path`` at ``out`` with header fields replaced."""
    data = path.read_bytes()
    length = int.from_bytes(data[8:12], "little")
    header = {**json.loads(data[12:12 + length]), **changes}
    text = json.dumps(header).encode()
    out.write_bytes(data[:8] + len(text).to_bytes(4, "little") + text + data[12 + length:])
    return header


@pytest.mark.parametrize("name", ["vertices", "faces", "normals"])
def test_decoded_arrays_are_checked_against_their_checksums(cow, tmp_path, name):
    # The arrays final after the batches, after the faces' placing and after
    # the normals' decoding are each checked.
    _, path = cow
    data = path.read_bytes()
    sums = json.loads(data[12:12 + int.from_bytes(data[8:12], "little")])["array_sha256"]
    bad = tmp_path / "sums.pmz"
    _with_header(path, bad, array_sha256={**sums, name: "0" * 64})
    with pytest.raises(PMFormatError, match=rf"sums.pmz: checksum mismatch in array '{name}'"):
        read_pm(bad)


def test_a_checksum_failure_is_named_before_a_broken_rule(cow, tmp_path, monkeypatch):
    # Content that breaks a rule of validate_pm (an unknown metric id),
    # written with the writer's checks off: refused by the rule, or by a
    # checksum first when one fails as well.
    pm, _ = cow
    metric = np.array(pm.metric)
    metric[0] = 250
    broken = pmjax.PMData(**{**pm.arrays(), "metric": metric}, header=pm.header)
    path = tmp_path / "rule.pmz"
    with monkeypatch.context() as m:
        m.setattr(pmjax._pmfile, "validate_pm", lambda *a, **k: None)
        m.setattr(pmjax._pmfile, "check_structure", lambda *a, **k: None)
        save_pm(broken, path)
    with pytest.raises(PMFormatError, match=r"rule.pmz: unknown metric id \(first at index 0\)"):
        read_pm(path)
    data = path.read_bytes()
    sums = json.loads(data[12:12 + int.from_bytes(data[8:12], "little")])["array_sha256"]
    bad = tmp_path / "both.pmz"
    _with_header(path, bad, array_sha256={**sums, "radius": "0" * 64})
    with pytest.raises(PMFormatError, match=r"both.pmz: checksum mismatch in array 'radius'"):
        read_pm(bad)


def test_a_file_cut_at_any_chunk_boundary_is_refused_or_read_as_the_prefix_it_holds(cow, tmp_path,
                                                                                       assert_same_pm):
    pm, path = cow
    data = path.read_bytes()
    cut = tmp_path / "cut.pmz"
    for i, (name, start, end) in enumerate(chunk_table(path)):
        # At the chunk's start, after its digest, and one byte short of its end.
        for at in (start, start + 32, end - 1):
            cut.write_bytes(data[:at])
            with pytest.raises(PMFormatError, match=rf"cut.pmz: truncated in chunk '{name}' \(bytes {start} to {end}; "
                                                    rf"the file ends at byte {at}\)"):
                read_pm(cut)
            if i:
                # The whole chunks before the cut read as the prefix they hold.
                assert_same_pm(read_pm(cut, batches=i - 1), read_pm(path, batches=i - 1))


def test_a_recorded_decoding_skips_the_array_checks_of_those_bytes_only(cow, tmp_path, monkeypatch,
                                                                         assert_same_pm):
    pm, path = cow
    monkeypatch.setenv("PMJAX_KNOWN_STRUCTURES", str(tmp_path / "known"))
    hashed = []
    sha256 = pmjax._pmfile._sha256
    monkeypatch.setattr(pmjax._pmfile, "_sha256", lambda a: hashed.append(a.shape) or sha256(a))
    first, fingerprint = read_arrays(path)
    assert len(hashed) == len(pm.arrays())
    # The same bytes by the same decoder: the arrays are not hashed again,
    # and the fingerprint is the content's, as version 1's.
    hashed.clear()
    again, same = read_arrays(path)
    assert not hashed and same == fingerprint
    assert_same_pm(again, pm)
    v1 = tmp_path / "v1.pmz"
    save_pm(pm, v1, version=1)
    assert read_arrays(v1)[1] == fingerprint
    # Other bytes (a forged checksum in the header) are checked, and refused each time.
    data = path.read_bytes()
    sums = json.loads(data[12:12 + int.from_bytes(data[8:12], "little")])["array_sha256"]
    bad = tmp_path / "sums.pmz"
    _with_header(path, bad, array_sha256={**sums, "faces": "0" * 64})
    for _ in range(2):
        with pytest.raises(PMFormatError, match=r"sums.pmz: checksum mismatch in array 'faces'"):
            read_arrays(bad)
    # The reader's identity is the code this process imported: a module file
    # gone from disk since changes nothing (the record still counts).
    with monkeypatch.context() as m:
        m.setattr(pmjax._pmdata, "__file__", str(tmp_path / "gone.py"))
        assert pmjax._pmfile.reader_identity() is None
        hashed.clear()
        assert read_arrays(path)[1] == fingerprint and not hashed
    # Another reader (a new decoder version, the NumPy steps, another NumPy,
    # other check code), or a damaged record: checked again.
    (tmp_path / "_pmdata.py").write_bytes(Path(pmjax._pmdata.__file__).read_bytes() + b"\n")
    for change in ("version", "numpy steps", "numpy version", "check code", "record"):
        with monkeypatch.context() as m:
            if change == "version":
                m.setattr(pmjax._codec, "DECODER_VERSION", pmjax._codec.DECODER_VERSION + 1)
            elif change == "numpy steps":
                m.setattr(pmjax._codec, "native", None)
            elif change == "numpy version":
                m.setattr(np, "__version__", np.__version__ + ".post1")
            elif change == "check code":
                m.setattr(pmjax._pmdata, "__file__", str(tmp_path / "_pmdata.py"))
            else:
                for record in (tmp_path / "known").glob("*.decoded"):
                    record.write_text("not a fingerprint")
            identity = pmjax._pmfile.reader_identity()
            assert identity is not None
            assert (identity == pmjax._pmfile.READER_IDENTITY) == (change == "record"), change
            m.setattr(pmjax._pmfile, "READER_IDENTITY", identity)
            hashed.clear()
            assert read_arrays(path)[1] == fingerprint and len(hashed) == len(pm.arrays()), change
            # The new reader's decoding is recorded under its own key.
            hashed.clear()
            assert read_arrays(path)[1] == fingerprint and not hashed, change


def test_without_a_reader_identity_no_decoding_is_recorded_or_used(cow, tmp_path, monkeypatch):
    pm, path = cow
    known = tmp_path / "known"
    monkeypatch.setenv("PMJAX_KNOWN_STRUCTURES", str(known))
    read_arrays(path)
    assert len(list(known.glob("*.decoded"))) == 1
    assert not [p.name for p in known.iterdir() if "tmp" in p.name]  # written whole, then renamed
    monkeypatch.setattr(pmjax._pmfile, "READER_IDENTITY", None)
    hashed = []
    sha256 = pmjax._pmfile._sha256
    monkeypatch.setattr(pmjax._pmfile, "_sha256", lambda a: hashed.append(a.shape) or sha256(a))
    records = sorted(known.glob("*.decoded"))
    for _ in range(2):
        hashed.clear()
        read_arrays(path)
        assert len(hashed) == len(pm.arrays())
    assert sorted(known.glob("*.decoded")) == records


def test_a_file_read_from_a_pipe_is_not_compared_as_a_file(cow, assert_same_pm):
    # A pipe's writer may change its times as it writes, and its bytes are
    # copied as they are read: only a regular file's state is compared. The
    # file is larger than a pipe's buffer, so the writer writes while the
    # reader reads.
    import threading

    pm, path = cow
    read, write = os.pipe()
    writer = threading.Thread(target=_write_all, args=(write, path.read_bytes()))
    writer.start()
    try:
        with os.fdopen(read, "rb") as fh:
            assert pmjax._pmfile._file_state(fh) is None
            assert_same_pm(read_pm(fh), pm)
    finally:
        writer.join()
    with open(path, "rb") as fh:
        assert pmjax._pmfile._file_state(fh)[0] == os.path.getsize(path)


def _write_all(fd, data):
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)


def test_the_decoding_key_frames_its_parts():
    key = pmjax._pmfile.decoding_key
    identity = bytes(32)
    # Header text and digests moved across a boundary give another key.
    assert key(identity, b"ab", [b"c" * 32]) != key(identity, b"a", [b"b" + b"c" * 32])
    assert key(identity, b"a", [b"b" * 32, b"c" * 32]) != key(identity, b"a", [b"b" * 32 + b"c" * 32])
    assert key(identity, b"a", []) == key(bytes(32), b"a", []) and key(None, b"a", []) is None


@pytest.mark.parametrize("how", ["rewritten", "cut"])
def test_a_file_changed_in_place_while_it_is_read_is_refused(cow, tmp_path, monkeypatch, how):
    pm, path = cow
    known = tmp_path / "known"
    monkeypatch.setenv("PMJAX_KNOWN_STRUCTURES", str(known))
    target = tmp_path / "changing.pmz"
    data = path.read_bytes()
    target.write_bytes(data)
    first = chunk_table(path)[1][1]
    chunk_sha = pmjax._codec.chunk_sha
    writes = []

    def rewrite_after_hashing(chunk):
        # The first chunk is hashed, then the file is written over in place:
        # "rewritten": the same bytes (same inode, same size, another
        # modification time); "cut": as ``cp`` does, opened with O_TRUNC and
        # written up to the second chunk (whose bytes are then gone).
        digest = chunk_sha(chunk)
        if not writes:
            if how == "cut":
                with open(target, "wb") as fh:
                    fh.write(data[:first])
            else:
                with open(target, "r+b") as fh:
                    fh.seek(first)
                    fh.write(data[first:first + 64])
            os.utime(target, ns=(os.stat(target).st_atime_ns, os.stat(target).st_mtime_ns + 10**9))
            writes.append(first)
        return digest

    monkeypatch.setattr(pmjax._codec, "chunk_sha", rewrite_after_hashing)
    for batches in (None, 1):
        writes.clear()
        target.write_bytes(data)
        with pytest.raises(PMFormatError, match=r"changing.pmz: the file changed while it was read"):
            read_arrays(target, batches=batches)
        assert writes
    # Nothing was recorded; unchanged, the same file reads and is recorded.
    assert not list(known.glob("*.decoded"))
    monkeypatch.setattr(pmjax._codec, "chunk_sha", chunk_sha)
    target.write_bytes(data)
    assert read_arrays(target)[1] == read_arrays(path)[1]
    assert len(list(known.glob("*.decoded"))) == 1


def test_a_damaged_chunk_anywhere_is_refused_though_the_file_was_read_before(cow, tmp_path, monkeypatch,
                                                                              assert_same_pm):
    pm, path = cow
    monkeypatch.setenv("PMJAX_KNOWN_STRUCTURES", str(tmp_path / "known"))
    bad = tmp_path / "bad.pmz"
    data = path.read_bytes()
    bad.write_bytes(data)
    read_pm(bad)  # its decoding is recorded: a damaged copy at the same path is still refused
    assert len(list((tmp_path / "known").glob("*.decoded"))) == 1
    for i, (name, start, end) in enumerate(chunk_table(path)):
        # One bit flipped in the chunk's digest, or in its compressed bytes.
        for at in (start, (start + 32 + end) // 2):
            damaged = bytearray(data)
            damaged[at] ^= 0x01
            bad.write_bytes(bytes(damaged))
            with pytest.raises(PMFormatError, match=rf"bad.pmz: chunk '{name}' \(bytes {start} to {end}\) fails its "
                                                    "SHA-256: the file is damaged"):
                read_pm(bad)
            if i:
                assert_same_pm(read_pm(bad, batches=i - 1), read_pm(path, batches=i - 1))
