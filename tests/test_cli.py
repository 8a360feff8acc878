"""The command line, run in-process: build, info, lod, and clear errors."""

import json

import numpy as np
import pytest
import trimesh

import pmjax
from pmjax._cli import main


def test_build_info_lod(tmp_path, data_path, capsys):
    out = tmp_path / "cow.pmz"
    assert main(["build", data_path("cow.ply"), "-o", str(out), "-q", "--metric", "edge:1,quadric"]) == 0
    pm = pmjax.read_pm(out)
    assert pm.header["source"] == "cow.ply" and pm.header["source_sha256"]
    capsys.readouterr()
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["pcols"] == pm.n_pcols and info["batches"] == pm.n_batches
    assert info["dependency_height"] == pmjax.dependency_levels(pm).max() <= pm.n_batches
    assert info["original_faces"] == 5804
    assert sum(row["pcols"] for row in info["batches_detail"]) == pm.n_pcols
    k = 4
    lod = tmp_path / "lod.ply"
    assert main(["lod", str(out), "--batch", str(k), "-o", str(lod)]) == 0
    mesh = trimesh.load(lod, process=False)
    v, f, _ = pmjax.lod_mesh(pm, k)
    assert len(mesh.faces) == len(f) == info["batches_detail"][k]["faces_after"]
    assert np.allclose(np.sort(mesh.vertices, axis=0), np.sort(v, axis=0))


def test_build_file_version(tmp_path, data_path):
    """--file-version 1 writes the zip of version 1, the default version 2;
    both hold the same arrays."""
    paths = {v: tmp_path / f"cow{v}.pmz" for v in (1, 2)}
    assert main(["build", data_path("cow.ply"), "-o", str(paths[1]), "-q", "--file-version", "1"]) == 0
    assert main(["build", data_path("cow.ply"), "-o", str(paths[2]), "-q"]) == 0
    assert paths[1].read_bytes()[:2] == b"PK" and paths[2].read_bytes()[:4] == b"\x89PMZ"
    one, two = pmjax.read_pm(paths[1]), pmjax.read_pm(paths[2])
    assert one.header["version"] == 1 and two.header["version"] == 2
    a, b = one.arrays(), two.arrays()
    assert a.keys() == b.keys() and "shading_normals" in a
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_errors_are_clear_and_leave_no_output(tmp_path, capsys):
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nf 1 2 2\n")
    out = tmp_path / "o.pmz"
    assert main(["build", str(bad), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "bad.obj" in err and "no valid face" in err
    assert not out.exists()
    assert main(["lod", str(tmp_path / "missing.pmz"), "-o", str(tmp_path / "x.ply")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_build_refuses_bad_options_before_reading_and_huge_coordinates_clearly(tmp_path, capsys):
    """A mistyped metric is refused before the mesh is read (here: before a
    missing file is noticed); a coordinate beyond float32's range is an error
    naming the vertex, not a traceback."""
    out = tmp_path / "o.pmz"
    assert main(["build", str(tmp_path / "missing.ply"), "-o", str(out), "-q", "--metric", "quadirc"]) == 2
    err = capsys.readouterr().err
    assert "unknown metric 'quadirc'" in err and "no such file" not in err
    huge = tmp_path / "huge.ply"
    header = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty double z\n"
              "element face 2\nproperty list uchar int vertex_indices\nend_header\n")
    huge.write_text(header + "0 0 0\n1e100 0 0\n0 1e100 0\n1e100 1e100 1e99\n3 0 1 2\n3 1 3 2\n")
    assert main(["build", str(huge), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert f"error: {huge}: vertex 1 is at [1e+100, 0.0, 0.0], beyond float32's largest value" in err
    assert "Traceback" not in err
    assert not out.exists()


def test_lod_batch_out_of_range(tmp_path, capsys):
    out = tmp_path / "spot.pmz"
    assert main(["build", pmjax.default_model_path(), "-o", str(out), "-q"]) == 0
    assert main(["lod", str(out), "--batch", "999", "-o", str(tmp_path / "x.ply")]) == 2
    assert "batch 999 outside" in capsys.readouterr().err


def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    lines = capsys.readouterr().out.splitlines()
    # The version first, then one line per engine from engine_info (what refines here).
    assert info.value.code == 0 and lines[0] == f"pmjax {pmjax.__version__}" and lines[1] == "engines:"
    assert [line.split()[0] for line in lines[2:]] == list(pmjax.engine_info())


def test_info_engines_names_the_compiled_loops(capsys, monkeypatch):
    """`info --engines` says, per optional ctypes extension, whether its C
    loops or the NumPy steps run here."""
    import json

    from pmjax import _codec, _normals

    assert main(["info", "--engines", "--json"]) == 0
    loops = json.loads(capsys.readouterr().out)["compiled_loops"]
    assert loops["pmz decoder"] == (_codec.native is not None)
    assert loops["shading normals' fit"] == (_normals.native is not None)
    monkeypatch.setattr(_normals, "native", None)
    assert main(["info", "--engines"]) == 0
    assert "  shading normals' fit: NumPy" in capsys.readouterr().out.splitlines()


def test_messages_name_the_flags_and_the_remedy(tmp_path, capsys):
    out = str(tmp_path / "c.json")
    assert main(["camera", "look-at", "--eye", "1", "2", "3", "--target", "1", "2", "3", "-o", out]) == 2
    assert "--eye and --target are the same point" in capsys.readouterr().err
    assert main(["camera", "look-at", "--eye", "1", "2", "3", "--target", "0", "0", "0", "--up", "0", "0", "0",
                 "-o", out]) == 2
    assert "--up is zero" in capsys.readouterr().err
    # A mesh where a .pmz is needed.
    mesh = tmp_path / "spot.ply"
    mesh.write_bytes(open(pmjax.default_model_path(), "rb").read())
    assert main(["refine", str(mesh), "--eye", "0", "0", "3", "--target", "0", "0", "0",
                 "-o", str(tmp_path / "v.ply")]) == 2
    err = capsys.readouterr().err
    assert "is a PLY mesh, not a .pmz" in err and f"pmjax build {mesh} -o model.pmz" in err
    assert not (tmp_path / "v.ply").exists()
