"""The ``.pmz`` progressive-mesh file: flat arrays plus a JSON header.

Version 2 (written by :func:`save_pm`) is a JSON header followed by
compressed chunks ordered coarse to fine (:mod:`pmjax._codec`), so a prefix
that ends at a batch boundary is a valid progressive mesh. Version 1 (still
read, and written with ``version=1``) is a zip archive (numpy's ``.npz``
layout) holding one ``.npy`` per array and ``header.json``. Both headers carry
a magic string, a format version, the counts, the build parameters, a SHA-256
of the source mesh and a SHA-256 of every array (in :data:`ARRAY_SPECS`
order), so truncation or tampering is caught on load. See ``docs/format.md``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import stat
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from . import _codec, _pmdata
from ._atomic import atomic_path
from ._pmdata import ARRAY_SPECS, METRICS, OPTIONAL_ARRAY_SPECS, PMData, PMFormatError  # noqa: F401 (re-exported)
from ._structure import check_structure, decoding_known, remember_decoding, remember_structure, structure_known

MAGIC = "pmjax.progressive-mesh"
# The version save_pm writes; read_pm reads every version in VERSIONS.
VERSION = 2
VERSIONS = (1, 2)
# Header fields that describe one file's layout, not the hierarchy.
LAYOUT_FIELDS = ("array_sha256", "chunks", "roots", "group_faces", "codec", "shading_normals", "batch_offsets",
                 "encoding")
# Largest header.json read, bytes: it holds counts, build parameters and
# checksums (a few KiB), so a larger one is damaged or forged.
HEADER_LIMIT = 1 << 20
# Largest .npy header read, bytes (numpy writes 128, and refuses over 10000).
NPY_HEADER_LIMIT = 10000

# Smallest compressed chunk that version 2's reader expands on a second
# thread: a smaller one costs less to expand than to hand over.
PIPELINE_BYTES = 1 << 16

# Largest distance from 1 of a stored shading normal's length: float32
# rounding of a normalized vector is below 1e-6.
SHADING_UNIT_TOLERANCE = 1e-4


def _sha256(a: np.ndarray) -> str:
    # Hash the array's memory directly (no tobytes() copy).
    return hashlib.sha256(np.ascontiguousarray(a).ravel().view(np.uint8)).hexdigest()


def _array_digests(arrays: dict) -> dict:
    """Each array's SHA-256 by name, the arrays hashed in parallel (hashlib
    releases the GIL on large buffers)."""
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        return dict(zip(arrays, pool.map(_sha256, arrays.values())))


def save_pm(pm: PMData, path: str | os.PathLike, *, version: int = VERSION, codec: str | None = None) -> None:
    """Write ``pm`` to ``path`` atomically (temporary file, then rename).

    The arrays are first checked with :func:`validate_pm` and
    :func:`pmjax.check_structure`, so an inconsistent progressive mesh is
    never written.

    Args:
        pm: the progressive mesh (host arrays).
        path: the ``.pmz`` file to write.
        version: 2 (compressed, coarse to fine) or 1 (the uncompressed zip
            that pmjax before version 2 reads).
        codec: version 2's compression, ``"zstd"`` (the default when the
            zstandard package is installed) or ``"zlib"``.
    """
    path = os.fspath(path)
    if version not in VERSIONS:
        raise ValueError(f"save_pm: version must be one of {VERSIONS}, got {version!r}")
    if codec is None:
        codec = "zstd" if _codec.zstd_available() else "zlib"
    if codec not in ("zstd", "zlib"):
        raise ValueError(f"save_pm: codec must be 'zstd' or 'zlib', got {codec!r}")
    validate_pm(pm, source=path)
    check_structure(pm, source=path)
    sums = _array_digests(pm.arrays())
    header = {k: v for k, v in pm.header.items() if k not in LAYOUT_FIELDS}
    header.update(
        magic=MAGIC,
        version=version,
        counts=dict(
            V0=pm.n_original_vertices,
            F=int(len(pm.faces)),
            P=pm.n_pcols,
            B=pm.n_batches,
        ),
        array_sha256=sums,
    )
    with atomic_path(path, ".pmz") as tmp:
        with open(tmp, "wb") as fh:
            if version == 1:
                _write_v1(fh, header, pm)
            else:
                fields, chunks = _codec.encode(pm, codec, _codec.ENCODING)
                header.update(fields, chunks=[[name, len(data), raw] for name, data, raw in chunks])
                text = json.dumps(header, indent=1, sort_keys=True).encode()
                if len(text) > HEADER_LIMIT:
                    raise PMFormatError(f"{path}: the header would take {len(text)} bytes, more than the "
                                        f"{HEADER_LIMIT} a reader accepts ({pm.n_batches} batches)")
                fh.write(_codec.MAGIC2 + len(text).to_bytes(4, "little") + text)
                for _, data, _ in chunks:
                    fh.write(_codec.chunk_sha(data))
                    fh.write(data)
    # Checked above: a later load of these bytes need not check again.
    remember_structure(content_fingerprint(sums))


def _write_v1(fh, header: dict, pm: PMData) -> None:
    """Version 1: an uncompressed zip of ``header.json`` and one ``.npy`` per array."""
    with zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_STORED) as zf:
        zf.writestr("header.json", json.dumps(header, indent=1, sort_keys=True))
        for name, a in pm.arrays().items():
            buf = io.BytesIO()
            np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
            zf.writestr(name + ".npy", buf.getvalue())


def file_sha256(path) -> str:
    """SHA-256 of a file's bytes, hex (a PM's source checksum; an evaluation
    job's record of its models and camera files)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def read_pm(path, *, batches: int | None = None) -> PMData:
    """Read and fully validate a ``.pmz`` file, its structure included
    (:func:`pmjax.check_structure`), unless content with the same array
    checksums passed that check before on this machine
    (:func:`pmjax.structure_known`).

    Args:
        path: a ``.pmz`` file, or a binary file object reading one.
        batches: read only the base mesh and the ``batches`` coarsest
            batches (``0 .. B``): the result is the progressive mesh whose
            original mesh is the full one's mesh after its other batches ran
            (``pmjax lod --batch B-1-batches``). A version 2 file is read
            only that far (``B``: every batch chunk, not the tail: the
            faces in the order read, no shading normals); ``None`` reads
            everything.

    Raises:
        PMFormatError: naming the file and what is wrong (magic, version, a
            missing array, a dtype or shape, an index range, a checksum, a
            truncated or damaged chunk, the structure).
    """
    pm, fingerprint = read_arrays(path, batches=batches, call="read_pm")
    if not structure_known(fingerprint):
        check_structure(pm, source=_source_name(path))
        remember_structure(fingerprint)
    return pm


def _source_name(path) -> str:
    if hasattr(path, "read"):
        return str(getattr(path, "name", "<stream>"))
    return os.fspath(path)


# Mesh formats recognised by their extension or first bytes, to say what a
# file given as a .pmz is.
_MESH_EXTENSIONS = {".ply": "PLY", ".obj": "OBJ", ".off": "OFF", ".stl": "STL", ".glb": "glTF", ".gltf": "glTF"}
_MESH_MAGIC = ((b"ply", "PLY"), (b"OFF", "OFF"), (b"solid", "STL"), (b"glTF", "glTF"))


def _mesh_kind(path: str) -> str:
    """``"PLY"``, ``"OBJ"``, ... for a file that looks like a mesh, else ``""``."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(64).lstrip()
    except OSError:
        return ""
    for magic, kind in _MESH_MAGIC:
        if head.startswith(magic):
            return kind
    return _MESH_EXTENSIONS.get(os.path.splitext(path)[1].lower(), "")


def read_arrays(path, *, batches: int | None = None, call: str = "read_arrays") -> tuple[PMData, str]:
    """Read a ``.pmz`` file with every check but the structure check.

    Nothing is read beyond what the header's counts allow. Version 2: the
    counts must fit the bytes the chunks declare (and, for a path, the
    chunks the read needs the file's size) before the arrays are allocated;
    each chunk's SHA-256 is checked before it is expanded, and it expands to
    at most the size its header entry gives; a file that ends inside a chunk
    the read needs is refused, naming the chunk and how many batches its
    whole chunks hold, and one cut or written over while it is read is
    refused as changed. Version 1: every array's ``.npy`` header (dtype,
    shape) is read first and checked against the counts, and each zip
    entry's declared size against its ``.npy`` header, before any array data
    is read; data is then read with that bound, so an entry that expands past
    its declared size (a zip bomb) is not expanded.

    Args:
        path: a ``.pmz`` file, or a binary file object reading one.
        batches: as :func:`read_pm`.
        call: the public call an argument error names.

    Returns:
        ``(pm, fingerprint)``: the fingerprint is a SHA-256 over the arrays'
        checksums, verified against the bytes read, so it names the content.
    """
    if batches is not None and (isinstance(batches, bool) or not isinstance(batches, (int, np.integer))
                                or batches < 0):
        raise ValueError(f"{call}: batches must be a whole number >= 0 or None, got {batches!r}")
    if hasattr(path, "read"):
        source = _source_name(path)
        head = _read_full(path.read, len(_codec.MAGIC2))
        if head == _codec.MAGIC2:
            return _read_v2(path, source, batches)
        path = io.BytesIO(head + path.read())
    else:
        path = os.fspath(path)
        source = path
        if not os.path.exists(path):
            raise PMFormatError(f"{path}: no such file")
        with open(path, "rb") as fh:
            if _read_full(fh.read, len(_codec.MAGIC2)) == _codec.MAGIC2:
                return _read_v2(fh, source, batches, by_position=True)
    pm, fingerprint = _read_v1(path, source)
    if batches is None:
        return pm, fingerprint
    kills = np.bincount(np.searchsorted(pm.batch_offsets, pm.killer[pm.killer >= 0], side="right") - 1,
                        minlength=pm.n_batches)
    _check_batches(source, batches, pm.n_batches, [int((pm.killer < 0).sum()), *kills[::-1]])
    data = _codec.finish_prefix(_codec.stream_of(pm, int(batches)), int(batches))
    return _prefix_pm(data, pm.header, int(batches), pm.n_batches, source)


def _check_batches(source: str, batches: int, B: int, group_faces) -> None:
    """``batches`` within ``0 .. B`` and giving a mesh with faces
    (``group_faces``: the base mesh's faces, then each batch's kills, coarse
    first)."""
    if batches > B:
        raise PMFormatError(f"{source}: batches={batches}, but the file has {B} batches")
    total = np.cumsum(group_faces)
    if total[-1] == 0:
        raise PMFormatError(f"{source}: the file holds no faces (F=0): no prefix of it is a mesh; the file is "
                            "damaged or forged")
    if total[batches] == 0:
        first = int(np.argmax(total > 0))
        raise PMFormatError(f"{source}: batches={batches} gives a mesh with no faces (the base mesh has none); "
                            f"batches={first} is the first prefix with faces")


def _prefix_pm(arrays: dict, header: dict, k: int, B: int, source: str) -> tuple[PMData, str]:
    """A progressive mesh of the ``k`` coarsest batches, validated, and its
    content fingerprint."""
    meta = {key: v for key, v in header.items() if key not in LAYOUT_FIELDS}
    V0 = len(arrays["vertices"]) - len(arrays["v1"])
    meta.update(counts=dict(V0=V0, F=len(arrays["faces"]), P=len(arrays["v1"]), B=k),
                prefix=dict(batches=k, of=B, full_counts=header.get("counts")))
    pm = PMData(**arrays, header=meta)
    validate_pm(pm, source=source)
    return pm, content_fingerprint(_array_digests(pm.arrays()))


def _read_full(read, n: int) -> bytes:
    """``n`` bytes from ``read(k)`` (a file object's ``read``), fewer only at
    the end of the file: a pipe or socket returns what has arrived, so one
    call may return fewer bytes than remain."""
    out = read(n) or b""
    if len(out) == n:
        return out
    parts, got = [out], len(out)
    while got < n:
        part = read(n - got)
        if not part:
            break
        parts.append(part)
        got += len(part)
    return b"".join(parts)


class _Positional:
    """A regular file read by position (``os.pread``), from any thread: each
    read copies its bytes, so a file cut or rewritten meanwhile gives fewer or
    other bytes (refused by the size and SHA-256 checks and the file's
    state), never a fault as the pages of a map cut short give."""

    def __init__(self, fh):
        self.fd = fh.fileno()
        self.at = fh.tell()

    def read_at(self, at: int, n: int) -> bytes:
        """``n`` bytes from byte ``at``, fewer only at the end of the file."""
        def read(k: int) -> bytes:
            nonlocal at
            out = os.pread(self.fd, k, at)
            at += len(out)
            return out

        return _read_full(read, n)

    def read(self, n: int) -> bytes:
        out = self.read_at(self.at, n)
        self.at += len(out)
        return out


def _framed(*parts: bytes) -> bytes:
    """``parts`` joined, each after its length (8 bytes, little-endian): no
    two lists of parts give the same bytes."""
    return b"".join(len(part).to_bytes(8, "little") + part for part in parts)


def reader_identity() -> bytes | None:
    """SHA-256 naming the version 2 reader this process runs: everything a
    recorded decoding's outcome depends on besides the file's bytes.

    Covers :data:`pmjax._codec.DECODER_VERSION`, NumPy's, zstandard's and
    zlib's versions, whether the C loops or the NumPy steps decode, and the
    contents of the decoder (``_codec.py``), the array checks (this module
    and ``_pmdata.py``, whose specs :func:`validate_pm` applies) and the C
    library loaded. Computed once, at import (:data:`READER_IDENTITY`): the
    code that runs is the code read then, whatever is on disk later.

    Returns:
        32 bytes, or ``None`` where a file cannot be read (no record of a
        decoding is then read or written).
    """
    try:
        try:
            import zstandard
            zstd = zstandard.__version__
        except ImportError:
            zstd = "absent"
        native = _codec.native
        files = [_codec.__file__, __file__, _pmdata.__file__] + ([native._name] if native is not None else [])
        names = [f"pmz decoder {_codec.DECODER_VERSION}", f"numpy {np.__version__}", f"zstandard {zstd}",
                 f"zlib {zlib.ZLIB_RUNTIME_VERSION}", "C loops" if native is not None else "NumPy steps"]
        contents = []
        for path in files:
            with open(path, "rb") as fh:
                contents.append(fh.read())
        return hashlib.sha256(_framed(*(name.encode() for name in names), *contents)).digest()
    except Exception:  # a file gone or unreadable, a module without its file
        return None


READER_IDENTITY = reader_identity()


@contextlib.contextmanager
def numpy_steps():
    """Within the ``with`` block, version 2 files are decoded by the NumPy
    steps, as where the C loops are not built (the same arrays, bit for
    bit), under that reader's identity: its decodings are recorded apart."""
    global READER_IDENTITY
    native, identity = _codec.native, READER_IDENTITY
    _codec.native = None
    try:
        READER_IDENTITY = reader_identity()
        yield
    finally:
        _codec.native = native
        READER_IDENTITY = identity


def decoding_key(identity: bytes | None, header: bytes, digests: list) -> str | None:
    """The key of a version 2 file's decoding record: a SHA-256 over the
    reader's identity, the header's bytes and the chunks' stored SHA-256s
    (each part framed by its length), or ``None`` without an identity."""
    if identity is None:
        return None
    return hashlib.sha256(_framed(identity, header, *digests)).hexdigest()


def _file_state(fh) -> tuple | None:
    """``(size, mtime_ns, inode, device)`` of an open regular file, or
    ``None`` for a file object without a descriptor (bytes in memory) or a
    pipe or socket (its bytes are copied as they are read, and a writer
    changes its times). Not the change time: a new file renamed over the
    path (how pmjax writes) changes the old inode's link count and change
    time, not its bytes."""
    try:
        st = os.fstat(fh.fileno())
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        return None
    return (st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev) if stat.S_ISREG(st.st_mode) else None


def _changed(path: str) -> PMFormatError:
    return PMFormatError(f"{path}: the file changed while it was read (another program wrote it); "
                         "read it again once it is whole")


def _read_v2(fh, path: str, batches: int | None, by_position: bool = False) -> tuple[PMData, str]:
    """Version 2 after its magic bytes: the header, then the chunks the read
    needs, each checked (SHA-256, size, content) before it is used.

    ``by_position``: ``fh`` is a file this reader opened; where it is a
    regular file, its size is known before any array is allocated and each
    chunk is read by position on the pool's thread that expands it."""
    # The file's size, times and inode as the read starts: a file changed in
    # place meanwhile (a copy over it) could have chunk bytes hashed, then
    # other bytes read.
    opened = _file_state(fh)
    positional = _Positional(fh) if by_position and opened is not None and hasattr(os, "pread") else None
    read = fh.read if positional is None else positional.read
    size = _read_full(read, 4)
    length = int.from_bytes(size, "little")
    if len(size) < 4:
        raise PMFormatError(f"{path}: truncated in its header (the file ends after {8 + len(size)} bytes)")
    if length > HEADER_LIMIT:
        raise PMFormatError(f"{path}: header declares {length} bytes, more than the {HEADER_LIMIT} a header can "
                            "need; the file is damaged or forged")
    text = bytes(_read_full(read, length))
    if len(text) < length:
        raise PMFormatError(f"{path}: truncated in its header ({len(text)} of {length} bytes)")
    try:
        header = json.loads(text)
    except Exception as exc:
        raise PMFormatError(f"{path}: header is unreadable ({type(exc).__name__}: {exc})") from exc
    _check_header(header, path, 2)
    shapes, counts = _expected_shapes(path, header.get("counts"))
    c = header["counts"]
    V0, F, P, B = c["V0"], c["F"], c["P"], c["B"]
    layout = _v2_layout(header, path, V0, F, P, B)
    k = B if batches is None else int(batches)
    _check_batches(path, k, B, header["group_faces"])
    # The chunks read: the base, k batches, and the tail for a full read.
    last = k + (1 if batches is None else 0)

    def truncated(i: int, name: str, at: int, end: int, ends: int) -> PMFormatError:
        held = (f"its base mesh and {i - 1} coarsest batches are whole; pmjax.load(path, batches={i - 1}) "
                "reads them") if i else "not even its base mesh is whole"
        return PMFormatError(f"{path}: truncated in chunk {name!r} (bytes {at} to {end}; the file ends at byte "
                             f"{ends}): {held}")

    at = 12 + length
    if positional is not None:
        # The chunks the read needs must lie in the file before the arrays
        # their counts give are allocated: a few bytes of forged header
        # must not claim gigabytes.
        end = at
        for i, (name, nbytes, _) in enumerate(layout[:last + 1]):
            if end + _codec.SHA_BYTES + nbytes > opened[0]:
                raise truncated(i, name, end, end + _codec.SHA_BYTES + nbytes, opened[0])
            end += _codec.SHA_BYTES + nbytes
    offsets = np.asarray(header["batch_offsets"], np.int64)
    try:
        stream = _codec.new_stream(V0, P, offsets, header.get("encoding", 1))
    except MemoryError as exc:
        raise MemoryError(f"{path}: its counts V0={V0}, P={P} need more memory than is free here") from exc
    names = [name for name, _, _ in layout]
    codec = header["codec"]
    tail = None
    wheres = {}
    digests = []  # each chunk's SHA-256 as stored (checked before its chunk is used)

    def expand(where: str, payload, raw: int):
        # On the pool's thread: hashlib and the decompressors release the GIL.
        data = memoryview(payload)[_codec.SHA_BYTES:]
        digest = bytes(payload[:_codec.SHA_BYTES])
        if _codec.chunk_sha(data) != digest:
            raise PMFormatError(f"{where} fails its SHA-256: the file is damaged")
        try:
            return digest, _codec.decompress(data, codec, raw)
        except ValueError as exc:
            raise PMFormatError(f"{where} is damaged: {exc}") from exc

    def read_expand(where: str, at: int, n: int, raw: int):
        # The chunk's bytes read on the same thread (the file held them as
        # the read started: fewer now means it was cut meanwhile).
        payload = positional.read_at(at, n)
        if len(payload) < n:
            raise _changed(path)
        return expand(where, payload, raw)

    def settle_group(i: int) -> None:
        # Batch chunk i's face ranks and killers, found beside the next
        # chunk's decoding: a bad rank there is chunk i's failure.
        if 1 <= i <= B:
            try:
                _codec.settle(stream, i)
            except ValueError as exc:
                raise PMFormatError(f"{wheres[i]} is damaged: {exc}") from exc

    def decode(i: int, where: str, job) -> None:
        nonlocal tail
        wheres[i] = where
        failure = None
        try:
            digest, raw_bytes = job.result()
            digests.append(digest)
            if i == 0:
                _codec.read_base(stream, raw_bytes, header["roots"], header["group_faces"][0])
            elif i <= B:
                _codec.read_batch(stream, raw_bytes, B - i, header["group_faces"][i], pool)
        except PMFormatError as exc:
            failure = exc
        except ValueError as exc:
            failure = PMFormatError(f"{where} is damaged: {exc}")
            failure.__cause__ = exc
        settle_group(i - 1)  # the previous chunk's failures come first
        if failure is not None:
            raise failure
        if i == B + 1:
            tail = (where, raw_bytes)

    # Chunk i+1 is read and expanded (on the pool when it is large) while
    # chunk i is decoded; every failure is still raised in file order (a
    # stream's chunk i's before chunk i+1's truncation; a file's truncation
    # is found from its size before any chunk is read).
    # One pool for reading, expanding and hashing: its threads start once.
    with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 1)) as pool:
        try:
            pending = None
            for i, (name, nbytes, raw) in enumerate(layout[:last + 1]):
                n = _codec.SHA_BYTES + nbytes
                where = f"{path}: chunk {name!r} (bytes {at} to {at + n})"
                run = pool.submit if nbytes >= PIPELINE_BYTES else _codec.finished
                if positional is not None:
                    job = run(read_expand, where, at, n, raw)
                else:
                    payload = _read_full(read, n)
                    if len(payload) < n:
                        if pending is not None:
                            decode(*pending)
                            settle_group(pending[0])
                        raise truncated(i, name, at, at + n, at + len(payload))
                    job = run(expand, where, payload, raw)
                if pending is not None:
                    decode(*pending)
                pending = (i, where, job)
                at += n
            if pending is not None:
                decode(*pending)
                settle_group(pending[0])
        except PMFormatError as exc:
            # A file changed meanwhile fails for that reason, whatever check
            # its new bytes failed.
            if opened is not None and _file_state(fh) != opened:
                raise _changed(path) from exc
            raise
        # Every chunk the read needs is expanded: the bytes expanded are the
        # bytes hashed only if the file did not change since it was opened.
        if _file_state(fh) != opened:
            raise _changed(path)
        try:
            _codec.killers_of(stream, names)
        except ValueError as exc:
            raise PMFormatError(f"{path}: {exc}; the file is damaged") from exc
        if batches is not None:
            return _prefix_pm(_codec.finish_prefix(stream, k), header, k, B, path)
        # Every chunk has passed its SHA-256: the header and the chunks'
        # digests name the file's bytes, and with the decoder its arrays. A
        # decoding of these bytes recorded on this machine matched the
        # arrays' checksums and passed validate_pm: only the decoding's own
        # checks run again.
        key = decoding_key(READER_IDENTITY, text, digests)
        known = decoding_known(key) if key is not None else None
        # Otherwise each array is hashed on the pool as soon as it is final,
        # beside the rest of the decoding and beside the array checks.
        hashing = {}
        ready = None if known else lambda name, a: hashing.setdefault(name, pool.submit(_sha256, a))
        where, raw_bytes = tail
        try:
            arrays = _codec.finish_full(stream, raw_bytes, B, F, header["shading_normals"], ready, pool)
        except ValueError as exc:
            raise PMFormatError(f"{where} is damaged: {exc}") from exc
        for name, shape in shapes.items():
            if arrays.get(name) is not None and arrays[name].shape != shape:
                raise PMFormatError(f"{path}: array {name!r} decodes to shape {arrays[name].shape}, expected {shape}")
        meta = {name: v for name, v in header.items() if name not in LAYOUT_FIELDS}
        pm = PMData(**arrays, header=meta)
        if known:
            return pm, known
        # The checksums' failures come first, as they name the damage.
        rules = None
        try:
            validate_pm(pm, source=path)
        except PMFormatError as exc:
            rules = exc
        sums = header["array_sha256"]
        sums_read = {name: hashing[name].result() for name, a in arrays.items() if a is not None}
        for name, digest in sums_read.items():
            if digest != sums.get(name):
                raise PMFormatError(f"{path}: checksum mismatch in array {name!r}")
        for name in sums:
            if name not in sums_read:
                raise PMFormatError(f"{path}: array {name!r} is missing (the header has its checksum)")
        if rules is not None:
            raise rules
        fingerprint = content_fingerprint(sums_read)
        if key is not None:
            remember_decoding(key, fingerprint)
    return pm, fingerprint


def _check_header(header: Any, path: str, version: int | None = None) -> None:
    """Magic, version and checksum table of a parsed header."""
    if not isinstance(header, dict) or header.get("magic") != MAGIC:
        raise PMFormatError(f"{path}: bad magic (expected {MAGIC!r})")
    if header.get("version") not in VERSIONS or (version is not None and header.get("version") != version):
        raise PMFormatError(
            f"{path}: unsupported format version {header.get('version')!r} "
            f"(this pmjax reads versions {', '.join(map(str, VERSIONS))})"
        )
    if not isinstance(header.get("array_sha256"), dict):
        raise PMFormatError(f"{path}: header has no array checksums")


def _v2_layout(header: dict, path: str, V0: int, F: int, P: int, B: int) -> list:
    """The chunk table ``[name, compressed bytes, raw bytes]`` of a version 2
    header, checked against the counts: names in order, sizes whole numbers,
    raw sizes within what the counts allow."""
    def bad(what):
        raise PMFormatError(f"{path}: header {what}; the file is damaged or forged")

    if header.get("codec") not in ("zstd", "zlib"):
        bad(f"codec {header.get('codec')!r} is not zstd or zlib")
    encoding = header.get("encoding", 1)
    if isinstance(encoding, bool) or not isinstance(encoding, int) or encoding not in _codec.ENCODINGS:
        raise PMFormatError(f"{path}: header encoding={encoding!r} is not one this pmjax reads "
                            f"({', '.join(map(str, _codec.ENCODINGS))}); a newer pmjax wrote it, or it is damaged")
    shading = header.get("shading_normals")
    if not isinstance(shading, bool):
        bad(f"shading_normals={shading!r} is not true or false")
    R = header.get("roots")
    if isinstance(R, bool) or not isinstance(R, int) or not 0 <= R <= V0 + P:
        bad(f"roots={R!r} is not a vertex count")
    offsets = header.get("batch_offsets")
    if not (isinstance(offsets, list) and len(offsets) == B + 1 and all(
            isinstance(o, int) and not isinstance(o, bool) for o in offsets)
            and offsets and offsets[0] == 0 and offsets[-1] == P and all(a <= b for a, b in zip(offsets, offsets[1:]))):
        bad(f"batch_offsets is not {B + 1} rising whole numbers from 0 to P={P}")
    groups = header.get("group_faces")
    if not (isinstance(groups, list) and len(groups) == B + 1 and all(
            isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in groups) and sum(groups) == F):
        bad(f"group_faces is not {B + 1} face counts summing to F={F}")
    names = ["base", *(f"batch {b}" for b in range(B - 1, -1, -1)), "tail"]
    table = header.get("chunks")
    if not (isinstance(table, list) and len(table) == len(names)):
        bad(f"chunks is not a table of {len(names)} chunks")
    # Largest raw size of each chunk: every array at its largest count.
    limits = [R * 24 + R * 12 + groups[0] * 12]
    for i, b in enumerate(range(B - 1, -1, -1)):
        n = offsets[b + 1] - offsets[b]
        limits.append(_codec.batch_bytes(n, 2 * n, groups[i + 1]))
    limits.append(F * 4 + V0 * 12 + (V0 + P) * 12)
    for (name, limit), entry in zip(zip(names, limits), table):
        if not (isinstance(entry, list) and len(entry) == 3 and entry[0] == name
                and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in entry[1:])):
            bad(f"chunk entry {entry!r} is not [{name!r}, bytes, raw bytes]")
        if entry[2] > limit:
            bad(f"chunk {name!r} declares {entry[2]} bytes expanded, more than the {limit} its counts allow")
    # The counts give the reader's arrays, allocated before any chunk is
    # read: the chunks together must declare at least the bytes those counts
    # store (each pcol's fields, each face's ranks, each original vertex's
    # normal residual), so that a few bytes of header cannot claim gigabytes.
    need = _codec.batch_bytes(P, 0, F) + 12 * V0
    declared = sum(entry[2] for entry in table)
    if declared < need:
        bad(f"chunks declare {declared} bytes expanded, fewer than the {need} its counts V0={V0}, F={F}, P={P} "
            "store")
    return table


def _read_v1(path, source: str) -> tuple[PMData, str]:
    """Version 1: the zip archive of ``.npy`` arrays."""
    try:
        zf = zipfile.ZipFile(path, "r")
    except Exception as exc:  # zipfile raises several types for a damaged archive
        kind = _mesh_kind(path) if isinstance(path, str) else ""
        if kind:  # a mesh given where a progressive mesh is needed
            article = "an" if kind[0] in "AEFHILMNORSX" else "a"  # as the letters are spoken
            raise PMFormatError(f"{path}: is {article} {kind} mesh, not a .pmz progressive mesh; make one with "
                                f"`pmjax build {path} -o model.pmz`") from exc
        raise PMFormatError(f"{source}: not a .pmz progressive mesh (not a zip archive: {exc}); "
                            f"`pmjax build MESH -o model.pmz` makes one") from exc
    path = source
    with zf:
        names = set(zf.namelist())
        if "header.json" not in names:
            raise PMFormatError(f"{path}: not a pmjax file (no header.json)")
        header = _read_header(zf, path)
        _check_header(header, path, 1)
        sums = header["array_sha256"]
        for name in ARRAY_SPECS:
            if name + ".npy" not in names:
                raise PMFormatError(f"{path}: array {name!r} is missing")
        # An optional array is read when the file holds it; one the checksums
        # name must be there.
        optional = [name for name in OPTIONAL_ARRAY_SPECS if name + ".npy" in names or name in sums]
        for name in optional:
            if name + ".npy" not in names:
                raise PMFormatError(f"{path}: array {name!r} is missing (the header has its checksum)")
        # Every array's shape and dtype, and its entry's size, checked before
        # any data is read.
        shapes, counts = _expected_shapes(path, header.get("counts"))
        layout = {name: _npy_layout(zf, path, name, shapes[name], counts) for name in [*ARRAY_SPECS, *optional]}
        arrays: dict[str, Any] = {}
        for name, (offset, shape, fortran, dtype) in layout.items():
            arrays[name] = _read_npy(zf, path, name, offset, shape, fortran, dtype)
    digests = _array_digests(arrays)
    for name, digest in digests.items():
        if digest != sums.get(name):
            raise PMFormatError(f"{path}: checksum mismatch in array {name!r}")
    meta = {k: v for k, v in header.items() if k not in LAYOUT_FIELDS}
    pm = PMData(**arrays, header=meta)
    # The shapes were checked against the header's counts before reading.
    validate_pm(pm, source=path)
    return pm, content_fingerprint(digests)


def _read_header(zf: zipfile.ZipFile, path: str) -> Any:
    """``header.json`` parsed, read with a bound of :data:`HEADER_LIMIT` bytes."""
    info = zf.getinfo("header.json")
    if info.file_size > HEADER_LIMIT:
        raise PMFormatError(f"{path}: header.json declares {info.file_size} bytes, more than the {HEADER_LIMIT} "
                            "a header can need; the file is damaged or forged")
    try:
        with zf.open(info) as fh:
            return json.loads(fh.read(HEADER_LIMIT))
    except Exception as exc:  # bad JSON, a damaged entry, an unknown compression method
        raise PMFormatError(f"{path}: header.json is unreadable ({type(exc).__name__}: {exc})") from exc


def _expected_shapes(path: str, counts: Any) -> tuple[dict[str, tuple[int, ...]], str]:
    """Each array's shape from the header's counts ``V0``, ``F``, ``P``, ``B``,
    and the counts as text for messages."""
    if not isinstance(counts, dict):
        raise PMFormatError(f"{path}: header has no counts (V0, F, P, B)")
    for key in ("V0", "F", "P", "B"):
        value = counts.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise PMFormatError(f"{path}: header count {key}={value!r} is not a whole number >= 0")
    sizes = dict(V=counts["V0"] + counts["P"], F=counts["F"], P=counts["P"], B1=counts["B"] + 1, **{"3": 3})
    text = ", ".join(f"{key}={counts[key]}" for key in ("V0", "F", "P", "B"))
    specs = {**ARRAY_SPECS, **OPTIONAL_ARRAY_SPECS}
    return {name: tuple(sizes[s] for s in shape) for name, (_, shape) in specs.items()}, text


def _npy_layout(zf: zipfile.ZipFile, path: str, name: str, want: tuple[int, ...], counts: str):
    """Read only the ``.npy`` header of array ``name`` and check it: the dtype
    of :data:`ARRAY_SPECS`, the shape ``want`` (from the header's ``counts``),
    and the zip entry's declared size equal to header plus data.

    Returns:
        ``(data offset, shape, fortran_order, dtype)``.
    """
    info = zf.getinfo(name + ".npy")
    try:
        with zf.open(info) as fh:
            # Magic string (6 bytes) and version (2), then the header length:
            # 2 bytes (version 1.0) or 4 (version 2.0), checked before the
            # header is read.
            start = fh.read(8)
            if len(start) < 8 or start[:6] != b"\x93NUMPY":
                raise ValueError("not a .npy array (bad magic string)")
            if start[6:8] not in (b"\x01\x00", b"\x02\x00"):
                raise ValueError(f".npy version {start[6]}.{start[7]} (this pmjax reads 1.0 and 2.0)")
            width = 2 if start[6] == 1 else 4
            size = fh.read(width)
            length = int.from_bytes(size, "little")
            if len(size) < width or length > NPY_HEADER_LIMIT:
                raise ValueError(f".npy header of {length} bytes (at most {NPY_HEADER_LIMIT})")
            text = fh.read(length)
        buf = io.BytesIO(start + size + text)
        version = np.lib.format.read_magic(buf)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read(buf)
    except Exception as exc:  # a damaged entry, a bad .npy header
        raise PMFormatError(f"{path}: array {name!r} is unreadable ({type(exc).__name__}: {exc})") from exc
    spec = np.dtype({**ARRAY_SPECS, **OPTIONAL_ARRAY_SPECS}[name][0])
    entry = f"{path}: array {name!r} (entry {info.filename})"
    if dtype != spec:
        raise PMFormatError(f"{entry} has dtype {dtype}, expected {spec}")
    if shape != want:
        raise PMFormatError(f"{entry} has shape {shape}, but the header counts {counts} give {want}; "
                            "the file is damaged or forged")
    offset = len(start) + len(size) + len(text)
    need = offset + math.prod(shape) * dtype.itemsize
    if info.file_size != need:
        raise PMFormatError(f"{entry} declares {info.file_size} bytes uncompressed, but its .npy header (shape "
                            f"{shape}, {dtype}) needs {need}; the file is damaged or forged")
    return offset, shape, fortran, dtype


def _read_npy(zf: zipfile.ZipFile, path: str, name: str, offset: int, shape, fortran: bool, dtype) -> np.ndarray:
    """The data of array ``name``, reading exactly the bytes its checked
    ``.npy`` header needs (the zip entry's CRC is checked at its end)."""
    count = math.prod(shape)
    nbytes = count * dtype.itemsize
    try:
        with zf.open(name + ".npy") as fh:
            # One read of the whole entry (header and data): no copy of the
            # data between reads.
            raw = fh.read(offset + nbytes)
    except Exception as exc:  # a damaged entry: a bad CRC, a truncated stream
        raise PMFormatError(f"{path}: array {name!r} is unreadable ({type(exc).__name__}: {exc})") from exc
    if len(raw) != offset + nbytes:
        raise PMFormatError(f"{path}: array {name!r} is unreadable (its zip entry ends after {len(raw)} "
                            f"of {offset + nbytes} bytes)")
    a = np.frombuffer(raw, dtype=dtype, count=count, offset=offset).copy()
    return a.reshape(shape[::-1]).transpose() if fortran else a.reshape(shape)


def content_fingerprint(sums: dict) -> str:
    """SHA-256 over the arrays' SHA-256s: names a hierarchy's content."""
    return hashlib.sha256(json.dumps(sums, sort_keys=True).encode()).hexdigest()


def validate_pm(pm: PMData, *, source: str = "<memory>") -> None:
    """Check dtypes, shapes, index ranges and the hierarchy rules of docs/format.md.

    Checks the structure that every consumer relies on: created vertices are
    made by earlier batches, each vertex is consumed at most once, killers and
    batch offsets are in range, attributes are finite and non-negative.

    Raises:
        PMFormatError: naming ``source`` and the first offending element.
    """
    P = len(pm.v1)
    V = len(pm.vertices)
    V0 = V - P
    F = len(pm.faces)
    sizes = dict(V=V, F=F, P=P, B1=len(pm.batch_offsets), **{"3": 3})
    specs = [(name, spec, False) for name, spec in ARRAY_SPECS.items()]
    specs += [(name, spec, True) for name, spec in OPTIONAL_ARRAY_SPECS.items()]
    for name, (dtype, shape), optional in specs:
        a = getattr(pm, name)
        if a is None and optional:
            continue
        if not isinstance(a, np.ndarray):
            raise PMFormatError(f"{source}: {name} is not an array")
        if a.dtype != np.dtype(dtype):
            raise PMFormatError(f"{source}: {name} has dtype {a.dtype}, expected {dtype}")
        want = tuple(sizes[s] for s in shape)
        if a.shape != want:
            raise PMFormatError(f"{source}: {name} has shape {a.shape}, expected {want}")
    if V0 < 1 or F < 1:
        raise PMFormatError(f"{source}: empty mesh (V0={V0}, F={F})")

    def first_bad(mask, what):
        if not mask.any():
            return
        bad = np.flatnonzero(mask)
        if len(bad):
            raise PMFormatError(f"{source}: {what} (first at index {int(bad[0])})")

    def first_bad_row(mask, what):
        # Row reductions of [N, 3] masks are slow: only run one when a bad element exists.
        if mask.any():
            first_bad(mask.any(axis=1), what)

    first_bad_row(~np.isfinite(pm.vertices), "non-finite vertex position")
    first_bad_row(~np.isfinite(pm.normals), "non-finite vertex normal")
    if pm.shading_normals is not None:
        shading = pm.shading_normals
        first_bad_row(~np.isfinite(shading), "non-finite shading normal")
        length = np.sqrt(np.einsum("ij,ij->i", shading, shading, dtype=np.float64))
        first_bad((length != 0) & (np.abs(length - 1) > SHADING_UNIT_TOLERANCE),
                  "shading normal neither unit length nor zero (re-save the mesh with pmjax.fitted_normals)")
    first_bad_row((pm.faces < 0) | (pm.faces >= V0), "face index out of range [0, V0)")
    off = pm.batch_offsets
    if off[0] != 0 or off[-1] != P or np.any(np.diff(off) < 0):
        raise PMFormatError(f"{source}: batch_offsets must rise from 0 to P={P}")
    # A pcol of batch b may only use vertices created before batch b starts.
    batch_of = np.repeat(np.arange(len(off) - 1), np.diff(off))
    limit = V0 + off[batch_of]
    for name in ("v1", "v2"):
        idx = getattr(pm, name)
        first_bad((idx < 0) | (idx >= limit), f"{name} refers to a vertex not created before its batch")
    first_bad(pm.v1 == pm.v2, "pcol with v1 == v2")
    # A counting pass, not np.unique: O(V), without a sort.
    counts = np.bincount(np.concatenate([pm.v1, pm.v2]), minlength=V)
    if counts.max(initial=0) > 1:
        raise PMFormatError(
            f"{source}: vertex {int(np.argmax(counts))} is consumed by more than one pcol"
        )
    first_bad((pm.killer < -1) | (pm.killer >= P), "killer out of range [-1, P)")
    for name in ("radius", "alpha", "delta", "mu"):
        a = getattr(pm, name)
        first_bad(~np.isfinite(a) | (a < 0), f"{name} negative or non-finite")
    first_bad(pm.metric >= len(METRICS), "unknown metric id")


