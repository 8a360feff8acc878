"""Reading, checking and writing mesh files.

Formats: PLY (ASCII and binary), OBJ, OFF (ASCII) and STL (ASCII and binary)
are checked by pmjax and then parsed by trimesh; binary glTF (.glb) is
recognised and handed to trimesh; other formats trimesh reads (.gltf, ...)
are handed to it when the contents do not look like another format. Meshes
are written (:func:`write_mesh`) as .ply, .obj, .off, .stl or .glb
(:data:`MESH_OUTPUTS`), atomically.

Checked before trimesh parses a file, because trimesh would accept it
silently or report it misleadingly:

- the contents are the format the extension names, recognised from the
  first bytes (a file without an extension is read as what it holds);
- text is decoded here, so trimesh never guesses an encoding: UTF-8, or
  UTF-16/32 (a byte-order mark, or UTF-16 ASCII without one); bytes that are
  not UTF-8 (a comment in another code page) become U+FFFD;
- a PLY header is well formed and the data is exactly what it describes
  (element counts, sizes, one line per row in ASCII, one list length per
  element in binary), with integer face indices;
- OBJ vertices have three coordinates or more and face indices are integers,
  1-based or negative (relative indices are made absolute), within the
  vertices declared;
- an OFF file holds the vertex and face lines its counts claim, with
  integer indices within the vertices;
- a binary STL's size matches its triangle count.

Large files are checked with vectorised numpy (a memory map for binary PLY
lists); Python walks the lines only to name the line of a failure, and the
rows of ASCII PLY lists of mixed lengths.

Messages: a file that fails is refused with a :class:`MeshError` (a
``ValueError``) naming the file (:func:`shown_name`: printable even when the
name is not UTF-8), the element, the line or byte at fault, what was
expected, and the remedy (rename the file, fix the counts, export with
1-based indices, triangulate, convert to ASCII). An output name pmjax cannot
write is refused with a ``ValueError`` naming the formats written. Cleaning
the mesh read is :mod:`pmjax._meshio`'s.
"""

from __future__ import annotations

import dataclasses
import io
import os
import re

import numpy as np


class MeshError(ValueError):
    """An input mesh cannot be used; the message names the file and element."""


def shown_name(path) -> str:
    """A file name as messages print it: the name itself when it is printable
    UTF-8, otherwise with each undecodable byte as ``\\xNN`` and each control
    character escaped, so that a message can always be printed and logged."""
    text = os.fsencode(os.fspath(path)).decode("utf-8", "backslashreplace")
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


# -- recognising a file's format --------------------------------------------------

# The formats pmjax checks before trimesh parses them: extension -> format.
_CHECKED_FORMATS = {".ply": "ply", ".obj": "obj", ".off": "off", ".stl": "stl", ".glb": "glb"}
# The extension a file should have, by the format its contents hold (the remedy
# a message proposes).
_EXTENSIONS = {"ply": ".ply", "obj": ".obj", "off": ".off", "stl": ".stl", "glb": ".glb", "gltf": ".gltf"}
# Each format _sniff_format recognises, as messages describe it.
_DESCRIPTIONS = {
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
_SNIFF_BYTES = 1 << 16  # bytes read to recognise a format
_MAX_PLY_HEADER = 1 << 24  # bytes searched for a PLY header's end_header

# The syntax of an integer and of a number (as trimesh's parsers accept them,
# nan and inf included), alone and whole.
_INT = rb"[+-]?\d+"
_NUM = rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?i:nan|inf(?:inity)?)"
_INT_RE = re.compile(_INT + rb"\Z")
_NUM_RE = re.compile(rb"(?:" + _NUM + rb")\Z")
_OFF_KEYWORD = re.compile(rb"(?:ST)?C?N?(4?n?)OFF")  # group 1: not 3D
# The keywords an OBJ file's first line may start with.
_OBJ_KEYWORDS = {b"v", b"vt", b"vn", b"vp", b"f", b"l", b"p", b"g", b"o", b"s", b"mtllib", b"usemtl"}


def _text_encoding(head: bytes) -> str | None:
    """The encoding of text that is not UTF-8 (a byte-order mark, or UTF-16
    without one: ASCII characters with every other byte zero); ``None`` for
    UTF-8, ASCII and binary data."""
    # A byte-order mark names the encoding.
    for bom, encoding in ((b"\xff\xfe\x00\x00", "utf-32"), (b"\x00\x00\xfe\xff", "utf-32"),
                          (b"\xff\xfe", "utf-16"), (b"\xfe\xff", "utf-16"), (b"\xef\xbb\xbf", "utf-8-sig")):
        if head.startswith(bom):
            return encoding
    # UTF-16 without one: in ASCII text, every other byte is zero (the first
    # of each pair in big-endian order, the second in little-endian).
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


def _sniff_format(head: bytes, size: int) -> tuple[str, str]:
    """``(format, detail)`` of a file from its first bytes (already decoded to
    UTF-8 when it is UTF-16/32 text) and its size: a key of
    ``_DESCRIPTIONS``, and ``"ascii"`` or ``"binary"`` where a format has both."""
    if size == 0:
        return "empty", ""
    # Formats that start with a signature: PLY, binary glTF, ZIP (a .pmz is one).
    if re.match(rb"ply[ \t]*\r?\n", head):
        form = re.search(rb"\nformat[ \t]+(\S+)", head[:200])
        return "ply", "ascii" if form and form.group(1) == b"ascii" else "binary"
    if head.startswith(b"glTF"):
        return "glb", "binary"
    if head.startswith(b"PK\x03\x04"):
        return ("pmz" if b"header.json" in head[:200] else "zip"), "binary"
    if head.startswith(b"\x89PMZ\r\n\x1a\n"):  # a version 2 .pmz
        return "pmz", "binary"
    # A text file's bytes 80-84 read as a count of 0x20202020 or more, so
    # only a binary STL of that size (27 GB) could be mistaken.
    if size >= 84 and 84 + 50 * int.from_bytes(head[80:84], "little") == size:
        return "stl", "binary"
    # A binary OFF names itself on its first line; other binary data (a zero
    # byte, which text never holds) is no format pmjax recognises.
    if re.match(rb"\s*" + _OFF_KEYWORD.pattern + rb"[ \t]+BINARY", head):
        return "off", "binary"
    if b"\x00" in head:
        return "binary", ""
    # Text: recognised by the first word of its first line that is not a comment.
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


def _describe(kind: str, detail: str, encoding: str | None) -> str:
    """What a file looks like, in words (``"an ASCII PLY file"``), from
    :func:`_sniff_format`'s ``(kind, detail)`` and :func:`_text_encoding`."""
    by_detail = {("ply", "ascii"): "an ASCII PLY file", ("ply", "binary"): "a binary PLY file",
                 ("stl", "ascii"): "ASCII STL text", ("stl", "binary"): "a binary STL file"}
    text = by_detail.get((kind, detail), _DESCRIPTIONS[kind])
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


# -- reading mesh files -----------------------------------------------------------


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
    # A missing file or a folder is named plainly, not as an OSError.
    if not os.path.exists(path):
        raise MeshError(f"{name}: no such file")
    if os.path.isdir(path):
        raise MeshError(f"{name}: is a folder; give a mesh file")
    try:
        with open(path, "rb") as fh:
            source, file_type = check_mesh_file(fh, path)
            # The checks may have read on: trimesh reads the file from its start.
            if source is fh:
                fh.seek(0)
            try:
                loaded = trimesh.load(source, file_type=file_type, process=False, force="mesh")
            except Exception as exc:  # trimesh raises many types for bad files
                # An OBJ vertex value trimesh could not parse: name its line.
                if file_type == "obj":
                    _check_obj_lines(source.getvalue(), name)  # names the line at fault, if it finds one
                # A format pmjax does not check, in an encoding trimesh would guess.
                if isinstance(exc, ModuleNotFoundError) and "charset_normalizer" in str(exc):
                    raise MeshError(f"{name}: the file is not UTF-8 text; save it as UTF-8") from exc
                raise MeshError(f"{name}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    except OSError as exc:
        raise MeshError(f"{name}: cannot read the file ({exc.strerror or exc})") from exc
    # trimesh may return other geometry (points, lines, a scene) for a file without triangles.
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
            :func:`_refuse_stl`).
    """
    import trimesh

    name = shown_name(path)
    ext = os.path.splitext(path)[1].lower()
    # Recognise the contents from the first bytes (UTF-16/32 text decoded first).
    size = os.fstat(fh.fileno()).st_size
    head = fh.read(_SNIFF_BYTES)
    fh.seek(0)
    encoding = _text_encoding(head)
    kind, detail = _sniff_format(_decode(head, encoding) if encoding else head, size)
    if kind == "empty":
        raise MeshError(f"{name}: the file is empty")
    looks = _describe(kind, detail, encoding)
    hint = f": rename it to {_EXTENSIONS[kind]}" if kind in _EXTENSIONS else ""
    if kind == "pmz":
        hint = " (pmjax info, lod, refine and the other commands read a .pmz; build reads a mesh)"
    # The format to check: the extension's, or for a file without one, the
    # format it holds when pmjax checks that format.
    wanted = _CHECKED_FORMATS.get(ext) or (kind if not ext and kind in _CHECKED_FORMATS.values() else None)
    # A format pmjax does not check goes to trimesh as it is, unless trimesh
    # does not read it or the contents are a mesh format the extension does
    # not name.
    if wanted is None:
        if ext.lstrip(".") not in trimesh.available_formats():
            formats = ", ".join(sorted(_CHECKED_FORMATS)) + " and the other formats trimesh reads"
            what = "has no extension" if not ext else f"the extension {ext!r} names no mesh format pmjax reads"
            raise MeshError(f"{name}: {what} ({formats}); its contents look like {looks}{hint}")
        if (kind in _EXTENSIONS and _EXTENSIONS[kind] != ext) or kind == "pmz":
            raise MeshError(f"{name}: is named {ext} but its contents look like {looks}{hint}")
        if os.fsencode(path).decode("utf-8", "replace") == path:
            return path, None  # a name trimesh can find companion files (.gltf buffers) from
        return fh, ext.lstrip(".")
    # Binary data named .stl: a binary STL whose size does not match its count.
    if wanted == "stl" and kind == "binary":
        _refuse_stl(head, size, name)
    if kind != wanted:
        raise MeshError(f"{name}: is named {ext} but its contents look like {looks}, not {_DESCRIPTIONS[wanted]}{hint}")
    # Binary formats go to trimesh as the open file (a binary PLY checked first).
    if wanted == "glb" or (detail == "binary" and wanted in ("ply", "stl") and not encoding):
        if wanted == "ply":
            _check_binary_ply(fh, head, size, name)
        return fh, wanted
    if wanted == "off" and detail == "binary":
        raise MeshError(f"{name}: is a binary OFF file, which pmjax does not read: convert it to ASCII OFF or PLY")
    # A binary header in UTF-16/32 text: the bytes cannot be the binary data.
    if detail == "binary":
        raise MeshError(f"{name}: a binary {wanted.upper()} file in {encoding.upper()} text: the file is damaged")
    # Text is decoded to UTF-8 and checked; trimesh parses the checked text
    # (OBJ: comments blanked, relative indices made absolute).
    data = _decode(fh.read(), encoding)
    if wanted == "ply":
        _check_ascii_ply(data, name)
    elif wanted == "obj":
        data = _check_obj(data, name)
    elif wanted == "off":
        _check_off(data, name)
    return io.BytesIO(data), wanted


# -- STL --------------------------------------------------------------------------


def _refuse_stl(head: bytes, size: int, name: str) -> None:
    """Refuse a file named .stl that is neither ASCII STL text (``solid``
    first) nor a binary STL (``84 + 50 * n`` bytes, ``n`` the triangle count
    at byte 80), naming the count and the size. Always raises
    :class:`MeshError`; a valid binary STL is recognised by
    :func:`_sniff_format` and never comes here."""
    if size < 84:
        raise MeshError(f"{name}: {size} bytes: too short for a binary STL (an 80-byte header and a 4-byte "
                        f"triangle count) and not ASCII STL text (which starts with 'solid')")
    n = int.from_bytes(head[80:84], "little")
    room, over = divmod(size - 84, 50)
    raise MeshError(
        f"{name}: binary STL header claims {n} triangles, which take 84 + 50 × {n} = {84 + 50 * n} bytes, but the "
        f"file holds {size} bytes (room for {room} triangles{f' and {over} bytes more' if over else ''}): the count "
        f"is wrong or the file is truncated")


# -- PLY --------------------------------------------------------------------------

# PLY property types (the names of the PLY specification and their sized aliases).
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "int64": "i8", "uint64": "u8", "float16": "f2", "float": "f4", "float32": "f4", "double": "f8",
    "float64": "f8",
}
# The names of a face's vertex index list.
_PLY_FACE_INDICES = ("vertex_indices", "vertex_index")


@dataclasses.dataclass
class _PlyProperty:
    """A property of a PLY element, from its header line."""

    name: str
    dtype: str  # numpy code of the value (of each list entry for a list)
    count_dtype: str | None = None  # numpy code of a list's length; None: a single value


@dataclasses.dataclass
class _PlyElement:
    """A PLY element (``vertex``, ``face``, ...), from its header lines."""

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
    # The header is the lines up to end_header; line 2 names the format.
    end = re.search(rb"(?:^|\n)end_header[ \t]*\r?(?:\n|\Z)", data)
    if end is None:
        raise MeshError(f"{name}: PLY header has no end_header line")
    lines = data[: end.end()].decode("ascii", "replace").splitlines()
    form = lines[1].split()
    if len(form) != 3 or form[0] != "format" or form[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshError(f"{name}: line 2: PLY format line must be 'format ascii|binary_little_endian|"
                        f"binary_big_endian 1.0', got {lines[1][:80]!r}")
    # Then element lines, each followed by its property lines; comment and
    # obj_info lines are skipped, any other line refused.
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
    # Face indices must have an integer type.
    for element in elements:
        if element.name == "face":
            for prop in element.properties:
                if prop.name in _PLY_FACE_INDICES and prop.dtype[0] not in "iu":
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
    # The header may be longer than the bytes read to recognise the format.
    if b"end_header" not in head and size > len(head):
        fh.seek(0)
        head = fh.read(_MAX_PLY_HEADER)
    form, elements, pos, _ = _ply_header(head, name)
    order = "<" if form == "binary_little_endian" else ">"
    # Element by element from the end of the header (pos: the element's first byte).
    for element in elements:
        # The row's layout as a numpy structured dtype: a single value is a
        # field, a list a length field then a field of the first row's length.
        fields, offset, has_list = [], 0, False
        for k, prop in enumerate(element.properties):
            if prop.count_dtype is None:
                fields.append((f"p{k}", order + prop.dtype))
                offset += np.dtype(prop.dtype).itemsize
                continue
            # The list's length in the first row, read at its offset.
            count_dtype = np.dtype(order + prop.count_dtype)
            fh.seek(pos + offset)
            blob = fh.read(count_dtype.itemsize)
            if element.count and len(blob) < count_dtype.itemsize:
                raise MeshError(f"{name}: the header claims {element.count} '{element.name}' elements (header line "
                                f"{element.line}) but the file ends at byte {size}, before the first of them: "
                                f"the counts are wrong or the file is truncated")
            n = int(np.frombuffer(blob, count_dtype)[0]) if element.count else 0
            # A face of fewer than 3 vertices: the data is out of step with the header.
            if element.count and element.name == "face" and prop.name in _PLY_FACE_INDICES and n < 3:
                before = ", ".join(f"{e.count} {e.name!r}" for e in elements[: elements.index(element)])
                raise MeshError(f"{name}: 'face' element 0 (header line {element.line}) lists {n} vertices at byte "
                                f"{pos + offset}; a face needs 3 or more: the header's counts"
                                f"{f' (before it: {before})' if before else ''} are wrong or the file is damaged")
            # The first row's list must end inside the file (a forged length
            # would otherwise make a row type of any size).
            list_bytes = count_dtype.itemsize + max(n, 0) * np.dtype(prop.dtype).itemsize
            if element.count and pos + offset + list_bytes > size:
                raise MeshError(f"{name}: '{element.name}' element 0 (header line {element.line}) starts with a list "
                                f"of {n} entries at byte {pos + offset}, which would end at byte "
                                f"{pos + offset + list_bytes}, past the file's end at byte {size}: the file is damaged "
                                "or truncated")
            fields += [(f"n{k}", count_dtype), (f"p{k}", order + prop.dtype, (max(n, 0),))]
            offset += list_bytes
            has_list = True
        # Rows the bytes left can hold (all, for an element without properties).
        row = np.dtype(fields).itemsize if fields else 0
        have = (size - pos) // row if row else element.count
        # Every row's list lengths must be the first row's: compared in one
        # read of all rows through a memory map.
        if has_list and min(have, element.count) > 1:
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
        # The element must fit in the file.
        if have < element.count:
            raise MeshError(
                f"{name}: the header claims {element.count} '{element.name}' elements (header line {element.line}) of "
                f"{row} bytes from byte {pos}, but the file ends at byte {size}, after {have} of them: the counts "
                f"are wrong or the file is truncated")
        pos += element.count * row
    # Nothing may follow the last element.
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
    # The values the row takes, from its list lengths; each value's property
    # (None for a list length); what each list says, for the message.
    need, lists, kinds = 0, [], []
    for prop in element.properties:
        if prop.count_dtype is not None:
            if need >= len(tokens):
                return (f"{len(tokens)} values where the header's properties ({names}) take more: the line ends "
                        f"before list {prop.name!r}")
            word = tokens[need]
            if not _INT_RE.match(word) or int(word) < 0:
                return f"list {prop.name!r} length {word.decode(errors='replace')!r} is not a whole number"
            if element.name == "face" and prop.name in _PLY_FACE_INDICES and int(word) < 3:
                return f"list {prop.name!r} holds {int(word)} vertices; a face needs 3 or more"
            lists.append(f"list {prop.name!r} says {int(word)} entries")
            kinds += [None] + [prop] * int(word)
            need += 1 + int(word)
        else:
            kinds.append(prop)
            need += 1
    if need != len(tokens):
        said = f" ({'; '.join(lists)})" if lists else ""
        return f"{len(tokens)} values where the header's properties ({names}) take {need}{said}"
    # Each value with its property's syntax.
    for word, prop in zip(tokens, kinds):
        if prop is None:
            continue
        integer = prop.dtype[0] in "iu"
        if not (_INT_RE if integer else _NUM_RE).match(word):
            what = ("face index" if element.name == "face" and prop.name in _PLY_FACE_INDICES
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
    # The data: the lines after end_header (trailing whitespace ignored).
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
    # One line per row: too few lines name the element the data stops in, too
    # many the first line left over.
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

    # Each element's rows (lines first to last), as one block of text.
    row = 0
    for element in elements:
        if element.count == 0:
            continue
        first, last = row, row + element.count
        block = body[line_start(first):line_end(last - 1)]
        lists = sum(p.count_dtype is not None for p in element.properties)
        if lists == 0:
            # No list: one pattern matches every row; the first row it fails
            # is split to say why.
            bad = re.search(rb"^(?!" + _ply_row_pattern(element) + rb"$)", block, re.M)
            if bad is not None:
                r = first + block.count(b"\n", 0, bad.start())
                refuse(element, r - first, r,
                       _ply_row_problem(element, body[line_start(r):line_end(r)].split()) or "unreadable values")
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
        else:
            # Several lists: each row is split.
            for r in range(first, last):
                problem = _ply_row_problem(element, body[line_start(r):line_end(r)].split())
                if problem:
                    refuse(element, r - first, r, problem)
        row = last


# -- vectorised text --------------------------------------------------------------


def _span_mask(begins, ends, n) -> np.ndarray:
    """Boolean mask of ``n`` bytes, true in the ranges ``[begins, ends)``
    (sorted, disjoint)."""
    bounds = np.empty(2 * len(begins) + 2, np.int64)
    bounds[0], bounds[-1] = 0, n
    bounds[1:-1:2], bounds[2:-1:2] = begins, ends
    inside = np.zeros(len(bounds) - 1, bool)
    inside[1::2] = True
    return np.repeat(inside, np.diff(bounds))


def _ragged_arange(starts, lengths) -> np.ndarray:
    """``concatenate([arange(s, s + n) for s, n in zip(starts, lengths)])``, vectorised."""
    lengths = np.asarray(lengths, np.int64)
    offsets = np.cumsum(lengths) - lengths
    return np.repeat(np.asarray(starts, np.int64) - offsets, lengths) + np.arange(int(lengths.sum()))


class _Text:
    """The lines and whitespace-separated tokens of a text, found with
    vectorised numpy: large files are checked without a Python loop over
    their lines. Lines are numbered from 0 here (messages add 1).

    Args:
        data: the text, UTF-8 bytes.
        comments: blank ``#`` comments (to the end of their line) first.
    """

    def __init__(self, data: bytes, comments: bool = False):
        # Lines: [starts[i], ends[i]), the newline excluded.
        a = np.frombuffer(data, np.uint8)
        self.starts = np.concatenate([[0], np.flatnonzero(a == 10) + 1])
        self.ends = np.concatenate([self.starts[1:] - 1, [len(a)]])
        # Comments blanked with spaces: from each line's first '#' to its end.
        if comments and b"#" in data:
            hashes = np.flatnonzero(a == 35)
            line = np.searchsorted(self.starts, hashes, "right") - 1
            first = np.concatenate([[True], line[1:] != line[:-1]])
            a = a.copy()
            a[_span_mask(hashes[first], self.ends[line[first]], len(a))] = 32
            data = a.tobytes()
        self.data, self.array = data, a
        # Tokens: runs of bytes that are not ASCII whitespace, as bytes.split()
        # sees it: space, and \t \n \v \f \r (9 to 13).
        space = np.ones(len(a) + 2, bool)
        space[1:-1] = (a == 32) | (a - np.uint8(9) <= 4)
        edge = np.flatnonzero(space[1:] != space[:-1])
        self.token_starts, self.token_ends = edge[0::2], edge[1::2]
        # Tokens of line i: line_tokens[i] to line_tokens[i + 1].
        self.line_tokens = np.concatenate([np.searchsorted(self.token_starts, self.starts), [len(self.token_starts)]])
        self.tokens_per_line = np.diff(self.line_tokens)

    def words(self, line: int) -> list:
        """The tokens of a line (comments blanked)."""
        return self.data[self.starts[line]:self.ends[line]].split()

    def keyword_codes(self) -> np.ndarray:
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
        keep = _span_mask(begins, ends, len(self.array))
        buffer = np.full(len(self.array), 32, np.uint8)
        buffer[keep] = self.array[keep]
        try:
            out = np.fromstring(buffer.tobytes(), dtype=dtype, sep=" ")
        except ValueError:
            return None
        return out if len(out) == count else None


# -- OBJ --------------------------------------------------------------------------

_OBJ_FACE_BYTES = np.zeros(256, bool)  # the bytes of plain face lines: "f 1 2 3", "f 1/1/1 2//2 3/3"
_OBJ_FACE_BYTES[list(b"0123456789/f \t\r\n")] = True
# The indices of a face corner (v/vt/vn), as messages name them.
_OBJ_INDEX_LABELS = {b"v": "vertex", b"vt": "texture", b"vn": "normal"}


def _check_obj(data: bytes, name: str) -> bytes:
    """OBJ text: every ``v`` line holds three values or more, every face
    corner is a 1-based (or negative, relative) integer index in range.

    Plain files (face lines of digits, ``/`` and spaces) are proven valid
    with vectorised parsing; any other face line (a relative index, index 0,
    a sign, a line continuation) makes the file walked line by line
    (:func:`_check_obj_lines`), which names the line at fault. The vertex values
    are parsed by trimesh (:func:`read_mesh` walks a file it fails on).

    Returns:
        the text to parse (UTF-8 bytes): comments blanked, relative indices
        made absolute.

    Raises:
        MeshError: naming the line, the index and the remedy.
    """
    text = _Text(data, comments=True)
    code = text.keyword_codes()
    v_lines, f_lines = np.flatnonzero(code == ord("v")), np.flatnonzero(code == ord("f"))
    tpl, first = text.tokens_per_line, text.line_tokens
    # Vertex lines need three values (trimesh parses them: a failure is walked
    # by read_mesh to name the line), faces three corners.
    plain = not (tpl[v_lines] < 4).any() and not (tpl[f_lines] < 4).any()
    if plain and len(f_lines):
        # Face lines of plain bytes only (no sign, so no relative index), and no
        # '/0' (a texture or normal index 0, or one with a leading zero).
        a = text.array
        face_bytes = _span_mask(text.starts[f_lines], text.ends[f_lines], len(a))
        zero_after_slash = face_bytes[1:] & (a[1:] == ord("0")) & (a[:-1] == ord("/"))
        plain = not (face_bytes & ~_OBJ_FACE_BYTES[a]).any() and not zero_after_slash.any()
        slashes = np.flatnonzero(face_bytes & (a == ord("/")))
        # The vertex indices: without '/', every token after the 'f'.
        if plain and not len(slashes):
            index = text.line_values(f_lines, skip=1, dtype=np.int64)
        elif plain:
            corners = _ragged_arange(first[f_lines] + 1, tpl[f_lines] - 1)
            # A corner's vertex index ends at its first '/'.
            ends = text.token_ends[corners].copy()
            owner = np.searchsorted(text.token_starts, slashes, "right") - 1
            once = np.concatenate([[True], owner[1:] != owner[:-1]])[: len(owner)]
            ends[np.searchsorted(corners, owner[once])] = slashes[once]
            index = text.values(corners, np.int64, ends)
        # Every vertex index names a vertex of the file (1-based).
        if plain:
            plain = index is not None and (len(index) == 0 or (index.min() >= 1 and index.max() <= len(v_lines)))
    # A file that is not plain is walked line by line, to find and name the
    # line at fault. Comments are blanked in the text returned: trimesh reads
    # a face line with a trailing comment as indices.
    return text.data if plain else _check_obj_lines(text.data, name)


def _check_obj_lines(data: bytes, name: str) -> bytes:
    """Check an OBJ line by line (see :func:`_check_obj`); return it with
    relative indices made absolute."""
    # Vertices, texture coordinates and normals declared so far (a negative
    # index counts back from them), and the vertices of the whole file (a
    # positive index may name a vertex declared after the face).
    counts = {b"v": 0, b"vt": 0, b"vn": 0}
    total = len(re.findall(rb"^[ \t]*v[ \t]", data, re.M))
    lines = data.split(b"\n")
    changed = False
    for number, line in enumerate(lines, start=1):
        words = line.split(b"#", 1)[0].split()
        if not words:
            continue
        key = words[0]
        # v, vt and vn lines are counted; a vertex needs three numbers.
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
        # Other lines than faces are left to trimesh.
        if key != b"f":
            continue
        if words[-1].endswith(b"\\"):
            raise MeshError(f"{name}: line {number} ends with '\\' (a line continuation), which pmjax does not "
                            "read: join it with the next line")
        if len(words) < 4:
            raise MeshError(f"{name}: line {number}: a face needs 3 corners or more, this one has {len(words) - 1}")
        # Each corner's indices (v/vt/vn, vt and vn optional): integers, not 0,
        # negative ones made absolute, vertex indices within the file's vertices.
        corners = []
        for word in words[1:]:
            parts = word.split(b"/")
            for slot, (part, what) in enumerate(zip(parts, (b"v", b"vt", b"vn"))):
                if slot and not part:
                    continue
                label = _OBJ_INDEX_LABELS[what]
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
        # Once an index was made absolute, face lines are rebuilt from their corners.
        if changed:
            lines[number - 1] = b"f " + b" ".join(corners)
    return b"\n".join(lines) if changed else data


# -- OFF --------------------------------------------------------------------------

_OFF_COUNTS = re.compile(rb"\d+")  # an OFF count: a whole number


def _check_off(data: bytes, name: str) -> None:
    """An ASCII OFF: the keyword, ``V F E`` counts, then exactly V vertex lines
    (three numbers or more) and F face lines (``n`` then ``n`` integer
    indices below V, then optional colour values); ``#`` starts a comment.

    The lines are checked with vectorised parsing; a failing file is walked
    line by line to name the line at fault.

    Raises:
        MeshError: naming the line, the element and the counts.
    """
    # The keyword, on the first line with content: 3D OFF only (not 4OFF or nOFF).
    text = _Text(data, comments=True)
    content = np.flatnonzero(text.tokens_per_line > 0)
    words = text.words(content[0])
    match = _OFF_KEYWORD.fullmatch(words[0])
    if match is None or match.group(1):
        raise MeshError(f"{name}: line {content[0] + 1}: OFF keyword {words[0].decode(errors='replace')!r}: pmjax "
                        "reads 3D OFF files ([ST][C][N]OFF)")
    # The counts: after the keyword, or on the next line with content.
    counts, items = words[1:], content[1:]
    count_line = content[0] + 1
    if not counts:
        if not len(items):
            raise MeshError(f"{name}: no vertex and face counts after the OFF keyword")
        counts, count_line, items = text.words(items[0]), items[0] + 1, items[1:]
    if len(counts) < 2 or not all(_OFF_COUNTS.fullmatch(w) for w in counts[:3]):
        raise MeshError(f"{name}: line {count_line}: OFF counts must be whole numbers 'VERTICES FACES EDGES', "
                        f"got {b' '.join(counts).decode(errors='replace')!r}")
    # One line with content per vertex and per face, as many as the counts claim.
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
                  else text.values(_ragged_arange(first[vertices], np.full(nv, 3))))
        plain = coords is not None
    # Faces: a corner count of 3 or more, then as many indices, all below V.
    if plain and nf:
        if (tpl[faces] == 4).all():
            index = text.line_values(faces, dtype=np.int64)
            plain = index is not None and (index[0::4] == 3).all()
            index = index.reshape(-1, 4)[:, 1:] if plain else None
        else:
            n = text.values(first[faces], np.int64)
            plain = n is not None and (n >= 3).all() and (tpl[faces] >= n + 1).all()
            index = text.values(_ragged_arange(first[faces] + 1, n), np.int64) if plain else None
            plain = index is not None
        plain = plain and index.min() >= 0 and index.max() < nv
    if not plain:
        _find_off_error(text, vertices, faces, nv, name)


def _find_off_error(text: _Text, vertices, faces, nv: int, name: str) -> None:
    """Find the OFF line that failed :func:`_check_off`'s vectorised checks,
    line by line, and refuse it; return when every line passes."""
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
        vertices: ``(V, 3)`` coordinates: float32 ones are written exactly in
            every format, float64 ones in OBJ and OFF (PLY, STL and GLB store
            float32).
        faces: ``(F, 3)`` integer indices into ``vertices``.

    Raises:
        ValueError: an extension pmjax does not write (:func:`check_mesh_output`),
            arrays of the wrong shape, or indices out of range.
    """
    import trimesh
    from trimesh.exchange.export import export_mesh

    from pmjax._atomic import atomic_path

    # The format first: a name pmjax cannot write is refused before the arrays.
    file_type = check_mesh_output(path)
    v = np.asarray(vertices)
    f = np.asarray(faces)
    name = shown_name(path)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{name}: a mesh needs (V, 3) vertices and (F, 3) integer faces, got {v.shape} and "
                         f"{f.shape} {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"{name}: face indices run from {f.min()} to {f.max()} but there are {len(v)} vertices")
    # Exported in memory, so a failing export leaves no file behind.
    if file_type in ("obj", "off"):
        data = _text_mesh(v, f, file_type)
    else:
        data = export_mesh(trimesh.Trimesh(v, f, process=False), None, file_type=file_type)
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_path(path, "." + file_type) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def _text_mesh(v: np.ndarray, f: np.ndarray, file_type: str) -> bytes:
    """An OBJ or OFF file of the mesh whose numbers read back exactly: each
    coordinate with the significant digits its float needs (9 for float32,
    17 otherwise), not a fixed count of decimals, which would flatten a model
    measured in micrometres and round any model's last bits."""
    digits = 9 if v.dtype == np.float32 else 17
    coords = [" ".join(f"{x:.{digits}g}" for x in row) for row in v.tolist()]
    if file_type == "obj":
        lines = ["v " + row for row in coords] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f.tolist()]
    else:
        lines = ["OFF", f"{len(v)} {len(f)} 0", *coords] + [f"3 {a} {b} {c}" for a, b, c in f.tolist()]
    return ("\n".join(lines) + "\n").encode("ascii")
