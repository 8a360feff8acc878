"""Mesh files: what a file claims is checked against what it holds, messages
name the file, the element and the line or byte at fault, and meshes are
written only in formats pmjax can write. (Cleaning: test_meshio.py.)"""

import os
import struct
import sys

import numpy as np
import pytest
import trimesh

import pmjax
from pmjax import MeshError
from pmjax._atomic import TEMP_MARK
from pmjax._cli import main
from pmjax._meshfiles import MESH_OUTPUTS, check_mesh_output, shown_name, write_mesh
from pmjax.builders import build_pm

V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
F = np.array([[0, 1, 2], [0, 2, 3]])


def ascii_ply(nv=4, nf=2, faces=("3 0 1 2", "3 0 2 3"), vertices=None, newline="\n"):
    """A square as ASCII PLY, its header claiming ``nv`` vertices and ``nf`` faces (9 header lines)."""
    lines = ["ply", "format ascii 1.0", f"element vertex {nv}", "property float x", "property float y",
             "property float z", f"element face {nf}", "property list uchar int vertex_indices", "end_header"]
    lines += vertices or ["%g %g %g" % tuple(p) for p in V]
    lines += list(faces)
    return (newline.join(lines) + newline).encode()


def binary_ply(faces=F, nv=None, nf=None, order="<", tail=b""):
    """A binary PLY of ``V`` and ``faces`` (lists of any length), its header claiming ``nv`` / ``nf``."""
    header = (f"ply\nformat binary_{'little' if order == '<' else 'big'}_endian 1.0\n"
              f"element vertex {len(V) if nv is None else nv}\nproperty float x\nproperty float y\n"
              f"property float z\nelement face {len(faces) if nf is None else nf}\n"
              f"property list uchar int vertex_indices\nend_header\n").encode()
    body = V.astype(order + "f4").tobytes()
    body += b"".join(struct.pack(f"{order}B{len(f)}i", len(f), *f) for f in faces)
    return header + body + tail


def off(nv=4, nf=2, faces=("3 0 1 2", "3 0 2 3")):
    """A square as OFF (counts on line 2, vertices from line 3)."""
    return ("OFF\n%d %d 0\n" % (nv, nf) + "".join("%g %g %g\n" % tuple(p) for p in V)
            + "".join(f + "\n" for f in faces)).encode()


def obj(faces=("f 1 2 3", "f 1 3 4"), prefix=""):
    """A square as OBJ (vertices on lines 1-4, faces from line 5)."""
    return (prefix + "".join("v %g %g %g\n" % tuple(p) for p in V) + "".join(f + "\n" for f in faces)).encode()


def binary_stl(triangles=2, claim=None):
    """The square as a binary STL soup whose header claims ``claim`` triangles."""
    tri = V.astype(np.float32)[F][:triangles]
    body = b"".join(struct.pack("<12fH", 0, 0, 1, *t.ravel(), 0) for t in tri)
    return b"\0" * 80 + struct.pack("<I", len(tri) if claim is None else claim) + body


def write(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    return path


def named(rows):
    """Parameter rows, each named by its first value (a file name)."""
    return [pytest.param(*row, id=row[0]) for row in rows]


def message(path):
    with pytest.raises(MeshError) as err:
        pmjax.read_mesh(path)
    return str(err.value)


# -- files that hold what they claim are read as before -------------------------------


@pytest.mark.parametrize("name, data", named([
    ("a.ply", ascii_ply()),
    ("crlf.ply", ascii_ply(newline="\r\n")),
    ("little.ply", binary_ply()),
    ("big.ply", binary_ply(order=">")),
    ("a.obj", obj()),
    ("slashes.obj", obj(["vt 0 0", "vn 0 0 1", "f 1/1/1 2/1/1 3/1/1", "f 1//1 3//1 4//1"])),
    ("relative.obj", obj(["f -4 -3 -2", "f -4 -2 -1"])),
    ("comments.obj", obj(["# two faces", "g square", "f 1 2 3 # first", "f 1 3 4"], prefix="# a square\n")),
    ("utf8bom.obj", b"\xef\xbb\xbf" + obj()),
    ("utf16.obj", obj().decode().encode("utf-16")),
    ("latin1-comment.obj", obj(prefix="# caf\xe9\n").decode().encode("latin-1")),
    ("crlf.obj", obj(["f 1/1 2/1 3/1", "f 1 3 4"], prefix="vt 0 0\n").replace(b"\n", b"\r\n")),
    ("a.off", off()),
    ("crlf.off", off().replace(b"\n", b"\r\n")),
    ("colours.off", b"COFF\n4 2 0\n" + b"".join(b"%g %g %g 255 0 0 255\n" % tuple(p) for p in V)
     + b"3 0 1 2 0.5 0 0\n3 0 2 3 0.5 0 0\n"),
    ("inline-counts.off", b"# a square\nOFF 4 2 0\n" + off()[len(b"OFF\n4 2 0\n"):]),
    ("no-extension", ascii_ply()),
]))
def test_files_that_hold_what_they_claim_read_the_square(tmp_path, monkeypatch, name, data):
    # Text is decoded without charset_normalizer (trimesh's guesser, an optional package).
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    v, f = pmjax.read_mesh(write(tmp_path, name, data))
    assert np.array_equal(v, V) and np.array_equal(f, F)


def test_binary_stl_soups_of_either_header_read_the_square(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    for header in (b"\0" * 80, b"solid square".ljust(80, b" ")):
        v, f = pmjax.read_mesh(write(tmp_path, "a.stl", header + binary_stl()[80:]))
        soup = V.astype(np.float32)[F].reshape(-1, 3)
        assert np.array_equal(v, soup) and np.array_equal(f, np.arange(6).reshape(2, 3))


@pytest.mark.parametrize("file_type, encoding", [("ply", "ascii"), ("ply", "binary"), ("obj", None), ("off", None),
                                                ("stl", None), ("stl_ascii", None), ("glb", None)])
def test_files_trimesh_writes_read_as_trimesh_reads_them(tmp_path, file_type, encoding):
    # Colours add integer properties beside the float coordinates and the face lists.
    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.visual.vertex_colors = np.random.default_rng(0).integers(0, 256, (len(mesh.vertices), 4), np.uint8)
    path = tmp_path / f"sphere.{file_type.split('_')[0]}"
    mesh.export(path, file_type=file_type, **({"encoding": encoding} if encoding else {}))
    v, f = pmjax.read_mesh(path)
    reference = trimesh.load(path, process=False, force="mesh")
    assert np.array_equal(v, reference.vertices) and np.array_equal(f, reference.faces)
    assert len(f) == 320


def test_relative_obj_indices_count_back_from_the_face(tmp_path):
    # Vertices after the first face: -3 there means vertex 1, after the second block vertex 4.
    text = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 5 0 0\nv 6 0 0\nv 5 1 0\nf -3 -2 -1\n"
    v, f = pmjax.read_mesh(write(tmp_path, "blocks.obj", text))
    assert np.array_equal(v[f], [[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[5, 0, 0], [6, 0, 0], [5, 1, 0]]])


def test_a_large_binary_ply_reads_as_trimesh_reads_it(data_path):
    path = data_path("dragon.ply")
    v, f = pmjax.read_mesh(path)
    reference = trimesh.load(path, process=False)
    assert np.array_equal(v, reference.vertices) and np.array_equal(f, reference.faces)


# -- files that claim more (or less) than they hold are refused ---------------------


@pytest.mark.parametrize("name, data, expected", named([
    ("more-vertices.ply", ascii_ply(nv=6),
     "more-vertices.ply: the header claims 6 'vertex' and 2 'face' elements, one per line (8 lines), but 6 follow "
     "end_header (to line 15): element 'face' (header line 7) has 0 of its 2 rows; the counts are wrong or the "
     "file is truncated"),
    ("more-faces.ply", ascii_ply(nf=5),
     "more-faces.ply: the header claims 4 'vertex' and 5 'face' elements, one per line (9 lines), but 6 follow "
     "end_header (to line 15): element 'face' (header line 7) has 2 of its 5 rows; the counts are wrong or the "
     "file is truncated"),
    ("fewer-faces.ply", ascii_ply(nf=1),
     "fewer-faces.ply: line 15: 1 more lines follow the 5 the header claims (4 'vertex' and 1 'face' elements): "
     "the counts are wrong or the file is damaged"),
    ("more-vertices.off", off(nv=6),
     "more-vertices.off: line 2 claims 6 vertices and 2 faces, one per line (8 lines), but 6 follow (to line 8): "
     "0 of the 2 faces; the counts are wrong or the file is truncated"),
    ("more-faces.off", off(nf=5),
     "more-faces.off: line 2 claims 4 vertices and 5 faces, one per line (9 lines), but 6 follow (to line 8): "
     "2 of the 5 faces; the counts are wrong or the file is truncated"),
    ("fewer-faces.off", off(nf=1),
     "fewer-faces.off: line 8: 1 more lines follow the 4 vertices and 1 faces that line 2 claims: the counts are "
     "wrong or the file is damaged"),
    ("cut-vertices.ply", binary_ply()[:200],
     "cut-vertices.ply: the header claims 4 'vertex' elements (header line 3) of 12 bytes from byte 169, but the "
     "file ends at byte 200, after 2 of them: the counts are wrong or the file is truncated"),
    ("more-vertices-binary.ply", binary_ply(nv=6),
     "more-vertices-binary.ply: 'face' element 0 (header line 7) lists 0 vertices at byte 241; a face needs 3 or "
     "more: the header's counts (before it: 6 'vertex') are wrong or the file is damaged"),
    ("no-faces.ply", binary_ply()[:217],
     "no-faces.ply: the header claims 2 'face' elements (header line 7) but the file ends at byte 217, before the "
     "first of them: the counts are wrong or the file is truncated"),
    ("cut-big-endian.ply", binary_ply(order=">")[:-5],
     "cut-big-endian.ply: the header claims 2 'face' elements (header line 7) of 13 bytes from byte 214, but the "
     "file ends at byte 235, after 1 of them: the counts are wrong or the file is truncated"),
    ("tail.ply", binary_ply(tail=b"\0" * 7),
     "tail.ply: the file holds 7 bytes after the 243 its PLY header describes (4 'vertex', 2 'face'): the counts "
     "are wrong or the file is damaged"),
    ("count.stl", binary_stl(claim=9),
     "count.stl: binary STL header claims 9 triangles, which take 84 + 50 × 9 = 534 bytes, but the file holds "
     "184 bytes (room for 2 triangles): the count is wrong or the file is truncated"),
    ("cut.stl", binary_stl()[:-20],
     "cut.stl: binary STL header claims 2 triangles, which take 84 + 50 × 2 = 184 bytes, but the file holds "
     "164 bytes (room for 1 triangles and 30 bytes more): the count is wrong or the file is truncated"),
]))
def test_a_header_that_lies_is_refused_naming_the_element_and_the_line(tmp_path, monkeypatch, name, data, expected):
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    assert message(write(tmp_path, name, data)) == f"{tmp_path}/{expected}"


def test_binary_ply_lists_are_checked_to_the_last_row(tmp_path):
    # 200,000 faces; one quad deep in the file: read as triangles every row after it would be garbage.
    faces = [(0, 1, 2)] * 200_000
    faces[150_000] = (0, 1, 2, 3)
    path = write(tmp_path, "mixed.ply", binary_ply(faces))
    assert message(path) == (
        f"{path}: 'face' element 150000 (header line 7) starts with a list of 4 entries where element 0 has 3: "
        "pmjax reads binary PLY lists of one length only (or the file is damaged); triangulate the mesh first")


def test_a_forged_binary_ply_list_length_is_refused_by_element_and_byte(tmp_path):
    data = binary_ply().replace(b"list uchar int", b"list uint int")
    start = data.index(b"end_header\n") + len(b"end_header\n") + V.astype("<f4").nbytes
    body = struct.pack("<I", 600_000_000) + b"\0" * 12 + struct.pack("<I3i", 3, 0, 2, 3)
    path = write(tmp_path, "forged.ply", data[:start] + body)
    assert message(path) == (
        f"{path}: 'face' element 0 (header line 7) starts with a list of 600000000 entries at byte {start}, which "
        f"would end at byte {start + 4 + 2_400_000_000}, past the file's end at byte {start + len(body)}: the file "
        "is damaged or truncated")


# -- face indices -------------------------------------------------------------------


@pytest.mark.parametrize("name, data, expected", named([
    ("float-index.ply", ascii_ply(faces=["3 0 1.5 2", "3 0 2 3"]),
     "line 14: face 0: face index '1.5' is not an integer"),
    ("short-row.ply", ascii_ply(vertices=["0 0 0", "1 0", "1 1 0", "0 1 0"]),
     "line 11: vertex 1: 2 values where the header's properties (x, y, z) take 3"),
    ("short-list.ply", ascii_ply(faces=["3 0 1 2", "3 0 2"]),
     "line 15: face 1: 3 values where the header's properties (vertex_indices) take 4 (list 'vertex_indices' says "
     "3 entries)"),
    ("two-corners.ply", ascii_ply(faces=["3 0 1 2", "2 0 2"]),
     "line 15: face 1: list 'vertex_indices' holds 2 vertices; a face needs 3 or more"),
    ("two-corners-first.ply", ascii_ply(faces=["2 0 1", "3 0 2 3"]),
     "line 14: face 0: list 'vertex_indices' holds 2 vertices; a face needs 3 or more"),
    ("blank-line.ply", ascii_ply(vertices=["0 0 0", "", "1 0 0", "1 1 0", "0 1 0"]),
     "line 11 is blank: an ASCII PLY holds one element per line, with no blank lines between them (the header "
     "claims 4 'vertex' and 2 'face' elements)"),
    ("float-type.ply", ascii_ply().replace(b"list uchar int", b"list uchar float"),
     "PLY element 'face' (header line 7): property 'vertex_indices' holds floating-point values; face indices "
     "must be integers"),
    ("float-index.off", off(faces=["3 0 1.5 2", "3 0 2 3"]), "line 7: face 0: face index '1.5' is not an integer"),
    ("outside.off", off(faces=["3 0 1 2", "3 0 2 4"]),
     "line 8: face 1: face index 4 is outside the 4 vertices (OFF indices run from 0 to 3)"),
    ("zero-based.obj", obj(["f 0 1 2", "f 0 2 3"]),
     "line 5: face vertex index 0: OBJ indices start at 1 (negative ones count back from the last vertex before "
     "the face); the file looks written with 0-based indices: export it again with 1-based ones"),
    ("zero-texture.obj", obj(["vt 0 0", "f 1/0 2/1 3/1"]), "line 6: face texture index 0: OBJ indices start at 1"),
    ("float-index.obj", obj(["f 1 2.5 3"]), "line 5: face vertex index '2.5' is not an integer"),
    ("outside.obj", obj(["f 1 2 3", "f 1 3 9"]), "line 6: face vertex index 9 but the file declares 4 vertices"),
    ("before-first.obj", obj(["f -1 -2 -5"]),
     "line 5: face vertex index -5 reaches before the first vertex (only 4 are declared above the face)"),
    ("two-corners.obj", obj(["f 1 2 3", "f 1 3"]), "line 6: a face needs 3 corners or more, this one has 2"),
    ("continued.obj", obj(["f 1 2 \\", " 3"]),
     "line 5 ends with '\\' (a line continuation), which pmjax does not read: join it with the next line"),
    ("bad-vertex.obj", b"v 0 0 0\nv 1 x 0\nv 1 1 0\nf 1 2 3\n", "line 2: vertex 2: coordinate 'x' is not a number"),
    ("short-vertex.obj", b"v 0 0 0\nv 1 0\nv 1 1 0\nf 1 2 3\n", "line 2: vertex 2 has 2 coordinates; a vertex needs 3"),
]))
def test_face_indices_must_be_integers_in_range(tmp_path, name, data, expected):
    got = message(write(tmp_path, name, data))
    assert got.startswith(f"{tmp_path}/{name}: {expected}"), got


# -- contents that are not what the name says ---------------------------------------


@pytest.mark.parametrize("name, data, expected", named([
    ("ply.obj", ascii_ply(),
     "is named .obj but its contents look like an ASCII PLY file, not OBJ text: rename it to .ply"),
    ("obj.ply", obj(), "is named .ply but its contents look like OBJ text, not a PLY file: rename it to .obj"),
    ("ply.stl", binary_ply(),
     "is named .stl but its contents look like a binary PLY file, not an STL file: rename it to .ply"),
    ("stl.off", binary_stl(),
     "is named .off but its contents look like a binary STL file, not an OFF file: rename it to .stl"),
    ("utf16.ply", obj().decode().encode("utf-16"),
     "is named .ply but its contents look like OBJ text (UTF-16 text), not a PLY file: rename it to .obj"),
    ("model.mesh", ascii_ply(),
     "the extension '.mesh' names no mesh format pmjax reads (.glb, .obj, .off, .ply, .stl and the other formats "
     "trimesh reads); its contents look like an ASCII PLY file: rename it to .ply"),
    ("notes", b"just words\n", "has no extension (.glb, .obj, .off, .ply, .stl and the other formats trimesh "
     "reads); its contents look like text in no mesh format pmjax recognises"),
    ("ply.xyz", ascii_ply(), "is named .xyz but its contents look like an ASCII PLY file: rename it to .ply"),
    ("empty.obj", b"", "the file is empty"),
    ("binary.off", b"OFF BINARY\n" + b"\0" * 24,
     "is a binary OFF file, which pmjax does not read: convert it to ASCII OFF or PLY"),
    ("tiny.stl", b"\0" * 10, "10 bytes: too short for a binary STL (an 80-byte header and a 4-byte triangle count) "
     "and not ASCII STL text (which starts with 'solid')"),
]))
def test_contents_that_are_not_the_named_format_are_described(tmp_path, monkeypatch, name, data, expected):
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    assert message(write(tmp_path, name, data)) == f"{tmp_path}/{name}: {expected}"


def test_a_progressive_mesh_given_as_a_mesh_is_named(tmp_path):
    pmz = tmp_path / "square.pmz"
    pmjax.save_pm(build_pm(*pmjax.clean_mesh(V, F)[:2]), pmz)
    assert message(pmz) == (
        f"{pmz}: the extension '.pmz' names no mesh format pmjax reads (.glb, .obj, .off, .ply, .stl and the other "
        "formats trimesh reads); its contents look like a pmjax progressive mesh (.pmz) (pmjax info, lod, refine "
        "and the other commands read a .pmz; build reads a mesh)")


def test_a_file_name_that_is_not_utf8_is_printed_escaped(tmp_path):
    bad = tmp_path / os.fsdecode(b"bad\xff.ply")
    bad.write_bytes(ascii_ply(nv=6))
    text = message(bad)
    assert text.startswith(f"{tmp_path}/bad\\xff.ply: the header claims 6 'vertex'")
    text.encode("utf-8")  # printable anywhere: no lone surrogate left
    good = tmp_path / os.fsdecode(b"good\xff.ply")
    good.write_bytes(ascii_ply())
    for path in (good, os.fsencode(good)):  # str with surrogate escapes, or bytes
        v, f = pmjax.read_mesh(path)
        assert np.array_equal(v, V) and np.array_equal(f, F)
    assert shown_name(os.fsencode(good)) == f"{tmp_path}/good\\xff.ply"
    assert shown_name("new\nline.ply") == "new\\nline.ply"


def test_build_refuses_a_lying_file_and_writes_nothing(tmp_path, capsys):
    src = write(tmp_path, "more-vertices.ply", ascii_ply(nv=6))
    out = tmp_path / "model.pmz"
    assert main(["build", str(src), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pmjax build: error: {src}: the header claims 6 'vertex' and 2 'face' elements"), err
    assert sorted(os.listdir(tmp_path)) == ["more-vertices.ply"]


# -- writing ------------------------------------------------------------------------


@pytest.mark.parametrize("path, expected", [
    ("out.pmz", "out.pmz: this command writes a plain mesh (.ply, .obj, .off, .stl or .glb); a .pmz progressive "
                "mesh is written by `pmjax build`"),
    ("out.xyz", "out.xyz: pmjax writes meshes as .ply, .obj, .off, .stl or .glb, not .xyz"),
    ("out.gltf", "out.gltf: pmjax writes meshes as .ply, .obj, .off, .stl or .glb, not .gltf"),
    (os.fsdecode(b"out\xff.dae"), "out\\xff.dae: pmjax writes meshes as .ply, .obj, .off, .stl or .glb, not .dae"),
])
def test_mesh_outputs_pmjax_cannot_write_are_refused(path, expected):
    with pytest.raises(ValueError) as err:
        check_mesh_output(path)
    assert str(err.value) == expected


def test_mesh_outputs_are_written_in_the_format_of_their_extension(tmp_path):
    assert [check_mesh_output(f"x{e}") for e in MESH_OUTPUTS] == ["ply", "obj", "off", "stl", "glb"]
    assert check_mesh_output("X.PLY") == "ply" and check_mesh_output("/dev/null") == "ply"
    for ext in MESH_OUTPUTS + ("",):
        path = tmp_path / f"square{ext}"
        write_mesh(path, V, F)
        v, f, _, _ = pmjax.load_clean_mesh(path)  # welds the STL soup
        assert np.array_equal(v, V) and np.array_equal(f, F), ext
    with pytest.raises(ValueError, match="not .xyz"):
        write_mesh(tmp_path / "square.xyz", V, F)
    with pytest.raises(ValueError, match=r"face indices run from 0 to 4 but there are 4 vertices"):
        write_mesh(tmp_path / "bad.ply", V, [[0, 1, 4]])
    assert sorted(os.listdir(tmp_path)) == sorted(f"square{e}" for e in MESH_OUTPUTS + ("",))


@pytest.mark.parametrize("scale", [1e-9, 1.0 / 3.0, 1e30])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_mesh_outputs_keep_every_bit_of_the_coordinates_at_any_scale(tmp_path, scale, dtype):
    """Every format gives back the coordinates written, bit for bit, also
    those of a model measured in nanometres or in light years (text
    formats write each number's significant digits, not fixed decimals)."""
    v = (np.asarray(V, np.float64) * scale + scale / 7).astype(dtype)
    for ext in MESH_OUTPUTS:
        if dtype == np.float64 and ext in (".ply", ".stl", ".glb"):
            continue  # float32 in the file
        write_mesh(tmp_path / f"s{ext}", v, F)
        got, f, _, _ = pmjax.load_clean_mesh(tmp_path / f"s{ext}")
        assert np.array_equal(got.astype(dtype), v) and np.array_equal(f, F), ext


@pytest.fixture(scope="module")
def square_pm(tmp_path_factory):
    path = tmp_path_factory.mktemp("square") / "square.pmz"
    pmjax.save_pm(build_pm(*pmjax.clean_mesh(V, F)[:2]), path)
    return str(path)


@pytest.mark.parametrize("argv, output, expected", [
    (["lod"], "out.pmz", "this command writes a plain mesh (.ply, .obj, .off, .stl or .glb); a .pmz progressive "
                         "mesh is written by `pmjax build`"),
    (["refine", "--eye", "0.5", "0.5", "3", "--target", "0.5", "0.5", "0"], "out.xyz",
     "pmjax writes meshes as .ply, .obj, .off, .stl or .glb, not .xyz"),
])
def test_lod_and_refine_refuse_a_format_they_cannot_write(square_pm, tmp_path, capsys, argv, output, expected):
    out = tmp_path / output
    assert main([argv[0], square_pm, *argv[1:], "-o", str(out)]) == 2
    assert capsys.readouterr().err == f"pmjax {argv[0]}: error: {out}: {expected}\n"
    assert os.listdir(tmp_path) == []
    assert not any(TEMP_MARK in n for n in os.listdir(os.path.dirname(square_pm)))
