"""Reading, cleaning and writing mesh files.

Files are parsed by trimesh, after checks of their own: the contents must be
the format the extension names, and PLY, OBJ, OFF and STL data must match
their headers (counts, sizes) and hold integer face indices (1-based in OBJ).
A file that fails is refused with a :class:`MeshError` naming the file, the
element and the line or byte at fault.

The cleaning is explicit and reported, so a user knows what was changed:
non-finite coordinates, out-of-range indices, degenerate and duplicate faces
and unreferenced vertices are either removed (with a count in the report) or,
when nothing usable is left, refused with a :class:`MeshError` that names the
file and the element. A triangle soup (an STL file: no vertex shared by two
faces) is welded first, merging vertices whose coordinates are equal in
float32, the precision pmjax stores.

Meshes are written (:func:`write_mesh`) as .ply, .obj, .off, .stl or .glb.
"""

from __future__ import annotations

import dataclasses
import io
import os
import re

import numpy as np


class MeshError(ValueError):
    """An input mesh cannot be used; the message names the file and element."""


@dataclasses.dataclass(frozen=True)
class CleanReport:
    """What :func:`clean_mesh` changed. All counts are of removed elements."""

    nonfinite_vertices: int = 0
    out_of_range_faces: int = 0
    faces_on_nonfinite_vertices: int = 0
    degenerate_faces: int = 0
    duplicate_faces: int = 0
    unreferenced_vertices: int = 0
    welded_vertices: int = 0  # merged into another vertex, not lost

    def messages(self) -> list[str]:
        """Human-readable lines, one per non-zero count."""
        out = []
        for field in dataclasses.fields(self):
            n = getattr(self, field.name)
            if n and field.name == "welded_vertices":
                out.append(f"welded a triangle soup: merged {n} vertices into others with equal float32 "
                           "coordinates (tolerance: float32 rounding)")
            elif n:
                out.append(f"removed {n} {field.name.replace('_', ' ')}")
        return out


def weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge vertices whose coordinates are equal once rounded to float32.

    Returns:
        ``(vertices, faces, kept)``: the first of each group of equal vertices
        is kept, in input order (``kept``: their input indices), and faces
        are renumbered to them.
    """
    _, first, inverse = np.unique(vertices.astype(np.float32), axis=0, return_index=True, return_inverse=True)
    # Keep the kept vertices in input order (np.unique sorts them).
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return vertices[first[order]], rank[inverse.ravel()][faces], first[order]


# Largest float32 spacing allowed at the model's farthest coordinate, as a
# share of its bounding-box diagonal (reached ~128 diagonals from the origin).
PRECISION_LIMIT = 2.0 ** -16


def check_float32_precision(vertices: np.ndarray, *, source: str = "<array>") -> None:
    """Refuse a model that float32 positions, which pmjax stores, would damage.

    Coordinates already exact in float32 lose nothing. Otherwise the float32
    spacing at the largest coordinate must stay below ``PRECISION_LIMIT`` of the
    bounding-box diagonal: a small model far from the origin (a survey offset)
    would otherwise collapse onto a few points.

    Raises:
        MeshError: naming ``source``, the offset, the size and the remedy.
    """
    v = np.asarray(vertices, np.float64)
    v = v[np.all(np.isfinite(v), axis=1)]
    if len(v) == 0 or np.array_equal(v.astype(np.float32).astype(np.float64), v):
        return
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    far = float(np.abs(v).max())
    spacing = float(np.spacing(np.float32(far)))
    if spacing > PRECISION_LIMIT * diag:
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        raise MeshError(
            f"{source}: coordinates reach {far:.6g} but the model is only {diag:.6g} across: pmjax stores float32 "
            f"positions, spaced {spacing:.3g} there ({spacing / diag:.1e} of the model), which would merge its "
            f"vertices. Translate the model near the origin first (its bounding-box centre is "
            f"{np.array2string(centre, precision=6)})"
        )


def is_soup(faces: np.ndarray, n_vertices: int) -> bool:
    """Whether no vertex is shared by two faces (and there are two faces or more)."""
    return len(faces) > 1 and int(np.bincount(faces.ravel(), minlength=n_vertices).max()) <= 1


def clean_mesh(
    vertices, faces, *, source: str = "<array>", weld_soup: bool | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, CleanReport]:
    """Validate and clean a triangle mesh.

    Args:
        vertices: ``(V, 3)`` coordinates, any real dtype.
        faces: ``(F, 3)`` integer vertex indices.
        source: name used in error messages (usually the file path).
        weld_soup: weld vertices with equal float32 coordinates first
            (:func:`weld`); ``None`` welds a triangle soup only (no vertex
            shared by two faces, as STL files store meshes).

    Returns:
        ``(vertices float64[V', 3], faces int32[F', 3], kept int64[V'], report)``
        where ``kept[i]`` is the input index of output vertex ``i`` (for a
        welded mesh, the first input vertex of its group).

    Raises:
        MeshError: wrong shapes or dtypes, or no valid face left.
    """
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"{source}: vertices must have shape (V, 3), got {v.shape}")
    if f.size == 0:
        raise MeshError(f"{source}: mesh has no faces")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(
            f"{source}: faces must be triangles with shape (F, 3), got {f.shape}"
        )
    if not np.issubdtype(v.dtype, np.number) or np.iscomplexobj(v):
        raise MeshError(f"{source}: vertex coordinates must be real numbers, got {v.dtype}")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{source}: face indices must be integers, got {f.dtype}")
    v = v.astype(np.float64)
    f = f.astype(np.int64)
    nv = len(v)

    # Faces pointing outside the vertex array cannot be repaired: drop them.
    in_range = np.all((f >= 0) & (f < nv), axis=1)
    out_of_range = int((~in_range).sum())
    f = f[in_range]

    # A triangle soup has one vertex per corner: weld it, or every face would
    # be its own part. Welded ids stand for their group's first input vertex.
    original_ids = np.arange(nv)
    welded = 0
    if weld_soup or (weld_soup is None and is_soup(f, nv)):
        v, f, original_ids = weld(v, f)
        welded, nv = nv - len(v), len(v)

    # Non-finite coordinates poison every quadric they touch: drop the vertex
    # and the faces that use it.
    finite = np.all(np.isfinite(v), axis=1)
    nonfinite = int((~finite).sum())
    on_bad = ~np.all(finite[f], axis=1)
    f = f[~on_bad]

    # Degenerate faces: repeated corners or (numerically) zero area.
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    diag = np.linalg.norm(np.ptp(v[finite], axis=0)) if finite.any() else 0.0
    zero_area = np.linalg.norm(cross, axis=1) <= (1e-14 * diag * diag)
    degenerate = repeated | zero_area
    f = f[~degenerate]

    # Duplicate faces: the same corner set, whatever the order or winding.
    if len(f):
        key = np.sort(f, axis=1)
        _, first = np.unique(key, axis=0, return_index=True)
        first.sort()
        duplicates = len(f) - len(first)
        f = f[first]
    else:
        duplicates = 0

    if len(f) == 0:
        raise MeshError(
            f"{source}: no valid face left after cleaning "
            f"({out_of_range} out of range, {nonfinite} non-finite vertices, "
            f"{int(degenerate.sum())} degenerate)"
        )

    # Unreferenced vertices carry no surface: compact them away.
    used = np.zeros(nv, bool)
    used[f.ravel()] = True
    kept = np.flatnonzero(used)
    remap = np.full(nv, -1, np.int64)
    remap[kept] = np.arange(len(kept))
    report = CleanReport(
        nonfinite_vertices=nonfinite,
        out_of_range_faces=out_of_range,
        faces_on_nonfinite_vertices=int(on_bad.sum()),
        degenerate_faces=int(degenerate.sum()),
        duplicate_faces=int(duplicates),
        # Non-finite vertices lose all their faces, so they are never kept.
        unreferenced_vertices=int(nv - len(kept) - nonfinite),
        welded_vertices=welded,
    )
    # Judged on what is kept: cleaning may leave a smaller model.
    check_float32_precision(v[kept], source=source)
    return v[kept], remap[f].astype(np.int32), original_ids[kept], report


# -- reading mesh files -----------------------------------------------------------
#
# trimesh parses the files; pmjax first checks what trimesh would accept
# silently or report misleadingly: a header whose counts do not match the data,
# face indices that are not integers, 0-based OBJ indices, a file whose
# contents are not the format its extension names. Text is decoded here
# (UTF-8, or UTF-16/32 with a byte-order mark), so trimesh never guesses an
# encoding. Binary data is checked by sizes and with vectorised reads only.


def shown_name(path) -> str:
    """A file name as messages print it: the name itself when it is printable
    UTF-8, otherwise with each undecodable byte as ``\\xNN`` and each control
    character escaped, so that a message can always be printed and logged."""
    text = os.fsencode(os.fspath(path)).decode("utf-8", "backslashreplace")
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


# What pmjax checks before trimesh parses: extension -> format.
_CHECKED = {".ply": "ply", ".obj": "obj", ".off": "off", ".stl": "stl", ".glb": "glb"}
_SUFFIX = {"ply": ".ply", "obj": ".obj", "off": ".off", "stl": ".stl", "glb": ".glb", "gltf": ".gltf"}
_LOOKS = {
    "ply": "a PLY file",
    "obj": "OBJ text",
    "off": "an OFF file",
    "stl": "an STL file",
    "glb": "a binary glTF (.glb) file",
    "gltf": "glTF JSON (.gltf)",
    "json": "JSON text",
    "xml": "XML text",
    "pmz": "a pmjax progressive mesh (.pmz)",
    "zip": "a ZIP archive",
    "text": "text in no mesh format pmjax recognises",
    "binary": "binary data in no mesh format pmjax recognises",
    "empty": "empty",
}
_HEAD = 1 << 16  # bytes read to recognise a format
_MAX_PLY_HEADER = 1 << 24

_INT = rb"[+-]?\d+"
_NUM = rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?i:nan|inf(?:inity)?)"
_INT_RE = re.compile(_INT + rb"\Z")
_NUM_RE = re.compile(rb"(?:" + _NUM + rb")\Z")
_OFF_KEYWORD = re.compile(rb"(?:ST)?C?N?(4?n?)OFF")  # group 1: not 3D
_OBJ_KEYWORDS = {b"v", b"vt", b"vn", b"vp", b"f", b"l", b"p", b"g", b"o", b"s", b"mtllib", b"usemtl"}


def _text_encoding(head: bytes) -> str | None:
    """The encoding of text that is not UTF-8 (a byte-order mark, or UTF-16
    without one: ASCII characters with every other byte zero); ``None`` for
    UTF-8, ASCII and binary data."""
    for bom, encoding in ((b"\xff\xfe\x00\x00", "utf-32"), (b"\x00\x00\xfe\xff", "utf-32"),
                          (b"\xff\xfe", "utf-16"), (b"\xfe\xff", "utf-16"), (b"\xef\xbb\xbf", "utf-8-sig")):
        if head.startswith(bom):
            return encoding
    sample = head[:512]
    if len(sample) >= 8 and len(sample) % 2 == 0:
        if not any(sample[1::2]) and all(32 <= b < 127 or b in b"\t\r\n" for b in sample[0::2]):
            return "utf-16-le"
        if not any(sample[0::2]) and all(32 <= b < 127 or b in b"\t\r\n" for b in sample[1::2]):
            return "utf-16-be"
    return None


def _first_words(head: bytes) -> list[bytes]:
    """The words of the first line that is not blank or a ``#`` comment."""
    for line in head.split(b"\n")[:200]:
        words = line.split(b"#", 1)[0].split()
        if words:
            return words
    return []


def _sniff(head: bytes, size: int) -> tuple[str, str]:
    """``(format, detail)`` of a file from its first bytes (already decoded to
    UTF-8 when it is UTF-16/32 text) and its size: a key of ``_LOOKS``, and
    ``"ascii"`` or ``"binary"`` where a format has both."""
    if size == 0:
        return "empty", ""
    if re.match(rb"ply[ \t]*\r?\n", head):
        form = re.search(rb"\nformat[ \t]+(\S+)", head[:200])
        return "ply", "ascii" if form and form.group(1) == b"ascii" else "binary"
    if head.startswith(b"glTF"):
        return "glb", "binary"
    if head.startswith(b"PK\x03\x04"):
        return ("pmz" if b"header.json" in head[:200] else "zip"), "binary"
    # A text file's bytes 80-84 read as a count of 0x20202020 or more, so
    # only a binary STL of that size (27 GB) could be mistaken.
    if size >= 84 and 84 + 50 * int.from_bytes(head[80:84], "little") == size:
        return "stl", "binary"
    if re.match(rb"\s*" + _OFF_KEYWORD.pattern + rb"[ \t]+BINARY", head):
        return "off", "binary"
    if b"\x00" in head:
        return "binary", ""
    words = _first_words(head)
    if not words:
        return "text", ""
    key = words[0]
    if key == b"solid":
        return "stl", "ascii"
    if _OFF_KEYWORD.fullmatch(key):
        return "off", "binary" if b"BINARY" in words[1:2] else "ascii"
    if key in _OBJ_KEYWORDS:
        return "obj", "ascii"
    if key.startswith(b"{"):
        return ("gltf" if b'"asset"' in head else "json"), "ascii"
    if key.startswith(b"<"):
        return "xml", "ascii"
    return "text", ""


def _looks(kind: str, detail: str, encoding: str | None) -> str:
    """What a file looks like, in words (``"an ASCII PLY file"``)."""
    text = {("ply", "ascii"): "an ASCII PLY file", ("ply", "binary"): "a binary PLY file",
            ("stl", "ascii"): "ASCII STL text", ("stl", "binary"): "a binary STL file"}
    text = text.get((kind, detail), _LOOKS[kind])
    if encoding and encoding != "utf-8-sig":
        text += f" ({encoding[:6].upper()} text)"
    return text


def _decode(raw: bytes, encoding: str | None) -> bytes:
    """Text as UTF-8 bytes: decoded from ``encoding`` (see :func:`_text_encoding`);
    bytes that are not UTF-8 (a comment in another code page) become U+FFFD."""
    if encoding:
        return raw.decode(encoding, "replace").encode("utf-8")
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("utf-8", "replace").encode("utf-8")
    return raw


def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh with trimesh, without any processing.

    PLY, OBJ, OFF and STL files are checked first (:func:`check_mesh_file`):
    a header whose counts do not match the data, a face index that is not a
    (1-based, for OBJ) integer, contents that are not the format the extension
    names are refused with the file, the element and the line or byte at fault.

    Args:
        path: a mesh file: ``.ply``, ``.obj``, ``.off``, ``.stl``, ``.glb``, or
            another format trimesh reads (``.gltf``, ...). A ``bytes`` path, or
            a ``str`` with undecodable bytes (``os.fsdecode``), is accepted.

    Returns:
        ``(vertices float64[V, 3], faces int64[F, 3])`` as stored in the file
        (polygons split into triangles by trimesh).

    Raises:
        MeshError: missing or unreadable file, contents that do not match the
            extension or the header, or no triangle geometry.
    """
    import trimesh

    path = os.fsdecode(os.fspath(path))
    name = shown_name(path)
    if not os.path.exists(path):
        raise MeshError(f"{name}: no such file")
    if os.path.isdir(path):
        raise MeshError(f"{name}: is a folder; give a mesh file")
    try:
        with open(path, "rb") as fh:
            source, file_type = check_mesh_file(fh, path)
            if source is fh:
                fh.seek(0)
            try:
                loaded = trimesh.load(source, file_type=file_type, process=False, force="mesh")
            except Exception as exc:  # trimesh raises many types for bad files
                if file_type == "obj":
                    _walk_obj(source.getvalue(), name)  # names the line at fault, if it finds one
                if isinstance(exc, ModuleNotFoundError) and "charset_normalizer" in str(exc):
                    raise MeshError(f"{name}: the file is not UTF-8 text; save it as UTF-8") from exc
                raise MeshError(f"{name}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    except OSError as exc:
        raise MeshError(f"{name}: cannot read the file ({exc.strerror or exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{name}: file holds no triangle mesh")
    return np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64)


def check_mesh_file(fh, path) -> tuple:
    """Check a mesh file before trimesh parses it; return what to hand trimesh.

    The contents must be the format the extension names (a file without an
    extension is read as what its contents are); PLY, OBJ, OFF and STL
    contents must then pass their format's checks.

    Args:
        fh: the file, open for reading in binary mode.
        path: its name (its extension chooses the format; messages name it).

    Returns:
        ``(source, file_type)`` for ``trimesh.load``: the file, its path, or a
        ``BytesIO`` of UTF-8 text; and the format (None: from the path).

    Raises:
        MeshError: naming the file, what its contents look like and the
            remedy, or what the format's check found (:func:`_check_binary_ply`,
            :func:`_check_ascii_ply`, :func:`_check_obj`, :func:`_check_off`,
            :func:`_check_stl`).
    """
    import trimesh

    name = shown_name(path)
    ext = os.path.splitext(path)[1].lower()
    size = os.fstat(fh.fileno()).st_size
    head = fh.read(_HEAD)
    fh.seek(0)
    encoding = _text_encoding(head)
    kind, detail = _sniff(_decode(head, encoding) if encoding else head, size)
    if kind == "empty":
        raise MeshError(f"{name}: the file is empty")
    looks = _looks(kind, detail, encoding)
    hint = f": rename it to {_SUFFIX[kind]}" if kind in _SUFFIX else ""
    if kind == "pmz":
        hint = " (pmjax info, lod, refine and the other commands read a .pmz; build reads a mesh)"
    wanted = _CHECKED.get(ext) or (kind if not ext and kind in _CHECKED.values() else None)
    if wanted is None:
        if ext.lstrip(".") not in trimesh.available_formats():
            formats = ", ".join(sorted(_CHECKED)) + " and the other formats trimesh reads"
            what = "has no extension" if not ext else f"the extension {ext!r} names no mesh format pmjax reads"
            raise MeshError(f"{name}: {what} ({formats}); its contents look like {looks}{hint}")
        if (kind in _SUFFIX and _SUFFIX[kind] != ext) or kind == "pmz":
            raise MeshError(f"{name}: is named {ext} but its contents look like {looks}{hint}")
        if os.fsencode(path).decode("utf-8", "replace") == path:
            return path, None  # a name trimesh can find companion files (.gltf buffers) from
        return fh, ext.lstrip(".")
    if wanted == "stl" and kind == "binary":
        _check_stl(head, size, name)
    if kind != wanted:
        raise MeshError(f"{name}: is named {ext} but its contents look like {looks}, not {_LOOKS[wanted]}{hint}")
    if wanted == "glb" or (detail == "binary" and wanted in ("ply", "stl") and not encoding):
        if wanted == "ply":
            _check_binary_ply(fh, head, size, name)
        return fh, wanted
    if wanted == "off" and detail == "binary":
        raise MeshError(f"{name}: is a binary OFF file, which pmjax does not read: convert it to ASCII OFF or PLY")
    if detail == "binary":
        raise MeshError(f"{name}: a binary {wanted.upper()} file in {encoding.upper()} text: the file is damaged")
    data = _decode(fh.read(), encoding)
    if wanted == "ply":
        _check_ascii_ply(data, name)
    elif wanted == "obj":
        data = _check_obj(data, name)
    elif wanted == "off":
        _check_off(data, name)
    return io.BytesIO(data), wanted


def _check_stl(head: bytes, size: int, name: str) -> None:
    """Refuse a file named .stl that is neither ASCII STL text (``solid``
    first) nor a binary STL (``84 + 50 * n`` bytes, ``n`` the triangle count
    at byte 80), naming the count and the size."""
    if size < 84:
        raise MeshError(f"{name}: {size} bytes: too short for a binary STL (an 80-byte header and a 4-byte "
                        f"triangle count) and not ASCII STL text (which starts with 'solid')")
    n = int.from_bytes(head[80:84], "little")
    room, over = divmod(size - 84, 50)
    raise MeshError(
        f"{name}: binary STL header claims {n} triangles, which take 84 + 50 × {n} = {84 + 50 * n} bytes, but the "
        f"file holds {size} bytes (room for {room} triangles{f' and {over} bytes more' if over else ''}): the count "
        f"is wrong or the file is truncated")


# PLY property types (the names of the PLY specification and their sized aliases).
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "int64": "i8", "uint64": "u8", "float16": "f2", "float": "f4", "float32": "f4", "double": "f8",
    "float64": "f8",
}


@dataclasses.dataclass
class _PlyProperty:
    name: str
    dtype: str  # numpy code of the value (of each list entry for a list)
    count_dtype: str | None = None  # numpy code of a list's length; None: a single value


@dataclasses.dataclass
class _PlyElement:
    name: str
    count: int
    line: int  # of its header line, 1-based
    properties: list


def _ply_header(data: bytes, name: str) -> tuple[str, list, int, int]:
    """Parse a PLY header.

    Returns:
        ``(format, elements, data_offset, header_lines)``: ``"ascii"``,
        ``"binary_little_endian"`` or ``"binary_big_endian"``; the elements
        (:class:`_PlyElement`) in file order; the byte where the data starts;
        the number of header lines.

    Raises:
        MeshError: naming the header line at fault.
    """
    end = re.search(rb"(?:^|\n)end_header[ \t]*\r?(?:\n|\Z)", data)
    if end is None:
        raise MeshError(f"{name}: PLY header has no end_header line")
    lines = data[: end.end()].decode("ascii", "replace").splitlines()
    form = lines[1].split()
    if len(form) != 3 or form[0] != "format" or form[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshError(f"{name}: line 2: PLY format line must be 'format ascii|binary_little_endian|"
                        f"binary_big_endian 1.0', got {lines[1][:80]!r}")
    elements = []
    for number, line in enumerate(lines[2:-1], start=3):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "element":
            if len(words) != 3 or not re.fullmatch(r"\d+", words[2]):
                raise MeshError(f"{name}: line {number}: PLY element line must be 'element NAME COUNT' "
                                f"with a whole-number count, got {line[:80]!r}")
            elements.append(_PlyElement(words[1], int(words[2]), number, []))
        elif words[0] == "property":
            if not elements:
                raise MeshError(f"{name}: line {number}: PLY property before any element")
            if len(words) == 5 and words[1] == "list":
                count_type, value_type = words[2], words[3]
            elif len(words) == 3:
                count_type, value_type = None, words[1]
            else:
                raise MeshError(f"{name}: line {number}: PLY property line must be 'property TYPE NAME' or "
                                f"'property list COUNT_TYPE TYPE NAME', got {line[:80]!r}")
            for t in (count_type, value_type):
                if t is not None and t not in _PLY_TYPES:
                    raise MeshError(f"{name}: line {number}: unknown PLY property type {t!r} (known: "
                                    f"{', '.join(_PLY_TYPES)})")
            if count_type is not None and _PLY_TYPES[count_type][0] not in "iu":
                raise MeshError(f"{name}: line {number}: a list length must have an integer type, got {count_type!r}")
            elements[-1].properties.append(_PlyProperty(words[-1], _PLY_TYPES[value_type],
                                                        count_type and _PLY_TYPES[count_type]))
        else:
            raise MeshError(f"{name}: line {number}: unknown PLY header line {line[:80]!r} (a header holds "
                            "format, element, property, comment and obj_info lines)")
    for element in elements:
        if element.name == "face":
            for prop in element.properties:
                if prop.name in ("vertex_indices", "vertex_index") and prop.dtype[0] not in "iu":
                    raise MeshError(f"{name}: PLY element 'face' (header line {element.line}): property {prop.name!r} "
                                    "holds floating-point values; face indices must be integers")
    return form[1], elements, end.end(), len(lines)


def _check_binary_ply(fh, head: bytes, size: int, name: str) -> None:
    """A binary PLY's data must be exactly what its header describes.

    Lists (a face's vertex indices) are read as trimesh reads them: every row
    of an element has the lists of its first row. Each element's size is
    compared with the bytes left, and the list lengths of every row are
    compared with the first row's in one vectorised read (a memory map), so
    a large file is never walked row by row here.

    Raises:
        MeshError: naming the element, its header line, the row or byte at
            fault, and the counts.
    """
    if b"end_header" not in head and size > len(head):
        fh.seek(0)
        head = fh.read(_MAX_PLY_HEADER)
    form, elements, pos, _ = _ply_header(head, name)
    order = "<" if form == "binary_little_endian" else ">"
    for element in elements:
        fields, offset, mixed = [], 0, False
        for k, prop in enumerate(element.properties):
            if prop.count_dtype is None:
                fields.append((f"p{k}", order + prop.dtype))
                offset += np.dtype(prop.dtype).itemsize
                continue
            count_dtype = np.dtype(order + prop.count_dtype)
            fh.seek(pos + offset)
            blob = fh.read(count_dtype.itemsize)
            if element.count and len(blob) < count_dtype.itemsize:
                raise MeshError(f"{name}: the header claims {element.count} '{element.name}' elements (header line "
                                f"{element.line}) but the file ends at byte {size}, before the first of them: "
                                f"the counts are wrong or the file is truncated")
            n = int(np.frombuffer(blob, count_dtype)[0]) if element.count else 0
            if element.count and element.name == "face" and prop.name in ("vertex_indices", "vertex_index") and n < 3:
                before = ", ".join(f"{e.count} {e.name!r}" for e in elements[: elements.index(element)])
                raise MeshError(f"{name}: 'face' element 0 (header line {element.line}) lists {n} vertices at byte "
                                f"{pos + offset}; a face needs 3 or more: the header's counts"
                                f"{f' (before it: {before})' if before else ''} are wrong or the file is damaged")
            fields += [(f"n{k}", count_dtype), (f"p{k}", order + prop.dtype, (max(n, 0),))]
            offset += count_dtype.itemsize + max(n, 0) * np.dtype(prop.dtype).itemsize
            mixed = True
        row = np.dtype(fields).itemsize if fields else 0
        have = (size - pos) // row if row else element.count
        if mixed and min(have, element.count) > 1:
            rows = np.memmap(fh, dtype=np.dtype(fields), mode="r", offset=pos, shape=(min(have, element.count),))
            for field, *_ in fields:
                if field.startswith("n"):
                    differ = np.flatnonzero(rows[field] != rows[field][0])
                    if len(differ):
                        i = int(differ[0])
                        raise MeshError(
                            f"{name}: '{element.name}' element {i} (header line {element.line}) starts with a list "
                            f"of {int(rows[field][i])} entries where element 0 has {int(rows[field][0])}: pmjax "
                            f"reads binary PLY lists of one length only (or the file is damaged); triangulate "
                            f"the mesh first")
            del rows
        if have < element.count:
            raise MeshError(
                f"{name}: the header claims {element.count} '{element.name}' elements (header line {element.line}) of "
                f"{row} bytes from byte {pos}, but the file ends at byte {size}, after {have} of them: the counts "
                f"are wrong or the file is truncated")
        pos += element.count * row
    if pos != size:
        raise MeshError(f"{name}: the file holds {size - pos} bytes after the {pos} its PLY header describes "
                        f"({', '.join(f'{e.count} {e.name!r}' for e in elements)}): the counts are wrong or the "
                        f"file is damaged")


def _ply_row_pattern(element: _PlyElement, first_count: int | None = None) -> bytes:
    """A regular expression for one ASCII row of ``element``: each value's
    syntax (integers for integer types), lists with any length, or with
    ``first_count`` entries (a single-list element's fast path)."""
    parts = []
    for prop in element.properties:
        value = _INT if prop.dtype[0] in "iu" else rb"(?:" + _NUM + rb")"
        if prop.count_dtype is None:
            parts.append(value)
        elif first_count is not None:
            parts.append(rb"0*" + str(first_count).encode() + (rb"(?:[ \t]+" + value + rb")") * first_count
                         if first_count else rb"0+")
        else:
            parts.append(_INT + rb"(?:[ \t]+" + value + rb")*")
    return rb"[ \t]*" + rb"[ \t]+".join(parts) + rb"[ \t]*\r?"


def _ply_row_problem(element: _PlyElement, tokens: list) -> str | None:
    """What is wrong with one ASCII row (its whitespace-separated tokens), or None."""
    names = ", ".join(p.name for p in element.properties)
    need, lists, kinds = 0, [], []  # values the row takes; what each list says; each value's property
    for prop in element.properties:
        if prop.count_dtype is not None:
            if need >= len(tokens):
                return (f"{len(tokens)} values where the header's properties ({names}) take more: the line ends "
                        f"before list {prop.name!r}")
            word = tokens[need]
            if not _INT_RE.match(word) or int(word) < 0:
                return f"list {prop.name!r} length {word.decode(errors='replace')!r} is not a whole number"
            if element.name == "face" and prop.name in ("vertex_indices", "vertex_index") and int(word) < 3:
                return f"list {prop.name!r} holds {int(word)} vertices; a face needs 3 or more"
            lists.append(f"list {prop.name!r} says {int(word)} entries")
            kinds += [None] + [prop] * int(word)
            need += 1 + int(word)
        else:
            kinds.append(prop)
            need += 1
    if need != len(tokens) or len(kinds) != need:
        said = f" ({'; '.join(lists)})" if lists else ""
        return f"{len(tokens)} values where the header's properties ({names}) take {max(need, len(kinds))}{said}"
    for word, prop in zip(tokens, kinds):
        if prop is None:
            continue
        integer = prop.dtype[0] in "iu"
        if not (_INT_RE if integer else _NUM_RE).match(word):
            what = ("face index" if element.name == "face" and prop.name in ("vertex_indices", "vertex_index")
                    else f"property {prop.name!r}")
            return f"{what} {word.decode(errors='replace')!r} is not {'an integer' if integer else 'a number'}"
    return None


def _check_ascii_ply(data: bytes, name: str) -> None:
    """An ASCII PLY must hold one line per element row, as many as its header
    claims, each value with its property's syntax. The rows are matched by
    regular expressions element by element; only a failing row (or the
    rows of lists of mixed lengths) are split in Python.

    Raises:
        MeshError: naming the element, the line and the value at fault.
    """
    _, elements, start, header_lines = _ply_header(data[:_MAX_PLY_HEADER], name)
    body = data[start:].rstrip()
    newlines = np.flatnonzero(np.frombuffer(body, np.uint8) == 10)
    n_lines = len(newlines) + 1 if body else 0
    claimed = sum(e.count for e in elements)
    summary = " and ".join(f"{e.count} {e.name!r}" for e in elements)
    # Blank lines between the rows (a longer line of spaces fails its row's check).
    bounds = np.concatenate([[-1], newlines, [len(body)]])
    for row in np.flatnonzero(np.diff(bounds) <= 3) if body else ():
        if not body[bounds[row] + 1:bounds[row + 1]].strip():
            raise MeshError(f"{name}: line {header_lines + 1 + row} is blank: an ASCII PLY holds one element per "
                            f"line, with no blank lines between them (the header claims {summary} elements)")
    if n_lines != claimed:
        if n_lines < claimed:
            row = 0
            for element in elements:
                if row + element.count > n_lines:
                    break
                row += element.count
            raise MeshError(
                f"{name}: the header claims {summary} elements, one per line ({claimed} lines), but {n_lines} "
                f"follow end_header (to line {header_lines + n_lines}): element {element.name!r} (header line "
                f"{element.line}) has {n_lines - row} of its {element.count} rows; the counts are wrong or the "
                f"file is truncated")
        raise MeshError(f"{name}: line {header_lines + claimed + 1}: {n_lines - claimed} more lines follow the "
                        f"{claimed} the header claims ({summary} elements): the counts are wrong or the file is "
                        f"damaged")

    def line_start(row):
        return 0 if row == 0 else int(newlines[row - 1]) + 1

    def line_end(row):
        return int(newlines[row]) if row < len(newlines) else len(body)

    def refuse(element, index, row, problem):
        raise MeshError(f"{name}: line {header_lines + row + 1}: {element.name} {index}: {problem}")

    row = 0
    for element in elements:
        if element.count == 0:
            continue
        first, last = row, row + element.count
        block = body[line_start(first):line_end(last - 1)]
        lists = sum(p.count_dtype is not None for p in element.properties)
        bad = None
        if lists == 0:
            bad = re.search(rb"^(?!" + _ply_row_pattern(element) + rb"$)", block, re.M)
        elif lists == 1:
            # Fast path: every row's list as long as the first row's (checked
            # alone first: its length is the pattern's).
            tokens = body[line_start(first):line_end(first)].split()
            problem = _ply_row_problem(element, tokens)
            if problem:
                refuse(element, 0, first, problem)
            k = [p.count_dtype is not None for p in element.properties].index(True)
            bad = re.search(rb"^(?!" + _ply_row_pattern(element, int(tokens[k])) + rb"$)", block, re.M)
            if bad is not None:
                # Lists of other lengths from there on (triangles and quads):
                # the rest is checked row by row.
                for r in range(first + block.count(b"\n", 0, bad.start()), last):
                    problem = _ply_row_problem(element, body[line_start(r):line_end(r)].split())
                    if problem:
                        refuse(element, r - first, r, problem)
                bad = None
        else:
            for r in range(first, last):
                problem = _ply_row_problem(element, body[line_start(r):line_end(r)].split())
                if problem:
                    refuse(element, r - first, r, problem)
        if bad is not None:
            r = first + block.count(b"\n", 0, bad.start())
            refuse(element, r - first, r,
                   _ply_row_problem(element, body[line_start(r):line_end(r)].split()) or "unreadable values")
        row = last


class _Text:
    """The lines and whitespace-separated tokens of a text, found with
    vectorised numpy: large files are checked without a Python loop over
    their lines. Lines are numbered from 0 here (messages add 1).

    Args:
        data: the text, UTF-8 bytes.
        comments: blank ``#`` comments (to the end of their line) first.
    """

    def __init__(self, data: bytes, comments: bool = False):
        a = np.frombuffer(data, np.uint8)
        self.starts = np.concatenate([[0], np.flatnonzero(a == 10) + 1])
        self.ends = np.concatenate([self.starts[1:] - 1, [len(a)]])
        if comments and b"#" in data:
            hashes = np.flatnonzero(a == 35)
            line = np.searchsorted(self.starts, hashes, "right") - 1
            first = np.concatenate([[True], line[1:] != line[:-1]])
            a = a.copy()
            a[self._spans(hashes[first], self.ends[line[first]], len(a))] = 32
            data = a.tobytes()
        self.data, self.array = data, a
        # ASCII whitespace, as bytes.split() sees it: space, and \t \n \v \f \r (9 to 13).
        space = np.ones(len(a) + 2, bool)
        space[1:-1] = (a == 32) | (a - np.uint8(9) <= 4)
        edge = np.flatnonzero(space[1:] != space[:-1])
        self.token_starts, self.token_ends = edge[0::2], edge[1::2]
        # Tokens of line i: line_tokens[i] to line_tokens[i + 1].
        self.line_tokens = np.concatenate([np.searchsorted(self.token_starts, self.starts), [len(self.token_starts)]])
        self.tokens_per_line = np.diff(self.line_tokens)

    @staticmethod
    def _spans(begins, ends, n):
        """Boolean mask of ``n`` bytes, true in the ranges ``[begins, ends)``
        (sorted, disjoint)."""
        bounds = np.empty(2 * len(begins) + 2, np.int64)
        bounds[0], bounds[-1] = 0, n
        bounds[1:-1:2], bounds[2:-1:2] = begins, ends
        inside = np.zeros(len(bounds) - 1, bool)
        inside[1::2] = True
        return np.repeat(inside, np.diff(bounds))

    def words(self, line: int) -> list:
        """The tokens of a line (comments blanked)."""
        return self.data[self.starts[line]:self.ends[line]].split()

    def keywords(self) -> np.ndarray:
        """Each line's first token when it is one byte (its code), else -1."""
        t = self.line_tokens[:-1]
        code = np.full(len(t), -1, np.int64)
        has = self.tokens_per_line > 0
        start = self.token_starts[t[has]]
        one = self.token_ends[t[has]] - start == 1
        code[np.flatnonzero(has)[one]] = self.array[start[one]]
        return code

    def values(self, tokens, dtype=np.float64, ends=None):
        """The tokens ``tokens`` (indices, ascending) parsed as numbers of
        ``dtype`` (each cut at ``ends``, byte offsets, where given), or None
        when one is not such a number."""
        tokens = np.asarray(tokens, np.int64)
        return self._parse(self.token_starts[tokens], self.token_ends[tokens] if ends is None else ends,
                           len(tokens), dtype)

    def line_values(self, lines, skip: int = 0, dtype=np.float64):
        """Every token of ``lines`` (ascending, each with more than ``skip``
        tokens) but the first ``skip`` of each, parsed as in :meth:`values`."""
        lines = np.asarray(lines, np.int64)
        return self._parse(self.token_starts[self.line_tokens[lines] + skip], self.ends[lines],
                           int((self.tokens_per_line[lines] - skip).sum()), dtype)

    def _parse(self, begins, ends, count, dtype):
        """Parse the bytes in the ranges ``[begins, ends)``: ``count`` numbers, or None."""
        if count == 0:
            return np.zeros(0, dtype)
        keep = self._spans(begins, ends, len(self.array))
        buffer = np.full(len(self.array), 32, np.uint8)
        buffer[keep] = self.array[keep]
        try:
            out = np.fromstring(buffer.tobytes(), dtype=dtype, sep=" ")
        except ValueError:
            return None
        return out if len(out) == count else None


def _ragged(starts, lengths) -> np.ndarray:
    """``concatenate([arange(s, s + n) for s, n in zip(starts, lengths)])``, vectorised."""
    lengths = np.asarray(lengths, np.int64)
    offsets = np.cumsum(lengths) - lengths
    return np.repeat(np.asarray(starts, np.int64) - offsets, lengths) + np.arange(int(lengths.sum()))


_OBJ_FACE_BYTES = np.zeros(256, bool)  # the bytes of plain face lines: "f 1 2 3", "f 1/1/1 2//2 3/3"
_OBJ_FACE_BYTES[list(b"0123456789/f \t\r\n")] = True


def _check_obj(data: bytes, name: str) -> bytes:
    """OBJ text: every ``v`` line holds three values or more, every face
    corner is a 1-based (or negative, relative) integer index in range.

    Plain files (face lines of digits, ``/`` and spaces) are proven valid
    with vectorised parsing; any other face line (a relative index, index 0,
    a sign, a line continuation) makes the file walked line by line
    (:func:`_walk_obj`), which names the line at fault. The vertex values
    are parsed by trimesh (:func:`read_mesh` walks a file it fails on).

    Returns:
        the text to parse (UTF-8 bytes): comments blanked, relative indices
        made absolute.

    Raises:
        MeshError: naming the line, the index and the remedy.
    """
    text = _Text(data, comments=True)
    code = text.keywords()
    v_lines, f_lines = np.flatnonzero(code == ord("v")), np.flatnonzero(code == ord("f"))
    tpl, first = text.tokens_per_line, text.line_tokens
    # Vertex lines need three values (trimesh parses them: a failure is walked
    # by read_mesh to name the line), faces three corners.
    plain = not (tpl[v_lines] < 4).any() and not (tpl[f_lines] < 4).any()
    if plain and len(f_lines):
        a = text.array
        face_bytes = text._spans(text.starts[f_lines], text.ends[f_lines], len(a))
        zero_after_slash = face_bytes[1:] & (a[1:] == ord("0")) & (a[:-1] == ord("/"))
        plain = not (face_bytes & ~_OBJ_FACE_BYTES[a]).any() and not zero_after_slash.any()
        slashes = np.flatnonzero(face_bytes & (a == ord("/")))
        if plain and not len(slashes):
            index = text.line_values(f_lines, skip=1, dtype=np.int64)
        elif plain:
            corners = _ragged(first[f_lines] + 1, tpl[f_lines] - 1)
            # A corner's vertex index ends at its first '/'.
            ends = text.token_ends[corners].copy()
            owner = np.searchsorted(text.token_starts, slashes, "right") - 1
            once = np.concatenate([[True], owner[1:] != owner[:-1]])[: len(owner)]
            ends[np.searchsorted(corners, owner[once])] = slashes[once]
            index = text.values(corners, np.int64, ends)
        if plain:
            plain = index is not None and (len(index) == 0 or (index.min() >= 1 and index.max() <= len(v_lines)))
    # Comments blanked: trimesh reads a face line with a trailing comment as indices.
    return text.data if plain else _walk_obj(text.data, name)


def _walk_obj(data: bytes, name: str) -> bytes:
    """Check an OBJ line by line (see :func:`_check_obj`); return it with
    relative indices made absolute."""
    counts = {b"v": 0, b"vt": 0, b"vn": 0}
    total = len(re.findall(rb"^[ \t]*v[ \t]", data, re.M))
    lines = data.split(b"\n")
    changed = False
    for number, line in enumerate(lines, start=1):
        words = line.split(b"#", 1)[0].split()
        if not words:
            continue
        key = words[0]
        if key in counts:
            counts[key] += 1
            if key == b"v":
                if len(words) < 4:
                    raise MeshError(f"{name}: line {number}: vertex {counts[key]} has {len(words) - 1} "
                                    f"coordinates; a vertex needs 3")
                for word in words[1:]:
                    if not _NUM_RE.match(word):
                        raise MeshError(f"{name}: line {number}: vertex {counts[key]}: coordinate "
                                        f"{word.decode(errors='replace')!r} is not a number")
            continue
        if key != b"f":
            continue
        if words[-1].endswith(b"\\"):
            raise MeshError(f"{name}: line {number} ends with '\\' (a line continuation), which pmjax does not "
                            "read: join it with the next line")
        if len(words) < 4:
            raise MeshError(f"{name}: line {number}: a face needs 3 corners or more, this one has {len(words) - 1}")
        corners = []
        for word in words[1:]:
            parts = word.split(b"/")
            for slot, (part, what) in enumerate(zip(parts, (b"v", b"vt", b"vn"))):
                if slot and not part:
                    continue
                label = {b"v": "vertex", b"vt": "texture", b"vn": "normal"}[what]
                if not _INT_RE.match(part):
                    raise MeshError(f"{name}: line {number}: face {label} index {part.decode(errors='replace')!r} "
                                    f"is not an integer")
                index = int(part)
                if index == 0:
                    raise MeshError(
                        f"{name}: line {number}: face {label} index 0: OBJ indices start at 1 (negative ones count "
                        f"back from the last {label} before the face); the file looks written with 0-based indices: "
                        f"export it again with 1-based ones")
                if index < 0:
                    absolute = counts[what] + 1 + index
                    if absolute < 1:
                        raise MeshError(
                            f"{name}: line {number}: face {label} index {index} reaches before the first {label} "
                            f"(only {counts[what]} are declared above the face)")
                    parts[slot] = str(absolute).encode()
                    changed = True
                elif what == b"v" and index > total:
                    raise MeshError(f"{name}: line {number}: face vertex index {index} but the file declares "
                                    f"{total} vertices")
            if len(parts) > 3:
                raise MeshError(f"{name}: line {number}: face corner {word.decode(errors='replace')!r} has more than "
                                f"three indices (v/vt/vn)")
            corners.append(b"/".join(parts))
        if changed:
            lines[number - 1] = b"f " + b" ".join(corners)
    return b"\n".join(lines) if changed else data


_OFF_COUNTS = re.compile(rb"\d+")


def _check_off(data: bytes, name: str) -> None:
    """An ASCII OFF: the keyword, ``V F E`` counts, then exactly V vertex lines
    (three numbers or more) and F face lines (``n`` then ``n`` integer
    indices below V, then optional colour values); ``#`` starts a comment.

    The lines are checked with vectorised parsing; a failing file is walked
    line by line to name the line at fault.

    Raises:
        MeshError: naming the line, the element and the counts.
    """
    text = _Text(data, comments=True)
    content = np.flatnonzero(text.tokens_per_line > 0)
    words = text.words(content[0])
    match = _OFF_KEYWORD.fullmatch(words[0])
    if match is None or match.group(1):
        raise MeshError(f"{name}: line {content[0] + 1}: OFF keyword {words[0].decode(errors='replace')!r}: pmjax "
                        "reads 3D OFF files ([ST][C][N]OFF)")
    counts, items = words[1:], content[1:]
    count_line = content[0] + 1
    if not counts:
        if not len(items):
            raise MeshError(f"{name}: no vertex and face counts after the OFF keyword")
        counts, count_line, items = text.words(items[0]), items[0] + 1, items[1:]
    if len(counts) < 2 or not all(_OFF_COUNTS.fullmatch(w) for w in counts[:3]):
        raise MeshError(f"{name}: line {count_line}: OFF counts must be whole numbers 'VERTICES FACES EDGES', "
                        f"got {b' '.join(counts).decode(errors='replace')!r}")
    nv, nf = int(counts[0]), int(counts[1])
    if len(items) < nv + nf:
        element, have, claimed = ("vertices", len(items), nv) if len(items) < nv else ("faces", len(items) - nv, nf)
        raise MeshError(
            f"{name}: line {count_line} claims {nv} vertices and {nf} faces, one per line ({nv + nf} lines), "
            f"but {len(items)} follow (to line {items[-1] + 1 if len(items) else count_line}): {have} of the "
            f"{claimed} {element}; the counts are wrong or the file is truncated")
    if len(items) > nv + nf:
        raise MeshError(f"{name}: line {items[nv + nf] + 1}: {len(items) - nv - nf} more lines follow the "
                        f"{nv} vertices and {nf} faces that line {count_line} claims: the counts are wrong or the "
                        f"file is damaged")
    vertices, faces = items[:nv], items[nv:]
    tpl, first = text.tokens_per_line, text.line_tokens
    # Lines of exactly "x y z" and "3 i j k" are parsed whole; others (colours,
    # polygons) token by token. A failing file is walked line by line.
    plain = (tpl[vertices] >= 3).all()
    if plain:
        coords = (text.line_values(vertices) if (tpl[vertices] == 3).all()
                  else text.values(_ragged(first[vertices], np.full(nv, 3))))
        plain = coords is not None
    if plain and nf:
        if (tpl[faces] == 4).all():
            index = text.line_values(faces, dtype=np.int64)
            plain = index is not None and (index[0::4] == 3).all()
            index = index.reshape(-1, 4)[:, 1:] if plain else None
        else:
            n = text.values(first[faces], np.int64)
            plain = n is not None and (n >= 3).all() and (tpl[faces] >= n + 1).all()
            index = text.values(_ragged(first[faces] + 1, n), np.int64) if plain else None
            plain = index is not None
        plain = plain and index.min() >= 0 and index.max() < nv
    if not plain:
        _walk_off(text, vertices, faces, nv, name)


def _walk_off(text: _Text, vertices, faces, nv: int, name: str) -> None:
    """Find the OFF line that failed :func:`_check_off`'s vectorised checks, line by line."""
    for i, line in enumerate(vertices):
        words = text.words(line)
        if len(words) < 3:
            raise MeshError(f"{name}: line {line + 1}: vertex {i} has {len(words)} coordinates; a vertex needs 3")
        for word in words[:3]:
            if not _NUM_RE.match(word):
                raise MeshError(f"{name}: line {line + 1}: vertex {i}: coordinate {word.decode(errors='replace')!r} "
                                "is not a number")
    for i, line in enumerate(faces):
        words = text.words(line)
        n = words[0]
        if not _INT_RE.match(n) or int(n) < 3:
            raise MeshError(f"{name}: line {line + 1}: face {i}: corner count {n.decode(errors='replace')!r}; a "
                            "face needs a whole number of 3 corners or more")
        if len(words) < int(n) + 1:
            raise MeshError(f"{name}: line {line + 1}: face {i} says {int(n)} corners but the line holds "
                            f"{len(words) - 1} values after it")
        for word in words[1 : int(n) + 1]:
            if not _INT_RE.match(word):
                raise MeshError(f"{name}: line {line + 1}: face {i}: face index {word.decode(errors='replace')!r} "
                                "is not an integer")
            if not 0 <= int(word) < nv:
                raise MeshError(f"{name}: line {line + 1}: face {i}: face index {int(word)} is outside the "
                                f"{nv} vertices (OFF indices run from 0 to {nv - 1})")


def load_clean_mesh(path):
    """:func:`read_mesh` followed by :func:`clean_mesh` (see both)."""
    v, f = read_mesh(path)
    return clean_mesh(v, f, source=shown_name(path))


# -- writing mesh files -----------------------------------------------------------

# Formats pmjax writes a mesh in (trimesh's exporters), by extension.
MESH_OUTPUTS = (".ply", ".obj", ".off", ".stl", ".glb")


def check_mesh_output(path) -> str:
    """Refuse, before any work, a mesh output whose format pmjax cannot write;
    return the format (``"ply"`` for a name without an extension, such as
    ``/dev/null``).

    Raises:
        ValueError: naming the file, the formats written, and for ``.pmz``
            the command that writes one.
    """
    name = shown_name(path)
    ext = os.path.splitext(os.fsdecode(os.fspath(path)))[1].lower()
    if not ext:
        return "ply"
    if ext in MESH_OUTPUTS:
        return ext[1:]
    formats = ", ".join(MESH_OUTPUTS[:-1]) + " or " + MESH_OUTPUTS[-1]
    if ext == ".pmz":
        raise ValueError(f"{name}: this command writes a plain mesh ({formats}); a .pmz progressive mesh is "
                         f"written by `pmjax build`")
    raise ValueError(f"{name}: pmjax writes meshes as {formats}, not {ext}")


def write_mesh(path, vertices, faces) -> None:
    """Write a triangle mesh atomically (a temporary file, then a rename: see
    :func:`pmjax._atomic.atomic_path`), in the format of its extension.

    Args:
        path: output file (:data:`MESH_OUTPUTS`; no extension: PLY).
        vertices: ``(V, 3)`` coordinates.
        faces: ``(F, 3)`` integer indices into ``vertices``.

    Raises:
        ValueError: an extension pmjax does not write (:func:`check_mesh_output`),
            arrays of the wrong shape, or indices out of range.
    """
    import trimesh
    from trimesh.exchange.export import export_mesh

    from pmjax._atomic import atomic_path

    file_type = check_mesh_output(path)
    v = np.asarray(vertices)
    f = np.asarray(faces)
    name = shown_name(path)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{name}: a mesh needs (V, 3) vertices and (F, 3) integer faces, got {v.shape} and "
                         f"{f.shape} {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"{name}: face indices run from {f.min()} to {f.max()} but there are {len(v)} vertices")
    data = export_mesh(trimesh.Trimesh(v, f, process=False), None, file_type=file_type)
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_path(path, "." + file_type) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def default_model_path() -> str:
    """Path of the model shipped in the package (Keenan Crane's Spot, public domain)."""
    return os.path.join(os.path.dirname(__file__), "data", "spot.ply")
