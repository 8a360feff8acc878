"""Camera sets as columnar tables: plain NumPy columns, one row per camera.

A :class:`CameraTable` is what large evaluations read and generate: millions of
cameras never become millions of Python objects, and any row range turns into
:class:`pmjax.Camera` batches (one per projection) on demand.

Files (``.npz`` or Parquet) hold the same flat columns (documented in
docs/eval.md): ``eye_x, eye_y, eye_z``; the orientation as
``target_x, target_y, target_z`` (with optional ``up_x, up_y, up_z``, default
+y) or as the camera-to-world rotation ``r00 … r22`` (row-major; columns
right, up, back); optional ``fov_y_deg`` (45), ``ortho_height`` (1),
``width`` (800), ``height`` (600), ``near``, ``far`` (default 1e-3 and 1e3
times the eye–target distance, or 1e-3 and 1e3 with a rotation),
``orthographic`` (false), ``path_id`` and ``frame``.

The generators (orbit, fly-through, random views) give row ranges of a set
without building the rest, and a row's camera depends on its index only, so a
set cut into chunks gives the same cameras however it is cut.
"""

from __future__ import annotations

import dataclasses
import math
import os
import zipfile
from typing import Iterator, Optional

import numpy as np

from ._atomic import atomic_path
from ._camera import Camera, CameraError, check_camera_values, look_at_rotations

# Column names of the file schema, grouped as they are read.
EYE = ("eye_x", "eye_y", "eye_z")
TARGET = ("target_x", "target_y", "target_z")
UP = ("up_x", "up_y", "up_z")
ROTATION = tuple(f"r{i}{j}" for i in range(3) for j in range(3))
SCALARS = ("fov_y_deg", "ortho_height", "near", "far")
SIZES = ("width", "height")
COLUMNS = EYE + TARGET + UP + ROTATION + SCALARS + SIZES + ("orthographic", "path_id", "frame")

# Block of rows drawn from one seeded generator (random views): fixed, so a
# row's camera does not depend on how the set is chunked.
RANDOM_BLOCK = 4096


@dataclasses.dataclass(frozen=True)
class CameraTable:
    """N cameras as columns (float64 geometry, so files round-trip exactly).

    Attributes:
        eye: ``float64[N, 3]``.
        rotation: ``float64[N, 3, 3]`` camera-to-world (columns right, up, back).
        fov_y: ``float64[N]`` radians.
        near, far, ortho_height: ``float64[N]`` model units.
        width, height: ``int32[N]`` pixels.
        orthographic: ``bool[N]``.
        path_id, frame: ``int64[N]`` or ``None`` when the set has no paths.
    """

    eye: np.ndarray
    rotation: np.ndarray
    fov_y: np.ndarray
    near: np.ndarray
    far: np.ndarray
    ortho_height: np.ndarray
    width: np.ndarray
    height: np.ndarray
    orthographic: np.ndarray
    path_id: Optional[np.ndarray] = None
    frame: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return int(self.eye.shape[0])

    def rows(self, lo: int, hi: int) -> "CameraTable":
        """Rows ``[lo, hi)``."""
        return CameraTable(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[lo:hi]
                              for f in dataclasses.fields(self)})

    def batches(self, dtype=np.float32) -> Iterator[tuple[np.ndarray, Camera]]:
        """``(row indices, Camera batch)`` per projection (perspective,
        orthographic), rows in increasing order within each; image sizes are
        traced, so they need no batch of their own. Fields are host NumPy
        arrays of ``dtype`` (float64 keeps the table's values exactly)."""
        for ortho in (False, True):
            idx = np.flatnonzero(self.orthographic == ortho)
            if len(idx):
                # Host (NumPy) float32 fields: refine_batch cuts its chunks on the host.
                yield idx, Camera(
                    eye=self.eye[idx].astype(dtype), rotation=self.rotation[idx].astype(dtype),
                    fov_y=self.fov_y[idx].astype(dtype), near=self.near[idx].astype(dtype),
                    far=self.far[idx].astype(dtype), ortho_height=self.ortho_height[idx].astype(dtype),
                    width=self.width[idx], height=self.height[idx], orthographic=ortho)

    def camera(self, dtype=np.float32) -> Camera:
        """All rows as one Camera batch (they must share the projection);
        fields as in :meth:`batches`."""
        groups = list(self.batches(dtype))
        if len(groups) != 1:
            raise CameraError("perspective and orthographic cameras in one set; use batches()")
        return groups[0][1]

    def columns(self) -> dict:
        """The file schema's columns (rotation form), NumPy arrays."""
        cols = {name: self.eye[:, i] for i, name in enumerate(EYE)}
        cols.update({name: self.rotation[:, i // 3, i % 3] for i, name in enumerate(ROTATION)})
        cols.update(fov_y_deg=np.degrees(self.fov_y), ortho_height=self.ortho_height, near=self.near, far=self.far,
                    width=self.width, height=self.height, orthographic=self.orthographic)
        if self.path_id is not None:
            cols.update(path_id=self.path_id, frame=self.frame)
        return cols


def table_from_cameras(camera: Camera, path_id=None, frame=None) -> CameraTable:
    """A :class:`CameraTable` holding a Camera batch (or one camera).

    Args:
        camera: a :class:`Camera` batch (eye ``[N, 3]``) or one camera (one row).
        path_id: which path each camera belongs to: one integer for all rows
            or ``[N]`` integers; None (default) when the set has no paths.
        frame: each camera's position along its path: one integer or ``[N]``
            integers (frame numbers from 0); None with ``path_id`` None (a
            camera file holds both columns or neither).

    Returns:
        :class:`CameraTable` of N rows (float64 eye, rotation, radians,
        world units; ``int64[N]`` path ids and frames or None).
    """
    n = int(camera.eye.shape[0]) if np.ndim(camera.eye) == 2 else 1
    flat = lambda a: np.asarray(a, np.float64).reshape(n)  # noqa: E731
    return CameraTable(
        eye=np.asarray(camera.eye, np.float64).reshape(n, 3),
        rotation=np.asarray(camera.rotation, np.float64).reshape(n, 3, 3),
        fov_y=flat(camera.fov_y), near=flat(camera.near), far=flat(camera.far),
        ortho_height=flat(camera.ortho_height),
        width=np.asarray(camera.width, np.int32).reshape(n), height=np.asarray(camera.height, np.int32).reshape(n),
        orthographic=np.full(n, bool(camera.orthographic)),
        path_id=None if path_id is None else np.broadcast_to(np.asarray(path_id, np.int64), (n,)).copy(),
        frame=None if frame is None else np.broadcast_to(np.asarray(frame, np.int64), (n,)).copy())


def _defaults(n, *, fov_y_deg=45.0, width=800, height=600, orthographic=False, ortho_height=1.0):
    return dict(fov_y=np.full(n, math.radians(fov_y_deg)), ortho_height=np.full(n, float(ortho_height)),
                width=np.full(n, int(width), np.int32), height=np.full(n, int(height), np.int32),
                orthographic=np.full(n, bool(orthographic)))


def _bounds(vertices):
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    return 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))


def orbit_rows(vertices, n_frames: int, lo: int, hi: int, *, elevation_deg=20.0, width=800, height=600,
               fov_y_deg=45.0) -> CameraTable:
    """Rows ``[lo, hi)`` of the standard orbit of ``n_frames`` cameras (see
    :func:`pmjax.standard_orbit`); one path, ``frame`` = row."""
    centre, r = _bounds(vertices)
    dist = r / math.sin(math.radians(22.5))
    el = math.radians(elevation_deg)
    k = np.arange(lo, hi)
    az = 2 * math.pi * k / n_frames
    offset = dist * np.stack([math.cos(el) * np.sin(az), np.full(len(k), math.sin(el)), math.cos(el) * np.cos(az)], 1)
    eye = centre + offset
    target = np.broadcast_to(centre, eye.shape)
    return CameraTable(eye=eye, rotation=look_at_rotations(eye, target, np.array([0.0, 1.0, 0.0])),
                       near=np.full(len(k), 0.01 * r), far=np.full(len(k), dist + 2 * r),
                       path_id=np.zeros(len(k), np.int64), frame=k.astype(np.int64),
                       **_defaults(len(k), fov_y_deg=fov_y_deg, width=width, height=height))


def random_rows(vertices, seed: int, lo: int, hi: int, *, min_scale=0.05, max_scale=4.0, width=800, height=600,
                fov_y_deg=45.0) -> CameraTable:
    """Rows ``[lo, hi)`` of the random views with ``seed``: directions uniform
    on the sphere, distances log-uniform in ``[min_scale, max_scale]`` times
    the half diagonal ``r``, each looking at a point drawn around the centre
    (``N(0, (r/2)²)`` per axis). Rows come in blocks of 4096 drawn from a
    generator seeded by ``(seed, block)``."""
    centre, r = _bounds(vertices)
    parts = []
    for block in range(lo // RANDOM_BLOCK, -(-hi // RANDOM_BLOCK)):
        rng = np.random.default_rng([seed, block])
        d = rng.normal(size=(RANDOM_BLOCK, 3))
        scale = np.exp(rng.uniform(math.log(min_scale), math.log(max_scale), RANDOM_BLOCK))
        aim = rng.normal(scale=0.5 * r, size=(RANDOM_BLOCK, 3))
        first = block * RANDOM_BLOCK
        keep = slice(max(lo - first, 0), min(hi - first, RANDOM_BLOCK))
        parts.append((d[keep], scale[keep], aim[keep]))
    d, scale, aim = (np.concatenate(p) for p in zip(*parts)) if parts else (np.zeros((0, 3)),) * 3
    dist = r * scale
    eye = centre + d / np.linalg.norm(d, axis=1, keepdims=True) * dist[:, None]
    target = centre + aim
    # A target on the eye (never seen in practice) looks at the centre instead.
    target[np.linalg.norm(target - eye, axis=1) < 1e-6 * r] = centre
    return CameraTable(eye=eye, rotation=look_at_rotations(eye, target, np.array([0.0, 1.0, 0.0])),
                       near=np.full(len(eye), 1e-3 * r), far=10 * r + dist,
                       **_defaults(len(eye), fov_y_deg=fov_y_deg, width=width, height=height))


def fly_rows(vertices, n_frames: int, lo: int, hi: int, *, width=800, height=600, fov_y_deg=45.0) -> CameraTable:
    """Rows ``[lo, hi)`` of a fly-through of ``n_frames`` cameras: from far in
    front of the model (4 r) to close by its side (0.3 r from the surface's
    bounding sphere), round the back and out again, always looking at the
    centre; one path, ``frame`` = row."""
    centre, r = _bounds(vertices)
    keys = np.array([[0.3, 0.5, 4.0], [1.3, 0.2, 0.2], [0.1, 0.4, -1.3], [-2.5, 0.8, -1.0]]) * r + centre
    s = np.arange(lo, hi) * ((len(keys) - 1) / max(1, n_frames - 1))
    i = np.minimum(s.astype(int), len(keys) - 2)
    w = (s - i)[:, None]
    eye = keys[i] * (1 - w) + keys[i + 1] * w
    dist = np.linalg.norm(eye - centre, axis=1)
    return CameraTable(eye=eye, rotation=look_at_rotations(eye, np.broadcast_to(centre, eye.shape),
                                                           np.array([0.0, 1.0, 0.0])),
                       near=1e-3 * dist, far=1e3 * dist, path_id=np.zeros(len(eye), np.int64),
                       frame=np.arange(lo, hi, dtype=np.int64),
                       **_defaults(len(eye), fov_y_deg=fov_y_deg, width=width, height=height))


# ---------------------------------------------------------------- files


# Camera files by extension (any case): camera lists, then camera tables.
CAMERA_LISTS, CAMERA_TABLES = (".json", ".csv"), (".npz", ".parquet")


def camera_file_kind(path) -> str:
    """The format of a camera file by its extension, in any case: ``"json"``
    or ``"csv"`` (camera lists, :func:`pmjax.save_cameras`), ``"npz"`` or
    ``"parquet"`` (camera tables, :func:`pmjax.write_camera_table`); a name
    with another extension (or none) reads as JSON, ``""``."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    return ext[1:] if ext in CAMERA_LISTS + CAMERA_TABLES else ""


def check_camera_output(path, formats=CAMERA_LISTS + CAMERA_TABLES) -> str:
    """The format a camera output is written in (:func:`camera_file_kind`),
    or an error before any work for an extension not among ``formats``.

    Raises:
        CameraError: naming the path and the extensions written.
    """
    kind = camera_file_kind(path)
    if "." + kind not in formats:
        ext = os.path.splitext(os.fspath(path))[1]
        raise CameraError(f"{path}: cameras are written as {', '.join(formats)} (by extension), not "
                          f"{ext or 'a name without an extension'}")
    return kind


def write_camera_table(table: CameraTable, path) -> None:
    """Write ``table`` to ``.npz`` or ``.parquet`` (atomically), in the
    rotation form of the schema."""
    path = os.fspath(path)
    kind = check_camera_output(path, CAMERA_TABLES)
    cols = table.columns()
    if kind == "npz":
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez(tmp, **cols)
    else:
        import pyarrow as pa
        import pyarrow.parquet as pq

        with atomic_path(path) as tmp:
            pq.write_table(pa.table(cols), tmp)


def _parquet_columns(path: str, limit) -> dict:
    """The columns of a Parquet table (its first ``limit`` rows, or all),
    refusing nulls."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if limit is None:
        table = pq.read_table(path)
    else:
        with pq.ParquetFile(path) as pf:
            # One batch: the row groups past the first ``limit`` rows stay unread.
            first = next(pf.iter_batches(batch_size=max(1, limit)), None)
            table = (pa.Table.from_batches([first]) if first is not None
                     else pf.schema_arrow.empty_table()).slice(0, limit)
    out = {}
    for name in table.column_names:
        col = table.column(name)
        if col.null_count:
            row = int(np.flatnonzero(np.asarray(col.is_null()))[0])
            raise CameraError(f"{path}: row {row}: column {name!r} is null")
        out[name] = col.to_numpy()
    return out


def _npz_columns(path: str, limit: int) -> dict:
    """The first ``limit`` values of each column of a ``.npz`` table, read
    from the head of each member (its ``.npy`` header, then the values): the
    rest of the file stays unread. The columns' shapes are checked from
    their headers."""
    out, shapes = {}, {}
    with zipfile.ZipFile(path) as zf:
        for member in zf.namelist():
            name = member.removesuffix(".npy")
            with zf.open(member) as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
                elif version == (2, 0):
                    shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
                else:
                    raise CameraError(f"{path}: column {name!r} is a .npy array of format version {version}; "
                                      "write the table with numpy.savez")
                if dtype.hasobject:
                    raise CameraError(f"{path}: column {name!r} has dtype object, expected numbers")
                shapes[name] = shape
                count = min(limit, shape[0]) if len(shape) == 1 else 0
                data = fh.read(count * dtype.itemsize)
                if len(data) != count * dtype.itemsize:
                    raise CameraError(f"{path}: column {name!r} is cut short")
                out[name] = np.frombuffer(data, dtype, count).copy()
    eye = shapes.get("eye_x")
    if eye is not None:
        if len(eye) == 0:
            raise CameraError(f"{path}: column 'eye_x' is not a column")
        for name, shape in shapes.items():
            if name in COLUMNS and shape != (eye[0],):
                raise CameraError(f"{path}: column {name!r} has shape {shape}, expected ({eye[0]},)")
    return out


def _read_columns(path: str, limit=None) -> dict:
    try:
        if camera_file_kind(path) == "npz":
            if limit is not None:
                return _npz_columns(path, limit)
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        if camera_file_kind(path) == "parquet":
            return _parquet_columns(path, limit)
    except CameraError:
        raise
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file
        raise CameraError(f"{path}: cannot read the camera table ({type(exc).__name__}: {exc})") from exc
    raise CameraError(f"{path}: camera tables are .npz or .parquet files")


def _numeric(path, cols, name, n, default=None, integer=False):
    if name not in cols:
        if default is None:
            raise CameraError(f"{path}: column {name!r} is missing")
        return np.full(n, default, np.int64 if integer else np.float64)
    a = np.asarray(cols[name])
    if a.shape != (n,):
        raise CameraError(f"{path}: column {name!r} has shape {a.shape}, expected ({n},)")
    if a.dtype == np.bool_:
        raise CameraError(f"{path}: column {name!r} holds booleans, expected "
                          f"{'integers' if integer else 'numbers'}")
    if a.dtype.kind not in "iuf":
        raise CameraError(f"{path}: column {name!r} has dtype {a.dtype}, expected numbers")
    if integer:
        # Whole numbers that int64 holds: a float's NaN, inf or fraction, or
        # a value past int64 (float or uint64), would change in the cast.
        if a.dtype.kind == "f":
            bad = np.flatnonzero(~((a == np.round(a)) & (np.abs(a) < 2.0 ** 63)))
        elif a.dtype.kind == "u":
            bad = np.flatnonzero(a > np.iinfo(np.int64).max)
        else:
            bad = np.array([], int)
        if len(bad):
            raise CameraError(f"{path}: row {bad[0]}: column {name!r} is {a[bad[0]]}, expected an integer within "
                              "int64")
        return a.astype(np.int64)
    a = a.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(a))
    if len(bad):
        raise CameraError(f"{path}: row {bad[0]}: column {name!r} is {a[bad[0]]}, expected a finite number")
    return a


def _flags(path, cols, name, n) -> np.ndarray:
    """A flag column: booleans, or integers 0 and 1 (not floats: a flag is
    not a measurement)."""
    if name not in cols:
        return np.zeros(n, bool)
    a = np.asarray(cols[name])
    if a.shape != (n,):
        raise CameraError(f"{path}: column {name!r} has shape {a.shape}, expected ({n},)")
    if a.dtype == np.bool_:
        return a.copy()
    if a.dtype.kind not in "iu":
        raise CameraError(f"{path}: column {name!r} has dtype {a.dtype}, expected booleans (or integers 0 and 1)")
    _first(path, (a != 0) & (a != 1), f"column {name!r} must be 0 or 1 (or a boolean)")
    return a.astype(bool)


def _first(path, bad, what):
    rows = np.flatnonzero(bad)
    if len(rows):
        raise CameraError(f"{path}: row {rows[0]}: {what}")


def read_camera_table(path, *, limit: Optional[int] = None) -> CameraTable:
    """Read and validate a camera table (``.npz`` or ``.parquet``).

    Every value is checked, per row: numbers (not booleans) where numbers
    belong, finite, image sizes integers in [1, 65536], a field of view in
    (0°, 180°), a positive orthographic height, ``0 < near < far``, a
    rotation that is orthonormal and right-handed, an eye off its target,
    ``orthographic`` a boolean (or an integer 0 or 1); unknown columns are
    refused. Errors name the file, the row and the column.

    Args:
        path: ``.npz`` or ``.parquet`` file.
        limit: read only the first ``limit`` rows (``>= 1``): of a Parquet
            file one batch of ``limit`` rows (from the row groups that hold
            them), of a ``.npz`` file the head of each column (the shapes
            checked from their headers); the other rows are neither read nor
            checked.

    Raises:
        CameraError: a bad file or value.
    """
    path = os.fspath(path)
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, (int, np.integer)) or limit < 1):
        raise ValueError(f"read_camera_table: limit must be an integer >= 1 or None, got {limit!r}")
    cols = _read_columns(path, limit)
    unknown = sorted(set(cols) - set(COLUMNS))
    if unknown:
        raise CameraError(f"{path}: unknown column {unknown[0]!r}; known columns: {', '.join(COLUMNS)}")
    if "eye_x" not in cols:
        raise CameraError(f"{path}: column 'eye_x' is missing")
    n = int(np.shape(cols["eye_x"])[0]) if np.ndim(cols["eye_x"]) else -1
    if n < 0:
        raise CameraError(f"{path}: column 'eye_x' is not a column")
    num = lambda name, default=None, integer=False: _numeric(path, cols, name, n, default, integer)  # noqa: E731
    eye = np.stack([num(c) for c in EYE], 1)
    has_target, has_rotation = any(c in cols for c in TARGET), any(c in cols for c in ROTATION)
    if has_target == has_rotation:
        raise CameraError(f"{path}: give either target_x/y/z (and optionally up_x/y/z) or r00..r22, "
                          f"not {'both' if has_target else 'neither'}")
    if has_target:
        target = np.stack([num(c) for c in TARGET], 1)
        up = np.stack([num(c, d) for c, d in zip(UP, (0.0, 1.0, 0.0))], 1)
        dist = np.linalg.norm(eye - target, axis=1)
        _first(path, ~(dist > 0), "eye and target coincide")
        _first(path, ~(np.linalg.norm(up, axis=1) > 0), "up is zero")
        rotation = look_at_rotations(eye, target, up)
    else:
        rotation = np.stack([num(c) for c in ROTATION], 1).reshape(n, 3, 3)
        gram = np.einsum("nji,njk->nik", rotation, rotation)
        _first(path, np.abs(gram - np.eye(3)).max(axis=(1, 2)) > 1e-4, "r00..r22 is not orthonormal")
        _first(path, np.linalg.det(rotation) < 0, "r00..r22 is a reflection (determinant -1)")
        if "near" not in cols or "far" not in cols:
            raise CameraError(f"{path}: columns r00..r22 need columns 'near' and 'far' (model units): without a "
                              "target there is no distance to scale their defaults by")
        dist = None
    fov = num("fov_y_deg", 45.0)
    ortho = _flags(path, cols, "orthographic", n)
    ortho_height = num("ortho_height", 1.0)
    width, height = num("width", 800, integer=True), num("height", 600, integer=True)
    near = num("near") if "near" in cols else 1e-3 * dist
    far = num("far") if "far" in cols else 1e3 * dist
    check_camera_values(eye, fov, near, far, ortho_height, width, height, ortho, name=lambda key: f"column {key!r}",
                        where=f"{path}: ", row="row")
    if ("path_id" in cols) != ("frame" in cols):
        raise CameraError(f"{path}: columns 'path_id' and 'frame' come together")
    path_id = num("path_id", integer=True) if "path_id" in cols else None
    frame = num("frame", integer=True) if "frame" in cols else None
    return CameraTable(eye=eye, rotation=rotation, fov_y=np.radians(fov), near=near, far=far,
                       ortho_height=ortho_height, width=width.astype(np.int32), height=height.astype(np.int32),
                       orthographic=ortho, path_id=path_id, frame=frame)
