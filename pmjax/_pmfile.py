"""The ``.pmz`` progressive-mesh file: flat arrays plus a JSON header.

A ``.pmz`` is a zip archive (numpy's ``.npz`` layout) holding one ``.npy`` per
array and ``header.json``. The header carries a magic string, a format version,
the counts, the build parameters, a SHA-256 of the source mesh and a SHA-256 of
every array (in :data:`ARRAY_SPECS` order), so truncation or tampering is caught
on load. See ``docs/format.md``.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import zipfile
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ._atomic import atomic_path
from ._pmdata import ARRAY_SPECS, METRICS, OPTIONAL_ARRAY_SPECS, PMData, PMFormatError  # noqa: F401 (re-exported)
from ._structure import check_structure, remember_structure, structure_known

MAGIC = "pmjax.progressive-mesh"
VERSION = 1
# Largest header.json read, bytes: it holds counts, build parameters and
# checksums (a few KiB), so a larger one is damaged or forged.
HEADER_LIMIT = 1 << 20
# Largest .npy header read, bytes (numpy writes 128, and refuses over 10000).
NPY_HEADER_LIMIT = 10000

# Largest distance from 1 of a stored shading normal's length: float32
# rounding of a normalized vector is below 1e-6.
SHADING_UNIT_TOLERANCE = 1e-4


def _sha256(a: np.ndarray) -> str:
    # Hash the array's memory directly (no tobytes() copy).
    return hashlib.sha256(np.ascontiguousarray(a).ravel().view(np.uint8)).hexdigest()


def save_pm(pm: PMData, path: str | os.PathLike) -> None:
    """Write ``pm`` to ``path`` atomically (temporary file, then rename).

    The arrays are first checked with :func:`validate_pm` and
    :func:`pmjax.check_structure`, so an inconsistent progressive mesh is
    never written.
    """
    path = os.fspath(path)
    validate_pm(pm, source=path)
    check_structure(pm, source=path)
    sums = {name: _sha256(a) for name, a in pm.arrays().items()}
    header = dict(pm.header)
    header.update(
        magic=MAGIC,
        version=VERSION,
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
            with zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_STORED) as zf:
                zf.writestr("header.json", json.dumps(header, indent=1, sort_keys=True))
                for name, a in pm.arrays().items():
                    buf = io.BytesIO()
                    np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
                    zf.writestr(name + ".npy", buf.getvalue())
            fh.flush()
            os.fsync(fh.fileno())
    # Checked above: a later load of these bytes need not check again.
    remember_structure(content_fingerprint(sums))


def file_sha256(path) -> str:
    """SHA-256 of a file's bytes, hex (a PM's source checksum; an evaluation
    job's record of its models and camera files)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def read_pm(path: str | os.PathLike) -> PMData:
    """Read and fully validate a ``.pmz`` file, its structure included
    (:func:`pmjax.check_structure`), unless content with the same array
    checksums passed that check before on this machine
    (:func:`pmjax.structure_known`).

    Raises:
        PMFormatError: naming the file and what is wrong (magic, version, a
            missing array, a dtype or shape, an index range, a checksum, the
            structure).
    """
    pm, fingerprint = read_arrays(path)
    if not structure_known(fingerprint):
        check_structure(pm, source=os.fspath(path))
        remember_structure(fingerprint)
    return pm


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


def read_arrays(path: str | os.PathLike) -> tuple[PMData, str]:
    """Read a ``.pmz`` file with every check but the structure check.

    Nothing is read beyond what the header's counts allow: every array's
    ``.npy`` header (dtype, shape) is read first and checked against the
    counts, and each zip entry's declared size against its ``.npy`` header,
    before any array data is read; data is then read with that bound, so an
    entry that expands past its declared size (a zip bomb) is not expanded.

    Returns:
        ``(pm, fingerprint)``: the fingerprint is a SHA-256 over the arrays'
        checksums, verified against the bytes read, so it names the content.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise PMFormatError(f"{path}: no such file")
    try:
        zf = zipfile.ZipFile(path, "r")
    except Exception as exc:  # zipfile raises several types for a damaged archive
        kind = _mesh_kind(path)
        if kind:  # a mesh given where a progressive mesh is needed
            article = "an" if kind[0] in "AEFHILMNORSX" else "a"  # as the letters are spoken
            raise PMFormatError(f"{path}: is {article} {kind} mesh, not a .pmz progressive mesh; make one with "
                                f"`pmjax build {path} -o model.pmz`") from exc
        raise PMFormatError(f"{path}: not a .pmz progressive mesh (not a zip archive: {exc}); "
                            f"`pmjax build MESH -o model.pmz` makes one") from exc
    with zf:
        names = set(zf.namelist())
        if "header.json" not in names:
            raise PMFormatError(f"{path}: not a pmjax file (no header.json)")
        header = _read_header(zf, path)
        if not isinstance(header, dict) or header.get("magic") != MAGIC:
            raise PMFormatError(f"{path}: bad magic (expected {MAGIC!r})")
        if header.get("version") != VERSION:
            raise PMFormatError(
                f"{path}: unsupported format version {header.get('version')!r} "
                f"(this pmjax reads version {VERSION})"
            )
        sums = header.get("array_sha256")
        if not isinstance(sums, dict):
            raise PMFormatError(f"{path}: header has no array checksums")
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
    # hashlib releases the GIL on large buffers: hash the arrays in parallel.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        digests = dict(zip(arrays, pool.map(_sha256, arrays.values())))
    for name, digest in digests.items():
        if digest != sums.get(name):
            raise PMFormatError(f"{path}: checksum mismatch in array {name!r}")
    meta = {k: v for k, v in header.items() if k not in ("array_sha256",)}
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
    # A counting pass, not np.unique: it is O(V) and ~100x faster on the dragon.
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


