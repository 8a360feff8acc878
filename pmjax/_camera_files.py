"""Camera files: JSON and CSV written and read, and the tables of evaluation jobs read as cameras.

Every camera read is checked as :func:`pmjax.look_at` checks its own; errors
are :class:`pmjax.CameraError` naming the file, the camera (or row and line)
and the field. Every row of a CSV is read and typed on its own.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._atomic import atomic_path
from ._camera_table import CAMERA_LISTS, camera_file_kind, check_camera_output
from ._camera import (ROTATION_TOLERANCE, Camera, CameraError, _flag, _numbers, _vector, camera_count, index_camera,
                      look_at, stack_cameras)


_FIELDS = ("eye", "rotation", "fov_y", "near", "far", "ortho_height")


def save_cameras(camera: Camera, path) -> None:
    """Write cameras to JSON (``.json``) or CSV (``.csv``), atomically.

    Raises:
        CameraError: another extension (camera tables:
            :func:`pmjax.write_camera_table`), before anything is written.
    """
    path = os.fspath(path)
    kind = check_camera_output(path, CAMERA_LISTS)
    K = camera_count(camera)
    cams = [camera] if K == 0 else [index_camera(camera, i) for i in range(K)]
    rows = [
        dict(eye=np.asarray(c.eye).tolist(), rotation=np.asarray(c.rotation).tolist(),
             fov_y_deg=math.degrees(float(c.fov_y)), near=float(c.near), far=float(c.far),
             ortho_height=float(c.ortho_height), width=int(c.width), height=int(c.height))
        for c in cams
    ]
    # JSON: the image size once at the top, and per camera only in a batch that mixes sizes.
    meta = dict(width=rows[0]["width"], height=rows[0]["height"], orthographic=camera.orthographic)
    if all((r["width"], r["height"]) == (meta["width"], meta["height"]) for r in rows):
        for r in rows:
            del r["width"], r["height"]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        if kind == "csv":
            w = csv.writer(fh)
            w.writerow(["ex", "ey", "ez"] + [f"r{i}{j}" for i in range(3) for j in range(3)]
                       + ["fov_y_deg", "near", "far", "ortho_height", "width", "height", "orthographic"])
            for row in rows:
                w.writerow(row["eye"] + sum(row["rotation"], []) + [row["fov_y_deg"], row["near"], row["far"],
                           row["ortho_height"], row.get("width", meta["width"]), row.get("height", meta["height"]),
                           int(meta["orthographic"])])
        else:
            json.dump(dict(meta, cameras=rows), fh, indent=1)


# Keys of a JSON camera file: the file's, and each camera's.
FILE_KEYS = ("width", "height", "orthographic", "cameras")
CAMERA_KEYS = ("eye", "target", "up", "rotation", "fov_y_deg", "near", "far", "ortho_height", "width", "height")

# A file's defaults (a CSV row gives every value).
_FILE_DEFAULTS = dict(width=800, height=600, orthographic=False)

# Columns of a CSV camera file, in the order save_cameras writes them.
CSV_COLUMNS = (("ex", "ey", "ez") + tuple(f"r{i}{j}" for i in range(3) for j in range(3))
               + ("fov_y_deg", "near", "far", "ortho_height", "width", "height", "orthographic"))

# A JSON camera file is parsed whole; load_first_camera refuses larger ones.
MAX_JSON_BYTES = 64 << 20
# A CSV line longer than this is not a camera row (one is about 400 bytes).
MAX_CSV_LINE = 1 << 20

_NUMBER = re.compile(r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)", re.IGNORECASE)


def _known_keys(doc, known):
    unknown = sorted(set(doc) - set(known))
    if unknown:
        raise CameraError(f"unknown key {unknown[0]!r}; known keys: {', '.join(known)}")


def _csv_lines(fh, path):
    """The lines of a CSV file opened in binary, decoded one by one (UTF-8,
    a byte-order mark allowed), refusing a line longer than
    ``MAX_CSV_LINE`` bytes before it is read whole."""
    line_no = 0
    while True:
        line = fh.readline(MAX_CSV_LINE + 1)
        if not line:
            return
        line_no += 1
        if len(line) > MAX_CSV_LINE:
            raise CameraError(f"{path}: line {line_no} is longer than {MAX_CSV_LINE} bytes: not a camera CSV row")
        try:
            yield line.decode("utf-8-sig" if line_no == 1 else "utf-8")
        except UnicodeDecodeError:
            raise CameraError(f"{path}: line {line_no} is not UTF-8 text: not a camera CSV file") from None


def _csv_number(text: str, key: str) -> float:
    if not _NUMBER.fullmatch(text.strip()):
        raise CameraError(f"{key} must be a number, got {text!r}")
    return float(text)


def _csv_cameras(path: str, limit=None) -> list:
    """``[(label, item)]`` of the first ``limit`` rows (every row with
    ``None``) of a CSV camera file: every field typed per row
    (``orthographic`` too); the rest of the file is not read."""
    items = []
    with open(path, "rb") as fh:
        reader = csv.reader(_csv_lines(fh, path))
        header = next(reader, None)
        if header is None:
            raise CameraError(f"{path}: empty file; a camera CSV starts with the header "
                              f"{','.join(CSV_COLUMNS)}")
        header = [name.strip() for name in header]
        for name in header:
            if name not in CSV_COLUMNS:
                raise CameraError(f"{path}: unknown column {name!r}; the columns are {', '.join(CSV_COLUMNS)}")
            if header.count(name) > 1:
                raise CameraError(f"{path}: column {name!r} appears twice")
        missing = [name for name in CSV_COLUMNS if name not in header]
        if missing:
            raise CameraError(f"{path}: column {missing[0]!r} is missing; the columns are {', '.join(CSV_COLUMNS)}")
        for fields in reader:
            if not fields:  # a blank line
                continue
            label = f"camera {len(items)} (line {reader.line_num})"
            try:
                if len(fields) != len(header):
                    raise CameraError(f"{len(fields)} fields, expected {len(header)} ({', '.join(header)})")
                row = dict(zip(header, fields))
                number = {key: _csv_number(row[key], key) for key in CSV_COLUMNS[:-1]}
                items.append((label, dict(
                    eye=[number[k] for k in ("ex", "ey", "ez")],
                    rotation=[[number[f"r{i}{j}"] for j in range(3)] for i in range(3)],
                    **{k: number[k] for k in ("fov_y_deg", "near", "far", "ortho_height", "width", "height")},
                    orthographic=_flag(row["orthographic"], "orthographic", words=True))))
            except CameraError as exc:
                raise CameraError(f"{path}: {label}: {exc}") from None
            if len(items) == limit:  # no further line is read
                break
    if not items:
        raise CameraError(f"{path}: no cameras (the header has no rows after it)")
    return items


def _json_cameras(path: str, max_bytes=None) -> tuple[list, dict]:
    """``([(label, item)], file defaults)`` of a JSON camera file, the file
    checked as a whole (object, keys, flag); a file over ``max_bytes`` is
    refused unread."""
    with open(path) as fh:
        size = os.fstat(fh.fileno()).st_size
        if max_bytes is not None and size > max_bytes:
            raise CameraError(f"{path}: a JSON camera file is read whole, and this one has {size} bytes "
                              f"(the limit is {max_bytes} bytes, {max_bytes / 2**20:g} MiB): write the cameras "
                              "as a .csv file or a .parquet table (read only as far as needed), or split the file")
        doc = json.load(fh)
    if not isinstance(doc, dict):
        raise CameraError(f"{path}: expected a JSON object (one camera, or cameras: [...]), "
                          f"got {type(doc).__name__}")
    try:
        _known_keys(doc, FILE_KEYS if "cameras" in doc else FILE_KEYS + CAMERA_KEYS)
        meta = dict(_FILE_DEFAULTS, **{k: doc[k] for k in ("width", "height") if k in doc},
                    orthographic=_flag(doc.get("orthographic", False), "orthographic"))
    except CameraError as exc:
        raise CameraError(f"{path}: {exc}") from None
    if "cameras" not in doc:  # one camera, checked with the file's keys
        return [("camera 0", {k: v for k, v in doc.items() if k != "orthographic"})], meta
    items = doc["cameras"]
    if not isinstance(items, list):
        raise CameraError(f"{path}: 'cameras' must be a list, got {type(items).__name__}")
    if not items:
        raise CameraError(f"{path}: no cameras ('cameras' is empty)")
    labelled = []
    for i, it in enumerate(items):
        if not isinstance(it, dict):
            raise CameraError(f"{path}: camera {i}: expected a JSON object, got {type(it).__name__}")
        try:
            _known_keys(it, CAMERA_KEYS)
        except CameraError as exc:
            raise CameraError(f"{path}: camera {i}: {exc}") from None
        labelled.append((f"camera {i}", it))
    return labelled, meta


def _camera_of(path: str, label: str, it: dict, meta: dict) -> Camera:
    """One camera of a file (``it``: a JSON camera or a typed CSV row; a
    missing value from ``meta``, the file's, or the defaults), checked by
    :func:`look_at`."""
    try:
        if "eye" not in it:
            raise CameraError("'eye' is missing")
        if ("target" in it) == ("rotation" in it):
            raise CameraError("give either 'target' (and optionally 'up') or 'rotation', "
                              + ("not both" if "target" in it else "neither"))
        eye = _vector(it["eye"], "eye")
        common = dict(fov_y_deg=it.get("fov_y_deg", 45.0), width=it.get("width", meta["width"]),
                      height=it.get("height", meta["height"]), near=it.get("near"), far=it.get("far"),
                      ortho_height=it.get("ortho_height", 1.0),
                      orthographic=it.get("orthographic", meta["orthographic"]))
        if "rotation" in it:
            rot = _numbers(it["rotation"], "rotation", (3, 3), "a 3×3 rotation matrix (3 rows of 3 numbers)")
            if not np.allclose(rot.T @ rot, np.eye(3), atol=ROTATION_TOLERANCE):
                raise CameraError("rotation is not a 3×3 rotation matrix (orthonormal columns)")
            if np.linalg.det(rot) < 0:
                raise CameraError("rotation is a reflection (determinant -1)")
            if common["near"] is None or common["far"] is None:
                raise CameraError("a camera given by 'rotation' needs 'near' and 'far' (model units): without a "
                                  "target there is no distance to scale their defaults by")
            # look_at checks every value; the rotation is then the one stored,
            # as a camera table's is (rebuilt from its axes it could differ in
            # the last bits).
            camera = look_at(eye, eye - rot[:, 2], rot[:, 1], **common)
            return eqx.tree_at(lambda c: c.rotation, camera, jnp.asarray(rot, camera.rotation.dtype))
        return look_at(eye, it["target"], it.get("up", (0, 1, 0)), **common)
    except (KeyError, ValueError, TypeError) as exc:
        raise CameraError(f"{path}: {label}: {str(exc).removeprefix('look_at: ')}") from exc


def _read_error(path: str, exc: Exception) -> CameraError:
    return CameraError(f"{path}: cannot read cameras ({type(exc).__name__}: {exc})")


def _table_camera(path: str, limit=None) -> Camera:
    """The rows of a camera table (``.npz``, ``.parquet``) as one batch of
    float32 JAX fields, as the JSON and CSV files give."""
    from ._camera_table import read_camera_table

    table = read_camera_table(path, limit=limit)
    if len(table) == 0:
        raise CameraError(f"{path}: no cameras (the table has no rows)")
    mixed = np.flatnonzero(table.orthographic != table.orthographic[0])
    if len(mixed):
        flag = lambda i: str(bool(table.orthographic[i])).lower()  # noqa: E731
        raise CameraError(f"{path}: row {mixed[0]}: orthographic is {flag(mixed[0])} but row 0's is {flag(0)}; "
                          "the cameras of one batch share the projection: put perspective and orthographic "
                          "cameras in separate files (pmjax eval reads mixed tables)")
    return jax.tree_util.tree_map(jnp.asarray, table.camera())


def load_cameras(path) -> Camera:
    """Read every camera of a file, as one batch (always a batch).

    Files: JSON as written by :func:`save_cameras` (or by hand: ``cameras:
    [{eye, target | rotation, fov_y_deg, ...}]``, a camera's own
    ``width``/``height`` overriding the file's), CSV (the columns of
    ``CSV_COLUMNS``, every row typed on its own), or a ``.npz``/``.parquet``
    table (:func:`pmjax.read_camera_table`). The cameras of one file share
    the projection (``orthographic``).

    Raises:
        CameraError: naming the file, the camera (CSV: and its line; tables:
            the row) and the value.
    """
    path = os.fspath(path)
    if camera_file_kind(path) in ("npz", "parquet"):
        return _table_camera(path)
    try:
        if camera_file_kind(path) == "csv":
            items, meta = _csv_cameras(path), _FILE_DEFAULTS
        else:
            items, meta = _json_cameras(path)
    except CameraError:
        raise
    except (OSError, ValueError, RecursionError, csv.Error) as exc:
        raise _read_error(path, exc) from exc
    cams = [_camera_of(path, label, it, meta) for label, it in items]
    first = cams[0].orthographic
    for (label, _), cam in zip(items, cams):
        if cam.orthographic != first:
            raise CameraError(f"{path}: {label}: orthographic is {str(cam.orthographic).lower()} but camera 0's "
                              f"is {str(first).lower()}; the cameras of one file share the projection: put "
                              "perspective and orthographic cameras in separate files")
    return stack_cameras(cams)


def load_first_camera(path) -> Camera:
    """The first camera of a camera file (any of :func:`load_cameras`'s
    kinds), reading no more of the file than it needs: a CSV file up to its
    first row, a Parquet table its first rows (one batch of its first row
    group), a ``.npz`` table the headers of its columns and their first
    values. A JSON file is parsed whole, so one over ``MAX_JSON_BYTES``
    (64 MiB) is refused. Only the first camera is read and checked; the
    file's header, keys or columns are checked as :func:`load_cameras`
    checks them.

    Returns:
        One :class:`Camera` (no batch axis), equal to camera 0 of
        :func:`load_cameras`.

    Raises:
        CameraError: as :func:`load_cameras`; a JSON file over 64 MiB.
    """
    path = os.fspath(path)
    if camera_file_kind(path) in ("npz", "parquet"):
        return index_camera(_table_camera(path, limit=1), 0)
    try:
        if camera_file_kind(path) == "csv":
            items, meta = _csv_cameras(path, limit=1), _FILE_DEFAULTS
        else:
            items, meta = _json_cameras(path, max_bytes=MAX_JSON_BYTES)
    except CameraError:
        raise
    except (OSError, ValueError, RecursionError, csv.Error) as exc:
        raise _read_error(path, exc) from exc
    return _camera_of(path, *items[0], meta)
