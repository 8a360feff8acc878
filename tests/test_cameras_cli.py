"""Camera files and the refine/path commands."""

import csv
import json

import numpy as np
import pytest

import pmjax
from pmjax._camera import camera_count, index_camera
from pmjax._cli import main


@pytest.mark.parametrize("ext", ["json", "csv"])
def test_camera_files_round_trip(tmp_path, ext):
    cams = pmjax.random_views(np.random.default_rng(0).normal(size=(50, 3)), 5, seed=1)
    path = tmp_path / f"cams.{ext}"
    pmjax.save_cameras(cams, path)
    back = pmjax.load_cameras(path)
    assert camera_count(back) == 5
    for name in ("eye", "rotation", "fov_y", "near", "far"):
        assert np.allclose(np.asarray(getattr(back, name)), np.asarray(getattr(cams, name)), atol=1e-5), name


def test_a_rotation_camera_reads_back_as_stored_and_needs_near_and_far(tmp_path):
    """A JSON camera given by its rotation keeps that rotation bit for bit,
    as a camera table does; without near and far (no target, so nothing to
    scale their defaults by) it is refused, in JSON and in a table."""
    cams = pmjax.random_views(np.random.default_rng(0).normal(size=(50, 3)) * 1e3, 40, seed=2)
    pmjax.save_cameras(cams, tmp_path / "c.json")
    pmjax.write_camera_table(pmjax.table_from_cameras(cams), tmp_path / "c.parquet")
    text, table = pmjax.load_cameras(tmp_path / "c.json"), pmjax.load_cameras(tmp_path / "c.parquet")
    for name in ("eye", "rotation", "near", "far"):
        assert np.array_equal(np.asarray(getattr(text, name)), np.asarray(getattr(table, name))), name
    p = tmp_path / "r.json"
    p.write_text(json.dumps({"cameras": [{"eye": [0, 0, 1], "rotation": np.eye(3).tolist(), "near": 0.1}]}))
    with pytest.raises(pmjax.CameraError, match="camera 0: a camera given by 'rotation' needs 'near' and 'far'"):
        pmjax.load_cameras(p)
    cols = {"eye_x": [0.0], "eye_y": [0.0], "eye_z": [1.0]}
    cols.update({f"r{i}{j}": [float(i == j)] for i in range(3) for j in range(3)})
    np.savez(tmp_path / "r.npz", **{k: np.asarray(v) for k, v in cols.items()})
    with pytest.raises(pmjax.CameraError, match="r.npz: columns r00..r22 need columns 'near' and 'far'"):
        pmjax.load_cameras(tmp_path / "r.npz")


def test_orbit_of_a_mesh_file_and_of_its_pmz_are_the_same_cameras(tmp_path, data_path):
    """A mesh file's cameras come from the float32 vertices its hierarchy
    stores, also where its coordinates are not float32 numbers."""
    import trimesh

    mesh = trimesh.load(data_path("cow.ply"), process=False)
    v = np.asarray(mesh.vertices, np.float64) / 3.0 + 0.1
    src = tmp_path / "third.off"  # written by hand: every digit of the float64 values
    src.write_text(f"OFF\n{len(v)} {len(mesh.faces)} 0\n" + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in v.tolist())
                   + "".join(f"3 {a} {b} {c}\n" for a, b, c in mesh.faces))
    assert not np.array_equal(pmjax.load_clean_mesh(str(src))[0], v.astype(np.float32))
    assert main(["build", str(src), "-o", str(tmp_path / "third.pmz"), "-q"]) == 0
    got = []
    for model, out in ((src, "a.npz"), (tmp_path / "third.pmz", "b.npz")):
        assert main(["camera", "orbit", str(model), "-n", "16", "-o", str(tmp_path / out)]) == 0
        got.append(pmjax.read_camera_table(tmp_path / out))
    for name in ("eye", "rotation", "near", "far"):
        assert np.array_equal(getattr(got[0], name), getattr(got[1], name)), name


def test_camera_outputs_are_written_by_their_extension_in_any_case(tmp_path, data_path, capsys):
    model = data_path("cow.ply")
    for name, read in (("o.CSV", lambda p: p.read_text().startswith("ex,ey,ez,r00")),
                       ("o.Json", lambda p: p.read_text().lstrip().startswith("{")),
                       ("o.NPZ", lambda p: p.read_bytes()[:2] == b"PK"),
                       ("o.Parquet", lambda p: p.read_bytes()[:4] == b"PAR1")):
        assert main(["camera", "orbit", model, "-n", "3", "-o", str(tmp_path / name)]) == 0
        assert read(tmp_path / name), name
        assert camera_count(pmjax.load_cameras(tmp_path / name)) == 3
    capsys.readouterr()
    assert main(["camera", "orbit", model, "-n", "3", "-o", str(tmp_path / "o.txt")]) == 2
    err = capsys.readouterr().err
    assert "o.txt: cameras are written as .json, .csv, .npz, .parquet (by extension), not .txt" in err
    assert not (tmp_path / "o.txt").exists()
    with pytest.raises(pmjax.CameraError, match="cameras are written as .json, .csv"):
        pmjax.save_cameras(pmjax.load_cameras(tmp_path / "o.CSV"), tmp_path / "x.npz")


def test_bad_camera_files_name_the_camera(tmp_path):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"cameras": [{"eye": [0, 0, 1], "target": [0, 0, 0]}, {"eye": [1, 2]}]}))
    with pytest.raises(ValueError, match="camera 1"):
        pmjax.load_cameras(p)
    p.write_text("{not json")
    with pytest.raises(ValueError, match="c.json"):
        pmjax.load_cameras(p)
    p.write_text(json.dumps({"cameras": [{"eye": [0, 0, 1], "rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}]}))
    with pytest.raises(ValueError, match="not a 3×3 rotation"):
        pmjax.load_cameras(p)


def test_fly_through_and_orthographic_views(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    v = data.vertices[: data.n_original_vertices]
    c = v.mean(0)
    path = pmjax.fly_through([(c + [0, 0, 40], c), (c + [40, 0, 0], c)], 5)
    eyes = np.asarray(path.eye)
    assert np.allclose(eyes[0], c + [0, 0, 40], atol=1e-4) and np.allclose(eyes[-1], c + [40, 0, 0], atol=1e-4)
    ortho = pmjax.look_at(c + [0, 0, 40], c, orthographic=True, ortho_height=20.0)
    r_small = pmjax.refine(pm, ortho, 1.0)
    tight = pmjax.look_at(c + [0, 0, 40], c, orthographic=True, ortho_height=2.0)  # zoomed in: more detail inside
    r_zoom = pmjax.refine(pm, tight, 1.0, tests=pmjax.Tests(frustum=False, orientation=False))
    r_wide = pmjax.refine(pm, ortho, 1.0, tests=pmjax.Tests(frustum=False, orientation=False))
    assert int(r_zoom.n_faces) > int(r_wide.n_faces)
    assert 0 < int(r_small.n_faces) < len(data.faces)


@pytest.mark.slow
def test_refine_and_path_commands(tmp_path, built, capsys):
    data = built("cow.ply")
    pmz = tmp_path / "cow.pmz"
    pmjax.save_pm(data, pmz)
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 6)
    pmjax.save_cameras(cams, tmp_path / "path.json")
    pmjax.save_cameras(index_camera(cams, 2), tmp_path / "one.json")
    out = tmp_path / "view.ply"
    assert main(["refine", str(pmz), "--camera", str(tmp_path / "one.json"), "--tau", "2", "-o", str(out),
                 "--stats-json", str(tmp_path / "s.json")]) == 0
    stats = json.loads((tmp_path / "s.json").read_text())
    r = pmjax.refine(pmjax.ProgressiveMesh.from_data(data), index_camera(cams, 2), 2.0)
    assert stats["faces"] == int(r.n_faces)
    import trimesh

    assert len(trimesh.load(out, process=False).faces) == stats["faces"]
    assert main(["path", str(pmz), "--path", str(tmp_path / "path.json"), "--csv", str(tmp_path / "p.csv"), "-q",
                 "--no", "orientation"]) == 0
    rows = list(csv.DictReader(open(tmp_path / "p.csv")))
    assert len(rows) == 6 and all(float(row["milliseconds"]) > 0 for row in rows)
    got = [int(row["faces"]) for row in rows]
    want = pmjax.refine_batch(pmjax.ProgressiveMesh.from_data(data), cams, 1.0,
                              tests=pmjax.Tests(orientation=False))["faces"]
    assert got == list(want)
    # Both engines through the CLI: the same rows, and the same mesh file.
    assert main(["path", str(pmz), "--path", str(tmp_path / "path.json"), "--csv", str(tmp_path / "f.csv"), "-q",
                 "--no", "orientation", "--method", "front"]) == 0
    assert [int(row["faces"]) for row in csv.DictReader(open(tmp_path / "f.csv"))] == got
    front = tmp_path / "front.ply"
    assert main(["refine", str(pmz), "--camera", str(tmp_path / "one.json"), "--tau", "2", "-o", str(front),
                 "--method", "front"]) == 0
    assert front.read_bytes() == out.read_bytes()
    assert main(["path", str(pmz), "--orbit", "3", "-q"]) == 0
    assert main(["refine", str(pmz), "--camera", str(tmp_path / "missing.json"), "-o", str(out)]) == 2
    assert "cannot read cameras" in capsys.readouterr().err


@pytest.mark.parametrize("ext", ["json", "csv"])
def test_failed_camera_write_leaves_the_old_file(tmp_path, monkeypatch, ext):
    """A write that fails halfway (after its first bytes) leaves the file
    that was there, whole, and no temporary."""
    cams = pmjax.random_views(np.random.default_rng(0).normal(size=(20, 3)), 2)
    path = tmp_path / f"c.{ext}"
    pmjax.save_cameras(cams, path)
    before = path.read_bytes()

    def fail_midway(*args, **kw):
        fh = args[1] if len(args) > 1 else kw["fp"]
        fh.write("{partial")
        raise OSError("disk gone")

    def fail_row(self, row):
        raise OSError("disk gone")

    monkeypatch.setattr(json, "dump", fail_midway)
    monkeypatch.setattr(pmjax._camera_files.csv, "writer", lambda fh: type("W", (), {
        "writerow": lambda self, row: fh.write("ex,") and fail_row(self, row)})())
    with pytest.raises(OSError, match="disk gone"):
        pmjax.save_cameras(cams, path)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [path.name]


@pytest.mark.parametrize("kw, message", [
    (dict(fov_y_deg=0), "fov_y_deg must lie in (0, 180)"), (dict(fov_y_deg=180), "fov_y_deg must lie in (0, 180)"),
    (dict(fov_y_deg=-5), "fov_y_deg must lie in (0, 180)"), (dict(fov_y_deg=float("nan")), "fov_y_deg must be finite"),
    (dict(width=0), "width must be an integer in [1, 65536]"), (dict(height=0), "height must be an integer in"),
    (dict(width=800.5), "width must be an integer, got 800.5"), (dict(width=True), "width must be a number"),
    (dict(near=-1.0), "near must be > 0"), (dict(near=2.0, far=1.0), "far must be greater than near"),
    (dict(orthographic="yes"), "orthographic must be true or false, got 'yes'"),
    (dict(orthographic=True, ortho_height=0.0), "ortho_height must be > 0"),
    (dict(eye=[0, 0, float("nan")]), "eye must be finite"), (dict(target=[0, 0, float("inf")]), "target must be finite"),
    (dict(up=[0, 0, 0]), "up is zero"), (dict(eye=[0, 0, 0]), "eye and target coincide"),
    (dict(eye=[0, 0]), "eye must be 3 numbers"),
])
def test_look_at_refuses_values_out_of_range(kw, message):
    args = dict(eye=[0, 0, 3], target=[0, 0, 0])
    args.update(kw)
    eye, target, up = args.pop("eye"), args.pop("target"), args.pop("up", (0, 1, 0))
    with pytest.raises(pmjax.CameraError) as info:
        pmjax.look_at(eye, target, up, **args)
    assert str(info.value).startswith("look_at: ") and message in str(info.value)


@pytest.mark.parametrize("doc, message", [
    ([1, 2], "expected a JSON object (one camera, or cameras: [...]), got list"),
    (None, "got NoneType"), (5, "got int"),
    ({"cameras": 3}, "'cameras' must be a list, got int"),
    ({"widht": 5, "cameras": []}, "unknown key 'widht'; known keys: width, height, orthographic, cameras"),
    ({"cameras": [{"eyes": [0, 0, 1], "target": [0, 0, 0]}]}, "camera 0: unknown key 'eyes'; known keys: eye,"),
    ({"cameras": [{"eye": [0, 0, 1], "target": [0, 0, 0]}, {"eye": [0, 0, 1], "target": [0, 0, 0], "fov_deg": 4}]},
     "camera 1: unknown key 'fov_deg'"),
    ({"cameras": [{"eye": [0, 0, 1]}]}, "camera 0: give either 'target' (and optionally 'up') or 'rotation', neither"),
    ({"cameras": [{"target": [0, 0, 1]}]}, "camera 0: 'eye' is missing"),
    ({"cameras": [{"eye": [0, 0, 1], "rotation": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}]}, "camera 0: rotation is a reflection"),
    ({"cameras": [{"eye": [0, 0, 1], "rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}]}, "camera 0: rotation is not a 3×3"),
    ({"orthographic": "yes", "cameras": [{"eye": [0, 0, 1], "target": [0, 0, 0]}]}, "orthographic must be true or false"),
    ({"height": 0, "cameras": [{"eye": [0, 0, 1], "target": [0, 0, 0]}]}, "camera 0: height must be an integer in"),
    ({"eye": [0, 0, 1], "target": [0, 0, 0], "orthographic": True, "ortho_height": -1}, "ortho_height must be > 0"),
])
def test_camera_files_are_refused_by_camera_and_key(tmp_path, doc, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(pmjax.CameraError) as info:
        pmjax.load_cameras(path)
    assert str(info.value).startswith(f"{path}: ") and message in str(info.value), str(info.value)
    # A single camera with the file's keys is fine.
    path.write_text(json.dumps({"eye": [0, 0, 1], "target": [0, 0, 0], "orthographic": True, "width": 64}))
    assert int(pmjax.load_cameras(path).width[0]) == 64


def test_camera_command_writes_every_kind(tmp_path, built, data_path, capsys):
    model = data_path("cow.ply")
    pm_path = tmp_path / "cow.pmz"
    pmjax.save_pm(built("cow.ply"), pm_path)
    v = pmjax.read_pm(pm_path).vertices[: pmjax.read_pm(pm_path).n_original_vertices]
    # look-at: the values typed, kept exactly, and the same view as --eye/--target on refine
    cam = tmp_path / "cam.json"
    assert main(["camera", "look-at", "--eye", "0", "1.5", "12", "--target", "0", "0.1", "0", "--size", "640",
                 "480", "--fov", "30", "-o", str(cam)]) == 0
    doc = json.loads(cam.read_text())
    assert doc["cameras"][0]["eye"] == [0.0, 1.5, 12.0] and (doc["width"], doc["height"]) == (640, 480)
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    assert main(["refine", str(pm_path), "--camera", str(cam), "-o", str(a)]) == 0
    assert main(["refine", str(pm_path), "--eye", "0", "1.5", "12", "--target", "0", "0.1", "0", "--size", "640",
                 "480", "--fov", "30", "-o", str(b)]) == 0
    assert a.read_bytes() == b.read_bytes()
    # A camera file gives the whole camera: look-at flags beside it are refused, not ignored.
    capsys.readouterr()
    assert main(["refine", str(pm_path), "--camera", str(cam), "--fov", "60", "--size", "64", "64", "-o", str(a)]) == 2
    assert "--camera gives the whole camera; --fov, --size only go with --eye" in capsys.readouterr().err
    # orbit round a mesh file or its .pmz: the standard orbit
    want = pmjax.standard_orbit(v, 24, width=400, height=300)
    for src, out in ((model, "orbit.json"), (str(pm_path), "orbit.csv")):
        assert main(["camera", "orbit", src, "-n", "24", "--size", "400", "300", "-o", str(tmp_path / out)]) == 0
        got = pmjax.load_cameras(tmp_path / out)
        assert camera_count(got) == 24 and np.array_equal(np.asarray(got.eye), np.asarray(want.eye))
        assert np.allclose(np.asarray(got.rotation), np.asarray(want.rotation), atol=1e-7)
    # random views and a fly-through, as tables for pmjax eval
    assert main(["camera", "random", str(pm_path), "-n", "100", "--seed", "4", "-o", str(tmp_path / "r.npz")]) == 0
    table = pmjax.read_camera_table(tmp_path / "r.npz")
    assert np.array_equal(table.camera().eye, np.asarray(pmjax.random_views(v, 100, seed=4).eye))
    assert main(["camera", "fly", model, "-n", "30", "-o", str(tmp_path / "f.parquet")]) == 0
    assert len(pmjax.read_camera_table(tmp_path / "f.parquet")) == 30
    capsys.readouterr()
    # errors: a degenerate view, a missing --target, a non-finite coordinate
    assert main(["camera", "look-at", "--eye", "0", "0", "0", "--target", "0", "0", "0", "-o", str(cam)]) == 2
    assert "--eye and --target are the same point" in capsys.readouterr().err
    assert main(["refine", str(pm_path), "--eye", "0", "0", "5", "-o", str(a)]) == 2
    assert "--eye needs --target" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["camera", "look-at", "--eye", "0", "0", "inf", "--target", "0", "0", "0", "-o", str(cam)])
    assert "argument --eye: inf is not a finite number" in capsys.readouterr().err


@pytest.mark.parametrize("ext", ["npz", "parquet"])
def test_load_cameras_reads_camera_tables(tmp_path, ext):
    cams = pmjax.random_views(np.random.default_rng(0).normal(size=(50, 3)), 5, seed=1, width=320, height=200)
    path = tmp_path / f"cams.{ext}"
    pmjax.write_camera_table(pmjax.table_from_cameras(cams), path)
    back = pmjax.load_cameras(path)
    assert camera_count(back) == 5 and back.orthographic is False
    for name in ("eye", "rotation", "near", "far", "width", "height"):
        got, want = np.asarray(getattr(back, name)), np.asarray(getattr(cams, name))
        assert got.dtype == want.dtype and np.array_equal(got, want), name
    assert np.allclose(np.asarray(back.fov_y), np.asarray(cams.fov_y), rtol=1e-7, atol=0)
    first = pmjax._camera_files.load_first_camera(path)
    assert np.array_equal(np.asarray(first.eye), np.asarray(cams.eye[0])) and int(first.width) == 320
