"""Camera values checked where cameras enter: files read row by row and typed,
cameras made by hand (check_camera), and the first camera of a file read
without reading the rest (load_first_camera)."""

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import pmjax
from pmjax._camera import Camera, CameraError, check_camera, index_camera
from pmjax._camera_files import CSV_COLUMNS, load_cameras, load_first_camera
from pmjax._camera_table import read_camera_table, table_from_cameras, write_camera_table

LOOK = dict(eye=[0.0, 0.5, 3.0], target=[0.0, 0.0, 0.0])


def _cloud():
    return np.random.default_rng(0).normal(size=(40, 3))


def _write_csv(path, rows, header=CSV_COLUMNS):
    path.write_text(",".join(header) + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))


def _csv_row(camera, **change):
    """The CSV fields of one camera (as save_cameras writes them), some replaced by text."""
    values = dict(zip(CSV_COLUMNS, list(np.asarray(camera.eye, float)) + list(np.asarray(camera.rotation).ravel())
                      + [math.degrees(float(camera.fov_y)), float(camera.near), float(camera.far),
                         float(camera.ortho_height), int(camera.width), int(camera.height),
                         int(camera.orthographic)]))
    values.update(change)
    return [values[k] for k in CSV_COLUMNS]


def _assert_fields_equal(a, b):
    for name in ("eye", "rotation", "fov_y", "near", "far", "ortho_height", "width", "height"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), name
    assert a.orthographic == b.orthographic


# ---------------------------------------------------------------- files, per row and typed


def test_csv_rows_keep_their_own_image_size(tmp_path):
    cams = [pmjax.look_at(**LOOK, width=w, height=h) for w, h in ((640, 480), (800, 600), (32, 4096))]
    path = tmp_path / "c.csv"
    _write_csv(path, [_csv_row(c) for c in cams])
    back = load_cameras(path)
    assert np.asarray(back.width).tolist() == [640, 800, 32] and np.asarray(back.height).tolist() == [480, 600, 4096]


@pytest.mark.parametrize("flags, message", [
    ((0, 1), "camera 1 (line 3): orthographic is true but camera 0's is false"),
    ((1, 1, 0), "camera 2 (line 4): orthographic is false but camera 0's is true"),
])
def test_csv_rows_that_mix_projections_are_refused_by_row(tmp_path, flags, message):
    cam = pmjax.look_at(**LOOK)
    path = tmp_path / "c.csv"
    _write_csv(path, [_csv_row(cam, orthographic=f) for f in flags])
    with pytest.raises(CameraError) as info:
        load_cameras(path)
    assert str(info.value).startswith(f"{path}: {message}; the cameras of one file share the projection")


@pytest.mark.parametrize("text, want", [("1", True), ("0", False), ("true", True), ("false", False),
                                        ("TRUE", True), (" False ", False)])
def test_csv_flags_are_read_per_row(tmp_path, text, want):
    cam = pmjax.look_at(**LOOK)
    path = tmp_path / "c.csv"
    _write_csv(path, [_csv_row(cam, orthographic=text)] * 2)
    assert load_cameras(path).orthographic is want and load_first_camera(path).orthographic is want


@pytest.mark.parametrize("change, message", [
    (dict(orthographic="maybe"), "orthographic must be true or false, got 'maybe' (write true, false, 1 or 0)"),
    (dict(orthographic="2"), "orthographic must be true or false, got '2'"),
    (dict(orthographic="1.0"), "orthographic must be true or false, got '1.0'"),
    (dict(orthographic=""), "orthographic must be true or false, got ''"),
    (dict(fov_y_deg="true"), "fov_y_deg must be a number, got 'true'"),
    (dict(near="1_0"), "near must be a number, got '1_0'"),
    (dict(ex=""), "ex must be a number, got ''"),
    (dict(width="800.5"), "width must be an integer, got 800.5"),
    (dict(height="0"), "height must be an integer in [1, 65536], got 0"),
    (dict(ez="nan"), "eye must be finite, got [0.0, 0.5, nan]"),
    (dict(r00="2"), "rotation is not a 3×3 rotation matrix (orthonormal columns)"),
    (dict(far="0.0001"), "far must be greater than near"),
])
def test_csv_values_are_refused_by_camera_line_and_field(tmp_path, change, message):
    cam = pmjax.look_at(**LOOK)
    path = tmp_path / "c.csv"
    _write_csv(path, [_csv_row(cam), _csv_row(cam, **change)])
    with pytest.raises(CameraError) as info:
        load_cameras(path)
    assert str(info.value).startswith(f"{path}: camera 1 (line 3): {message}"), str(info.value)
    # The same value in the first row: load_first_camera refuses it too.
    _write_csv(path, [_csv_row(cam, **change), _csv_row(cam)])
    with pytest.raises(CameraError) as info:
        load_first_camera(path)
    assert str(info.value).startswith(f"{path}: camera 0 (line 2): {message}"), str(info.value)


def test_csv_layout_is_checked(tmp_path):
    cam = pmjax.look_at(**LOOK)
    path = tmp_path / "c.csv"
    cases = [
        (list(CSV_COLUMNS) + ["extra"], [_csv_row(cam) + [1]], "unknown column 'extra'; the columns are ex, ey, ez,"),
        (list(CSV_COLUMNS[:-1]), [_csv_row(cam)[:-1]], "column 'orthographic' is missing"),
        (list(CSV_COLUMNS) + ["ex"], [_csv_row(cam) + [0]], "column 'ex' appears twice"),
        (list(CSV_COLUMNS), [_csv_row(cam)[:-1]], "camera 0 (line 2): 18 fields, expected 19 (ex, ey, ez, r00,"),
        (list(CSV_COLUMNS), [], "no cameras (the header has no rows after it)"),
    ]
    for header, rows, message in cases:
        _write_csv(path, rows, header)
        for load in (load_cameras, load_first_camera):
            with pytest.raises(CameraError) as info:
                load(path)
            assert str(info.value).startswith(f"{path}: {message}"), str(info.value)
    path.write_text("")
    with pytest.raises(CameraError, match="empty file; a camera CSV starts with the header ex,ey,ez,r00"):
        load_cameras(path)
    # Blank lines between rows are skipped; columns may come in any order.
    order = list(reversed(CSV_COLUMNS))
    path.write_text(",".join(order) + "\n\n" + ",".join(map(str, reversed(_csv_row(cam)))) + "\n\n")
    _assert_fields_equal(load_first_camera(path), pmjax.look_at(**LOOK))


@pytest.mark.parametrize("doc, message", [
    ({"orthographic": "maybe", "cameras": [{**LOOK}]}, "orthographic must be true or false, got 'maybe'"),
    ({"orthographic": 1.0, "cameras": [{**LOOK}]}, "orthographic must be true or false, got 1.0"),
    ({"orthographic": 2, "cameras": [{**LOOK}]}, "orthographic must be true or false, got 2"),
    ({"cameras": []}, "no cameras ('cameras' is empty)"),
    ({"cameras": [{**LOOK}, {"eye": [True, 0, 1], "target": [0, 0, 0]}]},
     "camera 1: eye must be 3 numbers, got [True, 0, 1]"),
    ({"cameras": [{"eye": ["0", "0", "1"], "target": [0, 0, 0]}]}, "camera 0: eye must be 3 numbers, got ['0',"),
    ({"cameras": [{"eye": [0, 0, 1], "target": [0, 0, 0], "up": [0, False, 1]}]}, "camera 0: up must be 3 numbers"),
    ({"cameras": [{"eye": [0, 0, 1], "rotation": [[1, 0, 0], [0, True, 0], [0, 0, 1]]}]},
     "camera 0: rotation must be a 3×3 rotation matrix (3 rows of 3 numbers), got [[1, 0, 0], [0, True, 0]"),
    ({"cameras": [{"eye": [0, 0, 1], "rotation": [[1, 0, 0], [0, 1, 0]]}]},
     "camera 0: rotation must be a 3×3 rotation matrix (3 rows of 3 numbers), got shape (2, 3)"),
    ({"cameras": [{**LOOK, "fov_y_deg": True}]}, "camera 0: fov_y_deg must be a number, got True"),
    ({"cameras": [{**LOOK, "near": "0.1"}]}, "camera 0: near must be a number, got '0.1'"),
    ({"width": "800", "cameras": [{**LOOK}]}, "camera 0: width must be a number, got '800'"),
    ({"cameras": [{**LOOK, "height": 600.5}]}, "camera 0: height must be an integer, got 600.5"),
    ({"cameras": [{**LOOK, "width": False}]}, "camera 0: width must be a number, got False"),
])
def test_json_values_are_typed(tmp_path, doc, message):
    path = tmp_path / "c.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(CameraError) as info:
        load_cameras(path)
    assert str(info.value).startswith(f"{path}: {message}"), str(info.value)


@pytest.mark.parametrize("flag, want", [(True, True), (False, False), (1, True), (0, False)])
def test_json_flags_accept_booleans_and_0_or_1(tmp_path, flag, want):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"orthographic": flag, "width": 640.0, "cameras": [{**LOOK}]}))
    cams = load_cameras(path)
    assert cams.orthographic is want and int(cams.width[0]) == 640


def _good_columns(n=4):
    return dict(eye_x=np.zeros(n), eye_y=np.zeros(n), eye_z=np.full(n, 5.0),
                target_x=np.zeros(n), target_y=np.zeros(n), target_z=np.zeros(n))


def _write_columns(path, cols, **kw):
    if str(path).endswith(".npz"):
        np.savez(path, **cols)
    else:
        pq.write_table(pa.table(cols), path, **kw)


@pytest.mark.parametrize("suffix", [".npz", ".parquet"])
@pytest.mark.parametrize("change, message", [
    (dict(fov_y_deg=np.ones(4, bool)), "column 'fov_y_deg' holds booleans, expected numbers"),
    (dict(near=np.ones(4, bool)), "column 'near' holds booleans, expected numbers"),
    (dict(eye_x=np.zeros(4, bool)), "column 'eye_x' holds booleans, expected numbers"),
    (dict(width=np.ones(4, bool)), "column 'width' holds booleans, expected integers"),
    (dict(orthographic=np.array([0.0, 1.0, 0.0, 0.0])),
     "column 'orthographic' has dtype float64, expected booleans (or integers 0 and 1)"),
    (dict(orthographic=np.array([0, 1, 3, 0])), "row 2: column 'orthographic' must be 0 or 1 (or a boolean)"),
])
def test_table_columns_are_typed(tmp_path, suffix, change, message):
    path = tmp_path / f"t{suffix}"
    _write_columns(path, {**_good_columns(), **change})
    # (load_first_camera reads row 0 only: a fault in a later row is not its to find)
    for read in (read_camera_table,) if message.startswith("row 2") else (read_camera_table, load_first_camera):
        with pytest.raises(CameraError) as info:
            read(path)
        assert str(info.value) == f"{path}: {message}", str(info.value)


@pytest.mark.parametrize("suffix", [".npz", ".parquet"])
def test_table_flags_are_read_per_row(tmp_path, suffix):
    for flags in (np.array([True, False, True, False]), np.array([1, 0, 1, 0], np.int8)):
        path = tmp_path / f"t{suffix}"
        _write_columns(path, {**_good_columns(), "orthographic": flags})
        table = read_camera_table(path)
        assert table.orthographic.tolist() == [True, False, True, False]
        assert [(ortho, rows.tolist()) for ortho, rows in
                [(cam.orthographic, idx) for idx, cam in table.batches()]] == [(False, [1, 3]), (True, [0, 2])]
        with pytest.raises(CameraError, match=r"row 1: orthographic is false but row 0's is true"):
            load_cameras(path)


# ---------------------------------------------------------------- cameras made by hand


def _hand(camera=None, **change):
    """A Camera built field by field from a look-at camera, some fields replaced."""
    c = camera if camera is not None else pmjax.look_at(**LOOK)
    fields = dict(eye=c.eye, rotation=c.rotation, fov_y=c.fov_y, near=c.near, far=c.far,
                  ortho_height=c.ortho_height, width=c.width, height=c.height, orthographic=c.orthographic)
    fields.update(change)
    return Camera(**fields)


def _unchecked(**change):
    """:func:`_hand` made without Camera's own check (as a pytree function
    makes cameras), so that check_camera is what sees the bad value."""
    c = pmjax.look_at(**LOOK)
    fields = dict(eye=c.eye, rotation=c.rotation, fov_y=c.fov_y, near=c.near, far=c.far,
                  ortho_height=c.ortho_height, width=c.width, height=c.height, orthographic=c.orthographic)
    fields.update(change)
    camera = object.__new__(Camera)
    for name, value in fields.items():
        object.__setattr__(camera, name, value)
    return camera


def _rot_x(deg):
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


# (Camera fields changed, check_camera's message, the same value given to look_at, look_at's message)
BAD_VALUES = [
    (dict(eye=jnp.array([0.0, 0.0, jnp.nan])), "eye must be finite, got [0.0, 0.0, nan]",
     dict(eye=[0.0, 0.0, np.nan]), "eye must be finite"),
    (dict(height=0), "height must be an integer in [1, 65536], got 0",
     dict(height=0), "height must be an integer in [1, 65536], got 0"),
    (dict(width=0), "width must be an integer in [1, 65536], got 0",
     dict(width=0), "width must be an integer in [1, 65536], got 0"),
    (dict(width=70000), "width must be an integer in [1, 65536], got 70000",
     dict(width=70000), "width must be an integer in [1, 65536], got 70000"),
    (dict(near=jnp.float32(2.0), far=jnp.float32(1.0)), "far must be greater than near, got 1.0 <= 2.0",
     dict(near=2.0, far=1.0), "far must be greater than near, got 1.0 <= 2.0"),
    (dict(near=jnp.float32(0.0)), "near must be > 0, got 0.0", dict(near=0.0), "near must be > 0, got 0.0"),
    (dict(far=jnp.float32(jnp.inf)), "far must be finite, got inf", dict(far=np.inf), "far must be finite, got inf"),
    (dict(fov_y=jnp.float32(0.0)), "fov_y must lie in (0, pi) radians, got 0.0",
     dict(fov_y_deg=0.0), "fov_y_deg must lie in (0, 180) degrees, got 0.0"),
    (dict(fov_y=jnp.float32(math.pi)), "fov_y must lie in (0, pi) radians, got 3.14159274",
     dict(fov_y_deg=180.0), "fov_y_deg must lie in (0, 180) degrees, got 180.0"),
    (dict(orthographic=True, ortho_height=jnp.float32(0.0)), "ortho_height must be > 0, got 0.0",
     dict(orthographic=True, ortho_height=0.0), "ortho_height must be > 0, got 0.0"),
]


@pytest.mark.parametrize("change, message, look, look_message", BAD_VALUES)
def test_check_camera_and_look_at_refuse_the_same_values(change, message, look, look_message):
    with pytest.raises(CameraError) as info:
        check_camera(_unchecked(**change))
    assert str(info.value).startswith(f"camera: {message}"), str(info.value)
    # Camera(...) itself refuses it, as look_at does.
    with pytest.raises(CameraError) as info:
        _hand(**change)
    assert str(info.value).startswith(f"Camera: {message}"), str(info.value)
    args = {**LOOK, **look}
    with pytest.raises(CameraError) as info:
        pmjax.look_at(args.pop("eye"), args.pop("target"), **args)
    assert str(info.value).startswith(f"look_at: {look_message}"), str(info.value)


@pytest.mark.parametrize("change, message", [
    (dict(rotation=2.0 * np.eye(3)), "rotation is not orthonormal (its columns right, up and back must be unit "
     "vectors at right angles; largest entry of RᵀR − I: 3, allowed 0.0001): make it with look_at"),
    (dict(rotation=_rot_x(30) @ np.diag([1.0, 1.0, 1.001])), "rotation is not orthonormal"),
    (dict(rotation=np.diag([-1.0, 1.0, 1.0])), "rotation is a reflection (determinant -1)"),
    (dict(rotation=np.full((3, 3), np.nan)), "rotation must be finite, got [[nan, nan, nan],"),
    (dict(fov_y=True), "fov_y must be numbers, got bool values"),
    (dict(ortho_height=None), "ortho_height must be numbers, got NoneType"),
    (dict(eye=np.array(["0", "0", "3"])), "eye must be numbers, got <U1 values"),
    (dict(eye=jnp.zeros(2)), "eye must have shape [..., 3] (one position per camera), got shape (2,)"),
    (dict(near=jnp.ones(2)), "near has shape (2,), expected () (eye has shape (3,))"),
    (dict(rotation=jnp.eye(4)), "rotation has shape (4, 4), expected (3, 3)"),
])
def test_check_camera_refuses_hand_made_cameras(change, message):
    with pytest.raises(CameraError) as info:
        check_camera(_unchecked(**change))
    assert str(info.value).startswith(f"camera: {message}"), str(info.value)
    with pytest.raises(CameraError, match="^view: "):
        check_camera(_unchecked(**change), what="view")
    with pytest.raises(CameraError, match="^Camera: "):
        _hand(**change)


@pytest.mark.parametrize("change, message", [
    (dict(width=800.5), "Camera: width must be an integer in [1, 65536] (pixels), got 800.5"),
    (dict(height=np.array(600.25)), "Camera: height must be an integer in [1, 65536] (pixels), got 600.25"),
    (dict(width=float("nan")), "Camera: width must be an integer in [1, 65536] (pixels), got nan"),
    (dict(width=2.0 ** 40), "Camera: width must be an integer in [1, 65536] (pixels), got 1099511627776.0"),
    (dict(width=np.int64(2) ** 33), "Camera: width must be an integer in [1, 65536] (pixels), got 8589934592"),
    (dict(width=True), "Camera: width must be an integer (pixels), got True"),
    (dict(width=jnp.ones((), bool)), "Camera: width must be integers (pixels), got booleans"),
    (dict(height="600"), "Camera: height must be integers (pixels), got <U3 values"),
    (dict(orthographic="maybe"), "Camera: orthographic must be true or false, got 'maybe' (a bool, or the "
     "integer 0 or 1)"),
    (dict(orthographic=2), "Camera: orthographic must be true or false, got 2"),
])
def test_camera_refuses_what_it_cannot_keep(change, message):
    """The int32 cast would change these sizes (800.5 becomes 800): the constructor refuses them."""
    with pytest.raises(CameraError) as info:
        _hand(**change)
    assert str(info.value).startswith(message), str(info.value)


def test_camera_keeps_whole_sizes_and_flags():
    cam = _hand(width=640.0, height=np.array(480), orthographic=1)
    assert int(cam.width) == 640 and cam.height.dtype == jnp.int32 and cam.orthographic is True
    check_camera(_hand(orthographic=np.bool_(False)))
    assert pmjax.look_at(**LOOK, orthographic=1).orthographic is True
    with pytest.raises(CameraError, match="^look_at: orthographic must be true or false, got 'true'"):
        pmjax.look_at(**LOOK, orthographic="true")
    # A size stored as a float by eqx.tree_at (no constructor): checked by check_camera.
    with pytest.raises(CameraError, match=r"^camera: width must be an integer in \[1, 65536\], got 800.5$"):
        check_camera(eqx.tree_at(lambda c: c.width, _hand(), jnp.float32(800.5)))
    check_camera(eqx.tree_at(lambda c: c.width, _hand(), np.float64(800.0)))


def test_check_camera_accepts_the_cameras_pmjax_makes():
    v = _cloud()
    single = pmjax.look_at(**LOOK)
    for cam in (single, pmjax.look_at(**LOOK, host=True), single.astype(jnp.float16), single.astype(jnp.bfloat16),
                pmjax.look_at(**LOOK, orthographic=True, fov_y_deg=180.0 - 1e-9, ortho_height=1e-3),
                pmjax.random_views(v, 500, seed=3, min_scale=1e-3, max_scale=1e3), pmjax.standard_orbit(v, 7),
                pmjax.fly_through([([0, 0, 5.0], [0, 0, 0]), ([5.0, 0, 0], [0, 0, 0])], 4),
                table_from_cameras(pmjax.random_views(v, 9, seed=1)).camera(np.float32)):
        check_camera(cam)
    # Paths: two leading axes.
    check_camera(jax.tree.map(lambda a: a.reshape((2, 3) + a.shape[1:]), pmjax.standard_orbit(v, 6)))


def _bad_batch(n=10, **rows):
    """A host batch with values replaced at some rows: field=(row, value)."""
    host = jax.tree.map(lambda a: np.array(a), pmjax.random_views(_cloud(), n, seed=2))
    for field, (row, value) in rows.items():
        getattr(host, field)[row] = value
    return host


def test_check_camera_names_the_first_bad_camera():
    bad = _bad_batch(near=(7, 0.0), rotation=(4, 2.0 * np.eye(3)))
    with pytest.raises(CameraError, match=r"^cameras\[4\]: rotation is not orthonormal"):
        check_camera(bad, what="cameras")
    bad = _bad_batch(near=(2, 0.0), rotation=(4, 2.0 * np.eye(3)))
    with pytest.raises(CameraError, match=r"^cameras\[2\]: near must be > 0, got 0.0$"):
        check_camera(bad, what="cameras")
    bad = _bad_batch(eye=(9, np.nan), far=(3, -1.0))
    with pytest.raises(CameraError, match=r"^cameras\[3\]: far must be greater than near, got -1.0 <="):
        check_camera(bad, what="cameras")
    bad = _bad_batch(height=(6, 0))
    with pytest.raises(CameraError, match=r"^camera\[6\]: height must be an integer in \[1, 65536\], got 0$"):
        check_camera(bad)
    # Two leading axes (K paths of T frames): the index is [k, t].
    paths = jax.tree.map(lambda a: a.reshape((2, 5) + a.shape[1:]), _bad_batch(fov_y=(7, 4.0)))
    with pytest.raises(CameraError, match=r"^cameras\[1, 2\]: fov_y must lie in \(0, pi\) radians, got 4.0$"):
        check_camera(paths, what="cameras")
    # A batch of JAX arrays, as refine_batch receives it.
    with pytest.raises(CameraError, match=r"^cameras\[5\]: eye must be finite"):
        check_camera(jax.tree.map(jnp.asarray, _bad_batch(eye=(5, np.inf))), what="cameras")
    with pytest.raises(CameraError, match=r"^cameras: fov_y has shape \(3,\), expected \(10,\)"):
        check_camera(eqx.tree_at(lambda c: c.fov_y, _bad_batch(), np.ones(3)), what="cameras")
    with pytest.raises(CameraError, match="^camera must be a pmjax.Camera, got dict$"):
        check_camera({"eye": [0, 0, 1]})


def test_check_camera_trusts_traced_values():
    bad = _unchecked(height=jnp.int32(0))
    with pytest.raises(CameraError):
        check_camera(bad)
    # Under jit and vmap the values are unknown: nothing is checked, nothing raised.
    assert float(jax.jit(lambda c: (check_camera(c), c.near)[1])(bad)) == pytest.approx(float(bad.near))
    batch = _bad_batch(near=(3, 0.0))
    got = jax.vmap(lambda c: (check_camera(c), c.near)[1])(jax.tree.map(jnp.asarray, batch))
    assert np.array_equal(np.asarray(got), batch.near)


def test_check_camera_is_vectorized():
    """A batch of 10^5 cameras is checked in well under a second (vectorized,
    no Python loop over cameras)."""
    import time

    cams = pmjax.random_views(_cloud(), 100_000, seed=5)
    check_camera(cams)
    start = time.perf_counter()
    check_camera(cams, what="cameras")
    assert time.perf_counter() - start < 1.0
    cams = eqx.tree_at(lambda c: c.near, cams, np.asarray(cams.near).copy())
    cams.near[99_999] = -1.0
    with pytest.raises(CameraError, match=r"^cameras\[99999\]: near must be > 0, got -1.0$"):
        check_camera(cams, what="cameras")


# ---------------------------------------------------------------- the first camera only


@pytest.mark.parametrize("suffix", [".json", ".csv", ".npz", ".parquet"])
@pytest.mark.parametrize("orthographic", [False, True])
def test_first_camera_is_camera_0_of_the_file(tmp_path, suffix, orthographic):
    v = _cloud()
    cams = pmjax.random_views(v, 6, seed=7, width=320, height=200)
    cams = Camera(cams.eye, cams.rotation, cams.fov_y, cams.near, cams.far, cams.ortho_height, cams.width,
                  cams.height, orthographic=orthographic)
    path = tmp_path / f"cams{suffix}"
    if suffix in (".json", ".csv"):
        pmjax.save_cameras(cams, path)
    else:
        write_camera_table(table_from_cameras(cams), path)
    first = load_first_camera(path)
    assert pmjax.camera_count(first) == 0
    _assert_fields_equal(first, index_camera(load_cameras(path), 0))
    assert np.allclose(np.asarray(first.eye), np.asarray(cams.eye[0]), atol=1e-6)
    check_camera(first)


def test_first_camera_of_a_csv_reads_one_row(tmp_path):
    cam = pmjax.look_at(**LOOK)
    path = tmp_path / "c.csv"
    _write_csv(path, [_csv_row(cam)])
    with open(path, "ab") as fh:  # whatever follows the first row is not read
        fh.write(b"\xff\xfe not text, not a row\n" + b"x" * (2 << 20) + b"\n")
    _assert_fields_equal(load_first_camera(path), cam)
    with pytest.raises(CameraError) as info:
        load_cameras(path)
    assert str(info.value) == f"{path}: line 3 is not UTF-8 text: not a camera CSV file"
    with open(path, "ab") as fh:
        fh.write(b"y" * (1 << 20) + b"\n")
    with pytest.raises(CameraError) as info:
        load_cameras(path)
    assert str(info.value) == f"{path}: line 3 is not UTF-8 text: not a camera CSV file"
    _write_csv(path, [_csv_row(cam)] * 2)
    with open(path, "ab") as fh:
        fh.write(b"y" * (1 << 20) + b"z\n")
    with pytest.raises(CameraError) as info:
        load_cameras(path)
    assert str(info.value) == f"{path}: line 4 is longer than 1048576 bytes: not a camera CSV row"
    # A byte-order mark (as spreadsheets write) before the header is allowed.
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes().splitlines(keepends=True)[0]
                     + ",".join(map(str, _csv_row(cam))).encode() + b"\n")
    _assert_fields_equal(load_first_camera(path), cam)


def test_first_camera_of_a_parquet_table_reads_its_first_row_group(tmp_path):
    cols = _good_columns(6)
    cols["eye_z"] = np.array([5.0, 5.0, 5.0, 5.0, np.nan, 5.0])
    path = tmp_path / "t.parquet"
    _write_columns(path, cols, row_group_size=2)
    assert pq.ParquetFile(path).metadata.num_row_groups == 3
    first = load_first_camera(path)
    assert np.asarray(first.eye).tolist() == [0.0, 0.0, 5.0]
    with pytest.raises(CameraError, match="row 4: column 'eye_z' is nan"):
        read_camera_table(path)
    assert len(read_camera_table(path, limit=3)) == 3
    # The last row group's pages overwritten with garbage: never read for the first camera.
    meta = pq.ParquetFile(path).metadata
    group = meta.row_group(2)
    chunks = [group.column(i) for i in range(group.num_columns)]
    starts = [c.dictionary_page_offset if c.has_dictionary_page else c.data_page_offset for c in chunks]
    lo, hi = min(starts), max(start + c.total_compressed_size for start, c in zip(starts, chunks))
    data = bytearray(path.read_bytes())
    data[lo:hi] = b"\xff" * (hi - lo)
    path.write_bytes(bytes(data))
    assert np.asarray(load_first_camera(path).eye).tolist() == [0.0, 0.0, 5.0]
    with pytest.raises(CameraError, match="cannot read the camera table"):
        read_camera_table(path)
    _write_columns(path, {k: v[:0] for k, v in cols.items()})
    with pytest.raises(CameraError, match=r"t.parquet: no cameras \(the table has no rows\)$"):
        load_first_camera(path)


@pytest.mark.parametrize("save", [np.savez, np.savez_compressed])
def test_first_camera_of_an_npz_table_reads_the_heads_of_its_columns(tmp_path, save):
    cols = _good_columns(5)
    cols["eye_z"] = np.array([5.0, np.nan, 5.0, 5.0, 5.0])
    path = tmp_path / "t.npz"
    save(path, **cols, width=np.array([64, 0, 64, 64, 64]))
    first = load_first_camera(path)
    assert np.asarray(first.eye).tolist() == [0.0, 0.0, 5.0] and int(first.width) == 64
    with pytest.raises(CameraError, match="row 1: column 'eye_z' is nan"):
        read_camera_table(path)
    # Shapes and kinds come from the column headers, before any value is read.
    for change, message in [(dict(eye_y=np.zeros(4)), "column 'eye_y' has shape (4,), expected (5,)"),
                            (dict(eye_y=np.zeros((5, 2))), "column 'eye_y' has shape (5, 2), expected (5,)"),
                            (dict(eye_x=np.float64(1.0)), "column 'eye_x' is not a column"),
                            (dict(near=np.array([1, "a"], object)), "column 'near' has dtype object")]:
        save(path, **{**cols, **change})
        with pytest.raises(CameraError) as info:
            load_first_camera(path)
        assert str(info.value).startswith(f"{path}: {message}"), str(info.value)
    path.write_bytes(b"not a zip file")
    with pytest.raises(CameraError, match="cannot read the camera table"):
        load_first_camera(path)


def test_first_camera_of_a_large_json_file_is_refused(tmp_path, monkeypatch):
    path = tmp_path / "big.json"
    path.write_text(json.dumps({"cameras": [{**LOOK}] * 50}))
    _assert_fields_equal(load_first_camera(path), pmjax.look_at(**LOOK))
    monkeypatch.setattr(pmjax._camera_files, "MAX_JSON_BYTES", 1000)
    with pytest.raises(CameraError) as info:
        load_first_camera(path)
    size = path.stat().st_size
    assert str(info.value) == (
        f"{path}: a JSON camera file is read whole, and this one has {size} bytes (the limit is 1000 bytes, "
        "0.000953674 MiB): write the cameras as a .csv file or a .parquet table (read only as far as needed), "
        "or split the file")
    assert pmjax._camera_files.MAX_JSON_BYTES == 1000 and size > 1000
    monkeypatch.undo()
    assert pmjax._camera_files.MAX_JSON_BYTES == 64 << 20


def test_read_camera_table_limit_is_checked(tmp_path):
    path = tmp_path / "t.npz"
    np.savez(path, **_good_columns())
    for limit in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match=f"limit must be an integer >= 1 or None, got {limit!r}"):
            read_camera_table(path, limit=limit)
    assert len(read_camera_table(path, limit=10)) == 4
