"""The version 2 .pmz decoder's C loops (pmjax/_pmz_native.c) against its NumPy steps: the same arrays bit for
bit, the same prefixes, and the same refusal, word for word, of every kind of damaged chunk."""

import contextlib
import json
import os
import zlib

import numpy as np
import pytest

from pmjax import PMFormatError, _codec, read_arrays, save_pm
from pmjax._pmfile import numpy_steps

REQUIRED = os.environ.get("PMJAX_REQUIRE_CORE") == "1"
needs_native = pytest.mark.skipif(_codec.native is None and not REQUIRED,
                                  reason="the .pmz decoder's C loops (pmjax._pmz_native) are not built")


def test_the_c_loops_are_built_where_required():
    # Under PMJAX_REQUIRE_CORE=1 (CI) every compiled part must load.
    if REQUIRED:
        assert _codec.native is not None, "pmjax._pmz_native is not built (python setup.py build_ext --inplace)"
    elif _codec.native is None:
        pytest.skip("the .pmz decoder's C loops (pmjax._pmz_native) are not built")


@pytest.fixture
def numpy_decoder():
    """Run the NumPy steps inside ``with numpy_decoder():``."""
    return numpy_steps


def both_ways(numpy_decoder, read):
    """``read()`` with the C loops, then with the NumPy steps: each result,
    or each exception's type and message."""
    def run():
        try:
            return read()
        except Exception as exc:  # compared below, type and words
            return type(exc), str(exc)

    native = run()
    with numpy_decoder():
        plain = run()
    return native, plain


def check_model(pm, tmp_path, numpy_decoder, assert_same_pm, codec="zstd"):
    if codec == "zstd":
        pytest.importorskip("zstandard")
    path = tmp_path / "m.pmz"
    save_pm(pm, path, codec=codec)
    (native, _), (plain, _) = both_ways(numpy_decoder, lambda: read_arrays(path))
    assert_same_pm(native, pm)
    assert_same_pm(plain, pm)
    B = pm.n_batches
    for k in sorted({B // 3, B // 2, B - 1, B}):
        (native, fa), (plain, fb) = both_ways(numpy_decoder, lambda: read_arrays(path, batches=k))
        assert_same_pm(native, plain)
        assert native.header == plain.header and fa == fb


@needs_native
@pytest.mark.parametrize("codec", ["zstd", "zlib"])
@pytest.mark.parametrize("beside", [False, True], ids=["inline", "beside"])
def test_cow_decodes_to_the_same_bits_both_ways(built, tmp_path, numpy_decoder, codec, beside, monkeypatch,
                                                 assert_same_pm):
    # Also with every batch's face ranks and killers, and half of the faces'
    # placing, on the pool (as a large model's).
    if beside:
        monkeypatch.setattr(_codec, "FACES_BESIDE", 0)
        monkeypatch.setattr(_codec, "FACES_SPLIT", 0)
    check_model(built("cow.ply"), tmp_path, numpy_decoder, assert_same_pm, codec)


@needs_native
@pytest.mark.slow
@pytest.mark.parametrize("name", ["bunny.ply", "terrain_gcanyon.ply", "dragon.ply"])
def test_models_decode_to_the_same_bits_both_ways(built, tmp_path, numpy_decoder, name, assert_same_pm):
    check_model(built(name), tmp_path, numpy_decoder, assert_same_pm)


@needs_native
def test_area_normals_and_residuals_match_the_numpy_steps(numpy_decoder, same_bits):
    rng = np.random.default_rng(7)
    vertices = (rng.normal(size=(300, 3)) * 10.0 ** rng.integers(-3, 4, size=(300, 1))).astype(np.float32)
    faces = rng.integers(0, 250, size=(900, 3)).astype(np.int32)
    faces[:40, 1] = faces[:40, 0]  # no area: zero normals where nothing else adds
    vertices[10:20] = vertices[9]
    n = 280  # vertices 250 .. 279 on no face: zero
    prediction = rng.normal(size=(500, 3)).astype(np.float32)
    special = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1e-45, -1e-45, 3.4e38], np.float32)
    prediction[:8, 0] = special
    residual = rng.integers(0, 2**32, size=(500, 3), dtype=np.uint64).astype(np.uint32)
    residual[:8, 1] = _codec.float_residual(special, prediction[:8, 1])
    native = (_codec.area_normals(vertices, faces, n), _codec.float_from_residual(residual, prediction))
    with numpy_decoder():
        plain = (_codec.area_normals(vertices, faces, n), _codec.float_from_residual(residual, prediction))
    for a, b in zip(native, plain):
        assert same_bits(a, b)
    assert not native[0][250:].any()
    assert same_bits(native[1][:8, 1], special)
    # The same residuals still byte-planed, decoded in one pass.
    planed = memoryview(_codec.planes(residual))
    with np.errstate(invalid="ignore"):  # the special rows' guides are NaNs
        guide = prediction / np.linalg.norm(prediction.astype(np.float64), axis=1, keepdims=True).astype(np.float32)
    for use in (contextlib.nullcontext, numpy_decoder):
        with use():
            out, unit = np.empty_like(prediction), np.empty_like(prediction)
            _codec.float_from_planed(planed, prediction, out)
            _codec.unit_from_planed(planed, guide, unit)
        assert same_bits(out, native[1])
        assert same_bits(unit, _codec.unit_from_residual(residual, guide))


# --- damaged chunks: the same message both ways --------------------------------


def rewrite(path, out, chunk, change):
    """Copy the version 2 file ``path`` to ``out`` with chunk ``chunk``'s
    expanded bytes replaced by ``change(bytearray)``'s (recompressed, its
    sizes and SHA-256 updated)."""
    data = path.read_bytes()
    length = int.from_bytes(data[8:12], "little")
    header = json.loads(data[12:12 + length])
    at, chunks = 12 + length, []
    for name, size, raw in header["chunks"]:
        chunks.append(_codec.decompress(data[at + 32:at + 32 + size], header["codec"], raw))
        at += 32 + size
    chunks[chunk] = bytes(change(bytearray(chunks[chunk])))
    packed = [_codec.compress(raw, header["codec"]) for raw in chunks]
    header["chunks"] = [[name, len(p), len(raw)] for (name, _, _), p, raw in zip(header["chunks"], packed, chunks)]
    text = json.dumps(header, indent=1, sort_keys=True).encode()
    out.write_bytes(data[:8] + len(text).to_bytes(4, "little") + text
                    + b"".join(_codec.chunk_sha(p) + p for p in packed))
    return header


def put32(raw, array_at, n, i, value):
    """Set element ``i`` of the byte-planed 4-byte array of ``n`` elements at ``array_at``."""
    for k, byte in enumerate(np.array([value]).astype(np.uint32).view(np.uint8)):
        raw[array_at + k * n + i] = byte
    return raw


def get32(raw, array_at, n, i):
    return int(np.frombuffer(bytes(raw[array_at + k * n + i] for k in range(4)), np.int32)[0])


@pytest.fixture(scope="module")
def cow_file(built, tmp_path_factory):
    pm = built("cow.ply")
    path = tmp_path_factory.mktemp("native") / "cow.pmz"
    save_pm(pm, path, codec="zlib")
    return pm, path


def damage_cases(pm):
    """``[(chunk index, change, expected message part)]``: the chunk of a
    batch of a few dozen pcols damaged each way the reader checks; left-over
    bytes in the finest batch's (whose children are mostly original vertices,
    so its header entry allows more bytes than it holds)."""
    B, V0 = pm.n_batches, pm.n_original_vertices
    b = int(np.flatnonzero(np.diff(pm.batch_offsets) >= 20)[-1])
    lo, hi = int(pm.batch_offsets[b]), int(pm.batch_offsets[b + 1])
    n = hi - lo
    late = V0 + hi  # made by a later (finer) batch
    seen_root = int(np.flatnonzero(np.bincount(np.concatenate([pm.v1, pm.v2]), minlength=V0 + pm.n_pcols) == 0)[0])
    faces_at = _codec.batch_bytes(n, int((pm.v1[lo:hi] >= V0).sum() + (pm.v2[lo:hi] >= V0).sum()), 0)
    return [
        (B - b, lambda r: put32(r, 0, n, 1, late), f"v1 of pcol {lo + 1} is not a vertex made before its batch"),
        (B - b, lambda r: put32(r, 4 * n, n, 2, -1), f"v2 of pcol {lo + 2} is not a vertex made before its batch"),
        (B - b, lambda r: put32(r, 0, n, 2, seen_root),
         f"a pcol's child is already a vertex of the coarser mesh (pcol {lo + 2})"),
        # v1 of pcol 3 repeats v2 of pcol 1: pcol 3 is named, not pcol 1.
        (B - b, lambda r: put32(r, 0, n, 3, get32(r, 4 * n, n, 1)), f"a pcol's child is already a vertex of the "
                                                                     f"coarser mesh (pcol {lo + 3})"),
        # v2 of pcol 1 repeats v1 of pcol 1.
        (B - b, lambda r: put32(r, 4 * n, n, 1, get32(r, 0, n, 1)), f"(pcol {lo + 1})"),
        (B - b, lambda r: put32(r, 8 * n, n, 4, 0), f"a pcol's leaf counts do not split its vertex's (pcol {lo + 4})"),
        (B, lambda r: r + b"\0\0\0\0", "4 bytes are left over after its arrays"),
        (B - b, lambda r: r[:-1], "its arrays need more than its"),
        (B - b, lambda r: r[:12 * n + 5], "its arrays need more than its"),
        (B - b, lambda r: put32(r[:12 * n + 5], 0, n, 1, late), f"v1 of pcol {lo + 1} is not a vertex made before"),
        (B - b, lambda r: put32(r, faces_at, n, 0, 2 * V0 + 6), "a face corner's rank is outside"),
        (B - b, far_corners(faces_at, V0), "has no two corners under one of its batch's pcols"),
    ]


def far_corners(faces_at, V0):
    """A change moving the first face's second and third corners to ranks 0
    and ``V0 - 1`` (under no pcol holding its first corner)."""
    def zigzag(d):
        return int(_codec.zigzag(np.array([d], np.int64).astype(np.uint32))[0])

    def change(r):
        m = 3 * ((len(r) - faces_at) // 12)
        r0 = int(_codec.unzigzag(np.array([get32(r, faces_at, m, 0)], np.int64).astype(np.uint32))[0])
        put32(r, faces_at, m, 1, zigzag(-r0))
        return put32(r, faces_at, m, 2, zigzag(V0 - 1 - r0))

    return change


@needs_native
@pytest.mark.parametrize("beside", [False, True], ids=["inline", "faces-beside"])
def test_damaged_batch_chunks_are_refused_in_the_same_words(cow_file, tmp_path, numpy_decoder, monkeypatch, beside):
    # Also with every batch's face ranks and killers found on the pool.
    if beside:
        monkeypatch.setattr(_codec, "FACES_BESIDE", 0)
    pm, path = cow_file
    for i, (chunk, change, words) in enumerate(damage_cases(pm)):
        bad = tmp_path / f"bad{i}.pmz"
        rewrite(path, bad, chunk, change)
        native, plain = both_ways(numpy_decoder, lambda: read_arrays(bad))
        assert native == plain, words
        assert native[0] is PMFormatError and words in native[1], (words, native)


@needs_native
def test_a_pcol_splitting_a_vertex_not_made_is_named_in_the_same_words(cow_file, monkeypatch, numpy_decoder):
    # A chunk cannot split a vertex the coarser chunks did not make unless
    # the state is damaged: the reader's mark of one of the batch's vertices
    # is cleared as its chunk is decoded.
    pm, path = cow_file
    B, V0 = pm.n_batches, pm.n_original_vertices
    b = int(np.flatnonzero(np.diff(pm.batch_offsets) >= 20)[-1])
    lo = int(pm.batch_offsets[b])
    read_batch = _codec.read_batch

    def unmark(s, raw, at, n_faces, pool=None):
        if at == b:
            s.seen[V0 + lo + 5] = 0
        return read_batch(s, raw, at, n_faces, pool)

    monkeypatch.setattr(_codec, "read_batch", unmark)
    native, plain = both_ways(numpy_decoder, lambda: read_arrays(path))
    assert native == plain
    assert native[0] is PMFormatError
    assert f"chunk 'batch {b}' (bytes " in native[1], native
    assert f"a pcol splits a vertex the coarser chunks did not make (pcol {lo + 5})" in native[1], native


@needs_native
def test_a_batch_without_pcols_holding_a_face_is_refused_in_the_same_words(cow_file, tmp_path, numpy_decoder):
    # The coarsest batch is empty and one base face is moved into its chunk:
    # no pcol of it kills that face.
    from pmjax._pmdata import PMData
    from pmjax._pmfile import LAYOUT_FIELDS

    pm, _ = cow_file
    arrays = pm.arrays()
    arrays["batch_offsets"] = np.append(pm.batch_offsets, pm.n_pcols).astype(np.int64)
    empty = PMData(**arrays, header=dict(pm.header))
    B = empty.n_batches
    fields, table = _codec.chunk_arrays(empty, _codec.ENCODING)
    (_, base), (name, coarsest) = table[0], table[1]
    assert name == f"batch {B - 1}" and fields["group_faces"][1] == 0
    ranks = _codec.ranks_decode(base[-1][1])
    base[-1] = ("faces", _codec.ranks_code(ranks[:-1]))
    coarsest[-1] = ("faces", _codec.ranks_code(ranks[-1:]))
    fields["group_faces"][0] -= 1
    fields["group_faces"][1] += 1
    chunks = []
    for chunk_name, parts in table:
        raw = b"".join(_codec.planes(a) for _, a in parts)
        chunks.append((chunk_name, _codec.compress(raw, "zlib"), len(raw)))
    header = {k: v for k, v in pm.header.items() if k not in LAYOUT_FIELDS}
    header.update(magic="pmjax.progressive-mesh", version=2, array_sha256={}, codec="zlib",
                  counts=dict(V0=empty.n_original_vertices, F=len(empty.faces), P=empty.n_pcols, B=B),
                  chunks=[[n, len(d), r] for n, d, r in chunks], **fields)
    text = json.dumps(header).encode()
    bad = tmp_path / "empty.pmz"
    bad.write_bytes(_codec.MAGIC2 + len(text).to_bytes(4, "little") + text
                    + b"".join(_codec.chunk_sha(d) + d for _, d, _ in chunks))
    native, plain = both_ways(numpy_decoder, lambda: read_arrays(bad))
    assert native == plain
    assert native[0] is PMFormatError
    assert f"chunk 'batch {B - 1}': face 0 of the chunk has no two corners under one of its batch's pcols" in native[1]
    empty_batch = np.empty(0, np.int64)
    assert np.array_equal(_codec.face_killers(np.array([[0, 1, 2]]), empty_batch, empty_batch, 5), [-1])


@needs_native
def test_a_bad_rank_found_beside_is_named_before_the_next_chunks_damage(cow_file, tmp_path, monkeypatch):
    # The ranks are checked on the pool while the next chunk is read: its
    # damage (a failed SHA-256) must not hide the earlier chunk's.
    monkeypatch.setattr(_codec, "FACES_BESIDE", 0)
    pm, path = cow_file
    chunk, change, words = next(case for case in damage_cases(pm) if "rank is outside" in case[2])
    bad = tmp_path / "rank.pmz"
    header = rewrite(path, bad, chunk, change)
    data = bytearray(bad.read_bytes())
    at = 12 + int.from_bytes(data[8:12], "little")
    starts = []
    for _, size, _ in header["chunks"]:
        starts.append(at)
        at += 32 + size
    data[starts[chunk + 1] + 40] ^= 0x10  # the next chunk fails its SHA-256
    bad.write_bytes(bytes(data))
    name = header["chunks"][chunk][0]
    with pytest.raises(PMFormatError, match=rf"chunk '{name}' \(bytes {starts[chunk]} to {starts[chunk + 1]}\) is "
                                            rf"damaged: {words}"):
        read_arrays(bad)


def test_a_rewritten_file_reads_unchanged(cow_file, tmp_path, assert_same_pm):
    # The damage cases' rewriting alone changes nothing.
    pm, path = cow_file
    same = tmp_path / "same.pmz"
    rewrite(path, same, 3, lambda r: r)
    assert_same_pm(read_arrays(same)[0], pm)
    assert zlib.crc32(same.read_bytes()) == zlib.crc32(path.read_bytes())


# --- encodings ------------------------------------------------------------------


@needs_native
def test_predictions_match_the_numpy_steps_and_invert_exactly(numpy_decoder, same_bits):
    # Unit vectors, their guides and the costs, with signed zeros, NaNs,
    # infinities, ties between the guide's components and non-unit vectors.
    rng = np.random.default_rng(11)
    x = rng.normal(size=(600, 3))
    x /= np.linalg.norm(x, axis=1)[:, None]
    guide = (x + 0.05 * rng.normal(size=x.shape)).astype(np.float32)
    x = x.astype(np.float32)
    special = np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 1e-45, 2.0, -0.7], np.float32)
    x[:64] = special[rng.integers(0, 8, size=(64, 3))]
    guide[64:128] = special[rng.integers(0, 8, size=(64, 3))]
    guide[128:136] = [[0.5, -0.5, 0.5], [-0.6, 0.6, 0.1], [0, 0, 0], [-0.0, 0, -0.0], [1, 1, 1], [0.3, 0.3, -0.3],
                      [np.nan, 0.9, 0.1], [0.1, np.nan, np.nan]]
    cost = np.sort(rng.exponential(size=300)) * 10.0 ** rng.integers(-30, 30, size=300)
    cost[::37] = [0.0, -0.0, np.inf, np.nan, -1.5, 1e-310, 0.5, 0.25, 1e300][:len(cost[::37])]
    residual = _codec.unit_residual(x, guide)
    random = rng.integers(0, 2**32, size=(200, 3), dtype=np.uint64).astype(np.uint32)
    native = (_codec.unit_from_residual(residual, guide), _codec.unit_from_residual(random, guide[:200]))
    with numpy_decoder():
        plain = (_codec.unit_from_residual(residual, guide), _codec.unit_from_residual(random, guide[:200]))
        assert same_bits(_codec.unit_residual(plain[1], guide[:200]), random)
    for a, b in zip(native, plain):
        assert same_bits(a, b)
    assert same_bits(native[0], x)
    assert same_bits(_codec.cost_decode(_codec.cost_code(cost)), cost)
    # A unit vector's residuals are mostly 0 or one ulp each way (zigzag 0 .. 2).
    assert np.mean(residual[200:] <= 2) > 0.3


def write_encoding(pm, path, encoding, monkeypatch, codec="zstd"):
    with monkeypatch.context() as m:
        m.setattr(_codec, "ENCODING", encoding)
        save_pm(pm, path, codec=codec)


@needs_native
def test_files_of_encoding_1_still_read_to_the_same_bits(built, tmp_path, numpy_decoder, monkeypatch, assert_same_pm):
    # Encoding 1: no "encoding" in the header, the attributes and normals
    # stored as they are.
    pytest.importorskip("zstandard")
    pm = built("cow.ply")
    old, new = tmp_path / "old.pmz", tmp_path / "new.pmz"
    write_encoding(pm, old, 1, monkeypatch)
    save_pm(pm, new)
    assert "encoding" not in header_of(old) and header_of(new)["encoding"] == _codec.ENCODING == 2
    assert os.path.getsize(new) < os.path.getsize(old)
    (native, fa), (plain, fb) = both_ways(numpy_decoder, lambda: read_arrays(old))
    assert_same_pm(native, pm)
    assert_same_pm(plain, pm)
    assert fa == fb == read_arrays(new)[1]
    for k in (1, pm.n_batches // 2, pm.n_batches):
        (native, _), (plain, _) = both_ways(numpy_decoder, lambda: read_arrays(old, batches=k))
        assert_same_pm(native, read_arrays(new, batches=k)[0])
        assert_same_pm(plain, native)


def header_of(path):
    data = path.read_bytes()
    return json.loads(data[12:12 + int.from_bytes(data[8:12], "little")])


def test_an_unknown_encoding_is_refused(cow_file, tmp_path):
    _, path = cow_file
    data = path.read_bytes()
    length = int.from_bytes(data[8:12], "little")
    header = json.loads(data[12:12 + length])
    for value in (3, "2", True, 2.0):
        header["encoding"] = value
        text = json.dumps(header).encode()
        bad = tmp_path / "bad.pmz"
        bad.write_bytes(data[:8] + len(text).to_bytes(4, "little") + text + data[12 + length:])
        with pytest.raises(PMFormatError, match=f"header encoding={value!r} is not one this pmjax reads"):
            read_arrays(bad)
