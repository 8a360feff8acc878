"""Evaluation jobs: models × camera sets × tolerances (or face budgets) → one
Parquet dataset, streamed, resumable, and optionally spread over Dask workers.

A job is cut into parts: one chunk of cameras of one camera set, for one model
and one tolerance (or budget). A part is refined with :func:`pmjax.refine_batch`
(budgets: :func:`pmjax.faces_for_budget_batch`) and written as one
Parquet file, atomically (a temporary file, then a rename), so a part file
that exists was written whole; its metadata records the job, the model's
SHA-256, the part's name, its row count, and a SHA-256 over that record and
the rows (:func:`_table_sha256`). The dataset folder holds the part files,
named so that their lexical order is the row order, and ``_job.parquet``, the
job's description (no rows; :func:`read_job`), so that pyarrow, pandas,
polars and DuckDB read the folder by name. Re-running a job reads every part
file there back in full and skips those that verify; one that does not (a
truncated file, a damaged page, the wrong rows) is moved into the folder
``FOLDER.damaged`` beside it with a line on stderr and computed again. A job
grows: a later command may add models, camera sets and values, whose parts
take new names; one that would change a part already there is refused
(:func:`_merge_job`). Models and camera files are known by their content, so
a moved data folder resumes. :func:`compact` rewrites the part files into few
large files that record the parts they hold, so the folder still resumes.

Parts are planned lazily, one at a time as the work reaches them, so a job's
size (10^12 random views) costs neither memory nor time before the first part
runs: memory follows the parts in flight and the part files in the folder.

Rows depend only on the job description, never on where or when a part ran:
a camera's row comes from that camera alone (generated sets give a row's
camera from its index), so an interrupted and resumed job, or one run on a
Dask cluster, gives the same rows as one uninterrupted process; only
``refine_ms`` and ``compile_ms``, measured times, differ.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import hashlib
import json
import os
import re
import sys
import threading
import time
from typing import Optional, Sequence

import numpy as np

from ._atomic import TEMP_MARK, atomic_path, remove_stale_temporaries
from ._bitsets import WORD
from ._camera import camera_count, index_camera
from ._camera_table import (CameraTable, _bounds, camera_file_kind, fly_rows, orbit_rows, random_rows,
                            read_camera_table)
from ._pmfile import file_sha256
from ._predicate import ALL_TESTS, Tests

FORMAT = "pmjax-eval/3"
# Folders of format pmjax-eval/2 are resumed too: their description names
# models by path alone, and their parts carry a checksum of that whole
# description (kept in the description as ``legacy_jobs``).
FORMAT_2 = "pmjax-eval/2"
# The settings that define every part of a job: a folder's parts keep them,
# so a command that gives others is refused.
SETTINGS = ("tests", "method", "chunk", "batch_chunk", "camera_columns", "columns")
# The job's description: a Parquet file with the job's columns and no rows,
# the description (JSON) in its metadata under JOB_KEY. Being Parquet of the
# same columns, it leaves a read of the whole folder unchanged: pyarrow and
# pandas skip files starting with '_', polars and DuckDB read it as no rows
# (polars reads every file under the folder and refuses any that is not
# Parquet, so the folder holds nothing else).
JOB_FILE = "_job.parquet"
JOB_KEY = b"pmjax_job"
# Where folders in format pmjax-eval/1 kept their description (JSON).
OLD_JOB_FILE = "_job.json"
# Part files failing verification are moved into a folder beside the dataset
# folder, named after it with this suffix: inside, polars and DuckDB's
# 'folder/**/*.parquet' would read them as rows.
DAMAGED_SUFFIX = ".damaged"
# Chunk numbers in part names have at least this many digits (more when a
# camera set has more chunks, so that lexical order stays row order).
CHUNK_DIGITS = 7
DEFAULT_CHUNK = 2048
# Rows per compacted file and per row group in it, by default: a compacted
# file is read whole when verified (about 110 bytes a row), one at a time.
COMPACT_ROWS = 1 << 22
COMPACT_GROUP_ROWS = 1 << 20
# Default folder of JAX's persistent compilation cache for evaluations.
DEFAULT_COMPILE_CACHE = os.path.join(os.path.expanduser("~"), ".cache", "pmjax", "xla")
# Models a process keeps loaded (with their compiled kernels) at once.
MODELS_KEPT = 2
# Image metrics per camera (``fidelity``): the columns of ``pmjax path
# --fidelity`` that a single view defines (popping compares two frames of a
# path and is left to it), drawn with 2×2 samples per pixel, unrounded.
FIDELITY_COLUMNS = ("differing_share", "psnr", "silhouette_share", "flip_mean", "flip_model_mean", "render_ms",
                    "fidelity_ms")
FIDELITY_SUPERSAMPLE = 2


class EvalError(ValueError):
    """A job that cannot run or cannot resume; the message says which model,
    camera set, file or setting, and why."""


class EvalInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped :func:`evaluate`; the parts written are kept, and the
    same call resumes. The message says how many.

    Attributes:
        folder: the dataset folder.
        parts_saved: part files of the job in the folder (verified, or written
            by this run); ``None`` when the run stopped while verifying them.
        parts_total, rows_saved, rows_total: the job's parts, and rows saved / in all.
    """

    def __init__(self, folder, parts_saved, parts_total, rows_saved, rows_total):
        self.folder, self.parts_saved, self.parts_total = folder, parts_saved, parts_total
        self.rows_saved, self.rows_total = rows_saved, rows_total
        if parts_saved is None:
            text = f"interrupted while verifying the parts in {folder}"
        else:
            text = (f"interrupted; {parts_saved} of {parts_total} parts saved in {folder} "
                    f"({rows_saved} of {rows_total} rows)")
        super().__init__(text + "; run the same command to resume")


# ---------------------------------------------------------------- the job


@dataclasses.dataclass(frozen=True)
class CameraSet:
    """A camera set of a job: a file, or a generator applied to each model.

    Attributes:
        kind: ``"file"``, ``"orbit"``, ``"fly"`` or ``"random"``.
        count: cameras (generators; a file's count is its row count).
        path: the file (``kind == "file"``).
        seed: random views' seed.
        width, height, fov_y_deg: image of generated cameras.
    """

    kind: str
    count: int = 0
    path: Optional[str] = None
    seed: int = 0
    width: int = 800
    height: int = 600
    fov_y_deg: float = 45.0

    @property
    def name(self) -> str:
        """The set's name in the ``camera_set`` column."""
        if self.kind == "file":
            return os.path.basename(self.path)
        name = f"random-{self.count}-seed{self.seed}" if self.kind == "random" else f"{self.kind}-{self.count}"
        # The image, when it is not the default 800x600 at 45 degrees.
        if (self.width, self.height) != (800, 600):
            name += f"-{self.width}x{self.height}"
        if self.fov_y_deg != 45.0:
            name += f"-fov{self.fov_y_deg:g}"
        return name

    def describe(self) -> dict:
        d = dataclasses.asdict(self)
        if self.kind == "file":
            d.update(path=os.path.abspath(self.path), sha256=file_sha256(self.path))
        return d

    def rows(self, vertices, lo: int, hi: int, table: Optional[CameraTable]) -> CameraTable:
        """Cameras ``[lo, hi)`` of this set for a model with ``vertices``."""
        image = dict(width=self.width, height=self.height, fov_y_deg=self.fov_y_deg)
        if self.kind == "file":
            return table.rows(lo, hi)
        if self.kind == "orbit":
            return orbit_rows(vertices, self.count, lo, hi, **image)
        if self.kind == "fly":
            return fly_rows(vertices, self.count, lo, hi, **image)
        return random_rows(vertices, self.seed, lo, hi, min_scale=0.05, max_scale=4.0, **image)


def camera_set(spec: str, *, width: int = 800, height: int = 600, fov_y_deg: float = 45.0) -> CameraSet:
    """A camera set from a short spec: ``orbit:N``, ``fly:N``,
    ``random:N[:SEED]`` or the path of a ``.npz`` / ``.parquet`` camera table."""
    head, _, rest = spec.partition(":")
    if head in ("orbit", "fly", "random") and rest:
        fields = rest.split(":")
        try:
            count = int(fields[0])
            seed = int(fields[1]) if len(fields) > 1 else 0
        except ValueError:
            raise EvalError(f"camera set {spec!r}: expected {head}:N" + ("[:SEED]" if head == "random" else "")) from None
        if count < 1 or (head != "random" and len(fields) > 1) or len(fields) > 2:
            raise EvalError(f"camera set {spec!r}: expected {head}:N with N >= 1"
                            + ("[:SEED]" if head == "random" else ""))
        if seed < 0:
            raise EvalError(f"camera set {spec!r}: the seed must be a whole number >= 0, not {seed}")
        return CameraSet(head, count, seed=seed, width=width, height=height, fov_y_deg=fov_y_deg)
    if camera_file_kind(spec) not in ("npz", "parquet"):
        raise EvalError(f"camera set {spec!r}: expected orbit:N, fly:N, random:N[:SEED] or a .npz/.parquet file")
    if not os.path.exists(spec):
        raise EvalError(f"camera set {spec!r}: no such file")
    return CameraSet("file", path=spec)


def _model_name(path) -> str:
    name = os.path.basename(path)
    return name[:-4] if name.endswith(".pmz") else name


def _tests_dict(tests: Tests) -> dict:
    return dict(frustum=bool(tests.frustum), orientation=bool(tests.orientation), screen=bool(tests.screen))


@dataclasses.dataclass(frozen=True)
class _Part:
    """One unit of work: a chunk of one camera set, one model, one value."""

    model: int
    cameras: int
    value: int
    chunk: int
    lo: int
    hi: int
    digits: int = CHUNK_DIGITS  # of the chunk number in the file name

    @property
    def file(self) -> str:
        return (f"part-m{self.model:04d}-c{self.cameras:04d}-v{self.value:04d}-"
                f"{self.chunk:0{self.digits}d}.parquet")


# ---------------------------------------------------------------- one part


_LOADED: "collections.OrderedDict[str, object]" = collections.OrderedDict()
_LOADED_LOCK = threading.Lock()
# Serialises warm-up calls: threads of one process compile a kernel once.
_WARM_LOCK = threading.Lock()


def _model(path: str, digest: str, shipped: Optional[str] = None):
    """The loaded model of content ``digest`` and the set of its engine calls
    this process has compiled (see :func:`_warm`), kept per process by
    digest (so its kernels stay compiled, whatever path names it) for the
    last few models; older ones are dropped with JAX's compiled executables,
    which otherwise pile up in a process that visits many models.

    The model is read from ``path`` when that holds the content ``digest``;
    else, on a Dask worker that cannot read it (no shared file system, or
    another file there), from the bytes the client shipped as the Dask
    dataset ``shipped`` (:meth:`_Runner.ship`), fetched once per process."""
    import jax

    from ._load import load

    with _LOADED_LOCK:
        if digest in _LOADED:
            _LOADED.move_to_end(digest)
            return _LOADED[digest]
        if shipped is not None and not (os.path.isfile(path) and os.access(path, os.R_OK)
                                        and file_sha256(path) == digest):
            path = _fetch_shipped(shipped, digest)
        elif file_sha256(path) != digest:
            raise EvalError(f"{path}: the model file changed while the job ran")
        _LOADED[digest] = load(path), set()
        if len(_LOADED) > MODELS_KEPT:
            _LOADED.popitem(last=False)
            jax.clear_caches()
            # Every model's kernels are gone: each compiles again on its next call.
            for _, warm in _LOADED.values():
                warm.clear()
        return _LOADED[digest]


def _fetch_shipped(key: str, digest: str) -> str:
    """The model bytes the client shipped as the Dask dataset ``key``, fetched
    from the cluster into a file of this machine's temporary folder named by
    ``digest`` (kept for later jobs: a file there of that content is used
    without a fetch); its path."""
    import tempfile

    folder = os.path.join(tempfile.gettempdir(), f"pmjax-models-{os.getuid()}")
    path = os.path.join(folder, f"{digest}.pmz")
    if os.path.isfile(path) and file_sha256(path) == digest:
        return path
    from distributed import get_client

    data = get_client().get_dataset(key).result()
    if hashlib.sha256(data).hexdigest() != digest:
        raise EvalError(f"the model bytes shipped under {key} do not have the content SHA-256 {digest[:12]}")
    os.makedirs(folder, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return path


def _warm(warm: set, key: tuple, call) -> float:
    """Run ``call`` once, untimed by the caller, when ``key`` (an engine call
    and what its compiled kernel depends on: padded batch size, projection,
    tests, method) is not in ``warm``; its wall time in milliseconds, 0 when
    the call was already compiled. Compilation (or its load from the
    persistent cache) so stays out of ``refine_ms``."""
    if key in warm:
        return 0.0
    with _WARM_LOCK:
        if key in warm:  # another thread warmed it meanwhile
            return 0.0
        t = time.perf_counter()
        call()
        warm.add(key)
        return 1e3 * (time.perf_counter() - t)


def _compile_cache(folder: Optional[str]) -> None:
    """Point JAX's persistent compilation cache at ``folder`` (once per process)."""
    if not folder:
        return
    import jax

    if jax.config.jax_compilation_cache_dir != folder:
        os.makedirs(folder, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


# Paths shorter than this go with the other cameras through refine_batch: the
# coherent engine shares work between consecutive frames, 16 or 32 at a time.
MIN_PATH_FRAMES = 32


def path_runs(table: CameraTable, idx: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """The cameras ``idx`` of ``table`` (one projection, increasing rows) as
    paths for :func:`pmjax.path_counts`: per path id and image size, positions
    into ``idx`` in frame order; and the positions of the cameras that are not
    on a path of at least :data:`MIN_PATH_FRAMES` frames."""
    if table.path_id is None:
        return [], np.arange(len(idx))
    path, frame = table.path_id[idx], table.frame[idx]
    width, height = table.width[idx], table.height[idx]
    order = np.lexsort((frame, height, width, path))
    key = np.stack([path, width, height], 1)[order]
    cuts = np.flatnonzero(np.any(key[1:] != key[:-1], axis=1)) + 1
    runs, rest = [], []
    for run in np.split(order, cuts):
        (runs if len(run) >= MIN_PATH_FRAMES else rest).append(run)
    rest = np.sort(np.concatenate(rest)) if rest else np.zeros(0, np.int64)
    return runs, rest


# Rows of budget parts answered together with an earlier part of the same
# cameras (run_part's budgets_together), until their own part runs: keyed
# by (part key, model digest, lo, hi), the oldest dropped past TOGETHER_KEPT
# (its part then computes them again).
_TOGETHER: "collections.OrderedDict[tuple, list]" = collections.OrderedDict()
TOGETHER_KEPT = 64


def _keep_together(key, columns):
    _TOGETHER[key] = columns
    while len(_TOGETHER) > TOGETHER_KEPT:
        _TOGETHER.popitem(last=False)


def run_part(task: dict):
    """Refine one part and return its rows as a ``pyarrow.Table``.

    ``task`` holds the model path and digest, the camera rows, the value (tau
    or budget), the part's file name and the job's settings; it is plain
    data, so a Dask worker can run it. Public for Dask; users call :func:`evaluate`.
    """
    import pyarrow as pa

    from ._path import path_counts
    from ._refine import faces_for_budget_batch, refine_batch

    _compile_cache(task["compile_cache"])
    pm, warm = _model(task["model_path"], task["model_sha256"], task.get("model_shipped"))
    table: CameraTable = task["rows"]
    tests = Tests(**task["tests"])
    n = len(table)
    faces, vertices, executed = (np.zeros(n, np.int64) for _ in range(3))
    tau, ms = np.zeros(n, np.float32), np.zeros(n)
    budget, method = task["budget"], task["method"]
    # Wall time of the part's warm-up calls (compilation, or its load from the
    # persistent cache), kept out of the per-camera times; on the part's first row.
    compile_ms = 0.0
    batches, cols = table.batches(), {}
    if budget is not None:
        # A part's columns answered with an earlier part's call, or the
        # budgets to answer with this one (see the budgets below).
        together = task.get("budgets_together") or dict(budgets=[budget], keys=[task["job_sha256"]])
        mine = _TOGETHER.pop((task["job_sha256"], task["model_sha256"], task["lo"], task["hi"]), None)
        if mine is not None:
            tau[:], faces[:], vertices[:], executed[:], ms[:] = mine
            batches = []
    for idx, cams in batches:
        setting = (cams.orthographic, tests, method)
        # Paths go through the coherent engine, frames in order; the other
        # cameras in one batched call, its wall time shared by its cameras.
        runs, rest = path_runs(table, idx) if method != "dense" else ([], np.arange(len(idx)))
        if budget is None:
            for run in runs:
                rows, path = idx[run], index_camera(cams, run)
                call = lambda c: path_counts(pm, c, task["tau"], tests=tests)
                # The coherent engine compiles one call per block size, which
                # the path's length decides: a path of this length is warmed
                # up once per process.
                compile_ms += _warm(warm, ("path", len(run)) + setting, lambda: call(path))
                t = time.perf_counter()
                out = call(path)
                ms[rows] = 1e3 * (time.perf_counter() - t) / len(rows)
                faces[rows], vertices[rows], executed[rows] = out["faces"], out["vertices"], out["executed_count"]
            if len(rest):
                rows, batch = idx[rest], index_camera(cams, rest)
                call = lambda c: refine_batch(pm, c, task["tau"], tests=tests, chunk=task["batch_chunk"],
                                              method=method)
                # refine_batch compiles one kernel per padded chunk size: the
                # first `size` cameras (the last repeated) compile the one used here.
                size = -(-min(task["batch_chunk"], len(rest)) // WORD) * WORD
                first = index_camera(batch, np.minimum(np.arange(size), len(rest) - 1))
                compile_ms += _warm(warm, ("batch", size) + setting, lambda: call(first))
                t = time.perf_counter()
                out = call(batch)
                ms[rows] = 1e3 * (time.perf_counter() - t) / len(rows)
                faces[rows], vertices[rows], executed[rows] = out["faces"], out["vertices"], out["executed_count"]
            tau[idx] = task["tau"]
            continue

        # A budget needs its own tolerance per camera: the exact one of
        # faces_for_budget, found for the batch's cameras together (the
        # core's threads across cameras), with the counts there. Paths pass
        # their frames in order (guesses seeded along the path, first counts
        # through the coherent engine); the other cameras in one batch.
        # With budgets_together, the part's cameras get every budget listed
        # at once (one guess traversal per camera for all), the call's wall
        # time shared by its cameras and budgets; the other budgets' columns
        # wait for their parts in _TOGETHER.
        values_now = np.asarray(together["budgets"], np.int64)
        for part, is_path in [(run, True) for run in runs] + ([(rest, False)] if len(rest) else []):
            rows, batch = idx[part], index_camera(cams, part)
            call = lambda c: faces_for_budget_batch(pm, c, np.broadcast_to(values_now, (camera_count(c),
                                                                                        len(values_now))),
                                                    tests=tests, chunk=task["batch_chunk"], method=method,
                                                    path=is_path)
            if is_path:  # the path's calls: its length decides their sizes
                compile_ms += _warm(warm, ("budget_path", len(part), len(values_now)) + setting,
                                    lambda: call(batch))
            else:
                size = -(-min(task["batch_chunk"], len(part)) // WORD) * WORD
                first = index_camera(batch, np.minimum(np.arange(size), len(part) - 1))
                compile_ms += _warm(warm, ("budget", size, len(values_now)) + setting, lambda: call(first))
            t = time.perf_counter()
            out = call(batch)
            took = 1e3 * (time.perf_counter() - t) / (len(rows) * len(values_now))
            for j, key in enumerate(together["keys"]):
                got = cols.setdefault(key, [np.zeros(n, np.float32)] + [np.zeros(n, np.int64) for _ in range(3)] +
                                      [np.zeros(n)])
                for col, name in zip(got, ("tau", "faces", "vertices", "executed_count")):
                    col[rows] = out[name][:, j]
                got[4][rows] = took
    for key, got in cols.items():
        if key == task["job_sha256"]:
            tau[:], faces[:], vertices[:], executed[:], ms[:] = got
        else:
            _keep_together((key, task["model_sha256"], task["lo"], task["hi"]), got)
    compile = np.zeros(n)
    compile[:1] = compile_ms
    camera = np.arange(task["lo"], task["hi"], dtype=np.int64)
    null_ints = pa.nulls(n, pa.int64())
    columns = {
        "model": pa.array([task["model_name"]] * n, pa.string()),
        "camera_set": pa.array([task["set_name"]] * n, pa.string()),
        "camera": pa.array(camera),
        "path_id": null_ints if table.path_id is None else pa.array(table.path_id, pa.int64()),
        "frame": null_ints if table.frame is None else pa.array(table.frame, pa.int64()),
        "budget": null_ints if budget is None else pa.array(np.full(n, budget, np.int64)),
        # A budget below the coarsest mesh cannot be met: tau is inf and the
        # faces (the base mesh's) exceed it.
        "budget_met": pa.nulls(n, pa.bool_()) if budget is None else pa.array(faces <= budget),
        "tau": pa.array(tau),
        "faces": pa.array(faces),
        "vertices": pa.array(vertices),
        "executed": pa.array(executed),
        "refine_ms": pa.array(ms),
        "compile_ms": pa.array(compile),
    }
    if task["bounds"] is not None:
        columns.update(_camera_context(table, task["bounds"][:3], task["bounds"][3]))
    if task.get("fidelity"):
        # Budgets: each camera's refinement at the tolerance found (its row's tau).
        taus = np.full(n, task["tau"]) if budget is None else tau
        columns.update({k: pa.array(v) for k, v in _fidelity(pm, task["model_sha256"], table, taus, tests,
                                                             method).items()})
    out = pa.table(columns, schema=_schema(task["bounds"] is not None, bool(task.get("fidelity"))))
    # Checked when the folder is reopened (_verify_part): the part read back
    # must have these rows, and this checksum over them and this record.
    info = dict(job=task["job_sha256"], model_sha256=task["model_sha256"], part=task["part"], rows=n)
    return out.replace_schema_metadata({"pmjax": json.dumps(dict(info, sha256=_table_sha256(out, info)))})


_ORIGINALS: "collections.OrderedDict[str, tuple]" = collections.OrderedDict()
# One OpenGL context per image size serves the process: one thread draws at a time.
_RENDER_LOCK = threading.Lock()


def _fidelity(pm, digest: str, table: CameraTable, taus: np.ndarray, tests: Tests, method: str) -> dict:
    """The image metrics (:data:`FIDELITY_COLUMNS`) of each camera of
    ``table``: its refinement at ``taus[row]`` against the original mesh,
    both drawn from that camera (:func:`pmjax.render.camera_fidelity`, the
    per-frame measure of :func:`pmjax.render.path_fidelity`, the refinement
    shaded with normals fitted on the mesh drawn); ``fidelity_ms``
    is the camera's measuring (renders and metrics, not the refine)."""
    from pmjax.render import Renderer, camera_fidelity, original_arrays, refined_arrays

    from ._refine import refine

    with _LOADED_LOCK:
        if digest not in _ORIGINALS:
            _ORIGINALS[digest] = original_arrays(pm)
            while len(_ORIGINALS) > MODELS_KEPT:
                _ORIGINALS.popitem(last=False)
        original = _ORIGINALS[digest]
    out = {name: np.zeros(len(table)) for name in FIDELITY_COLUMNS}
    for idx, cams in table.batches():
        for j, row in enumerate(idx):
            cam = index_camera(cams, j)
            mesh = refined_arrays(pm, refine(pm, cam, float(taus[row]), tests=tests, method=method),
                                  eye=np.asarray(cam.eye))
            with _RENDER_LOCK:
                t = time.perf_counter()
                renderer = Renderer(int(cam.width), int(cam.height), FIDELITY_SUPERSAMPLE, True)
                got, _ = camera_fidelity(renderer, original, (mesh[0], mesh[1], mesh[3]), cam)
                got["fidelity_ms"] = 1e3 * (time.perf_counter() - t)
            for name in FIDELITY_COLUMNS:
                out[name][row] = got[name]
    return out


def run_part_on_worker(task: dict):
    """:func:`run_part` on a Dask worker: an error raised there comes back as
    an :class:`EvalError` naming the worker (its address), the part and the
    model, so the client's message says where it happened."""
    try:
        return run_part(task)
    except Exception as exc:
        try:
            from distributed import get_worker

            where = f"Dask worker {get_worker().address}"
        except (ImportError, ValueError):
            where = "a Dask worker"
        raise EvalError(f"{where}: part {task.get('part')} of model {task.get('model_path')}: "
                        f"{type(exc).__name__}: {exc}") from None


def _camera_context(table: CameraTable, centre, radius) -> dict:
    """The camera columns of ``table``'s rows: eye, its distance to the
    model's bounding-box ``centre`` (model units) and that distance over the
    bounding sphere's ``radius`` (half the box diagonal), vertical field of
    view in degrees (null for orthographic cameras) and image size."""
    import pyarrow as pa

    eye = np.asarray(table.eye, np.float64)
    distance = np.linalg.norm(eye - np.asarray(centre, np.float64), axis=1)
    fov = np.degrees(np.asarray(table.fov_y, np.float64))
    return dict(eye_x=pa.array(eye[:, 0]), eye_y=pa.array(eye[:, 1]), eye_z=pa.array(eye[:, 2]),
                distance=pa.array(distance), distance_radii=pa.array(distance / radius),
                fov_y_deg=pa.array(fov, mask=np.asarray(table.orthographic, bool)),
                width=pa.array(np.asarray(table.width, np.int32)), height=pa.array(np.asarray(table.height, np.int32)))


def _table_sha256(table, info: dict) -> str:
    """SHA-256, hex, of a part's record ``info`` (job, model checksum, part
    file name, rows) and of its table's content: per column its name, type, validity and values
    (dictionary columns decoded), so it names the rows whatever the chunking or
    encoding of the file they were read from."""
    import pyarrow as pa

    h = hashlib.sha256(json.dumps(info, sort_keys=True).encode() + b"\0%d\0" % table.num_rows)
    for field, column in zip(table.schema, table.columns):
        if pa.types.is_dictionary(field.type):
            column = column.cast(field.type.value_type)
        h.update(f"{field.name}\0{column.type}\0".encode())
        h.update(np.packbits(column.is_valid().to_numpy(zero_copy_only=False)))
        if pa.types.is_integer(column.type) or pa.types.is_floating(column.type):
            values = column.fill_null(0).to_numpy()
            h.update(np.ascontiguousarray(values, values.dtype.newbyteorder("<")).view(np.uint8))
        else:
            h.update(json.dumps(column.to_pylist()).encode())
    return h.hexdigest()


# Columns of the camera context (``camera_columns``), after the others.
CAMERA_COLUMNS = ("eye_x", "eye_y", "eye_z", "distance", "distance_radii", "fov_y_deg", "width", "height")


def _schema(camera_columns: bool = False, fidelity: bool = False):
    """The columns of a job's rows (``camera_columns``: with the camera
    context; ``fidelity``: with the image metrics, after it)."""
    import pyarrow as pa

    extra = [(name, pa.float64()) for name in CAMERA_COLUMNS[:6]] + [("width", pa.int32()), ("height", pa.int32())]
    return pa.schema([
        # Plain strings (Parquet still stores them dictionary-encoded): one
        # Arrow type whatever the part, so readers group and join on them
        # without unifying per-file dictionaries.
        ("model", pa.string()),
        ("camera_set", pa.string()),
        ("camera", pa.int64()),
        ("path_id", pa.int64()),
        ("frame", pa.int64()),
        ("budget", pa.int64()),
        ("budget_met", pa.bool_()),
        ("tau", pa.float32()),
        ("faces", pa.int64()),
        ("vertices", pa.int64()),
        ("executed", pa.int64()),
        ("refine_ms", pa.float64()),
        ("compile_ms", pa.float64()),
    ] + (extra if camera_columns else [])
      + ([(name, pa.float64()) for name in FIDELITY_COLUMNS] if fidelity else []))


# ---------------------------------------------------------------- the driver


@dataclasses.dataclass(frozen=True)
class EvalSummary:
    """What :func:`evaluate` did.

    Attributes:
        folder: the dataset folder.
        rows: rows in the dataset (the whole job's once it is complete).
        parts_written, parts_skipped: parts computed now / found done and verified.
        cameras: camera refinements computed now (rows written now).
        seconds: wall time of this run.
    """

    folder: str
    rows: int
    parts_written: int
    parts_skipped: int
    cameras: int
    seconds: float

    @property
    def cameras_per_s(self) -> float:
        return self.cameras / self.seconds if self.seconds > 0 else 0.0


def evaluate(
    models: Sequence[str],
    camera_sets: Sequence,
    folder: str,
    *,
    taus: Sequence[float] = (),
    budgets: Sequence[int] = (),
    tests: Tests = ALL_TESTS,
    method: str = "auto",
    chunk: int = DEFAULT_CHUNK,
    batch_chunk: int = 256,
    compile_cache: Optional[str] = DEFAULT_COMPILE_CACHE,
    scheduler: Optional[str] = None,
    workers: int = 0,
    progress: bool = True,
    max_parts: Optional[int] = None,
    camera_columns: bool = False,
    fidelity: bool = False,
) -> EvalSummary:
    """Evaluate models × camera sets × tolerances (or face budgets) into a
    Parquet dataset folder, one row per (model, camera set, value, camera).

    Args:
        models: ``.pmz`` paths.
        camera_sets: :class:`CameraSet` objects or specs for :func:`camera_set`
            (``orbit:N``, ``fly:N``, ``random:N[:SEED]``, a ``.npz`` or
            ``.parquet`` camera table).
        folder: the dataset folder (created; a finished or interrupted run of
            the same job there is resumed, and a job there gains the models,
            camera sets and values it lacks, see docs/eval.md).
        taus: tolerances in pixels; or
        budgets: face budgets (exclusive with ``taus``): per camera, the
            smallest tolerance whose face count is the largest within the
            budget (:func:`pmjax.faces_for_budget`), the cameras of a part
            together (:func:`pmjax.faces_for_budget_batch`).
        tests, method: as :func:`pmjax.refine_batch`.
        chunk: cameras per part (the unit of resumption and of Dask tasks).
        batch_chunk: cameras per vmapped kernel call inside a part.
        compile_cache: folder of JAX's persistent compilation cache (``None``:
            off), so a second run of a job, or another worker, skips compiling.
        scheduler: address of a running Dask scheduler (``tcp://HOST:PORT``;
            :func:`pmjax.slurm_cluster` makes one on SLURM). Workers that
            cannot read a model file at its path receive its bytes.
        workers: run on a local Dask cluster of this many threads in this
            process (0: no cluster); they share each loaded model and its
            compiled kernels (docs/eval.md).
        progress: a progress bar (cameras/s and ETA).
        max_parts: compute at most this many parts in this run, then stop
            (``None``: every part); a later run of the same job resumes.
        camera_columns: also write each camera's context (eye, distance to
            the model, field of view, image size; docs/eval.md); part of the
            job, so a resumed run must give the same setting.
        fidelity: also write each camera's image metrics against the
            original mesh (:data:`FIDELITY_COLUMNS`: differing share, PSNR,
            silhouette share, FLIP over the image and over the model's
            pixels, render and measuring times), rendering the refinement
            and the original headless (EGL or OSMesa) once per camera, where
            the part runs; part of the job, like ``camera_columns``.

    Returns:
        :class:`EvalSummary`. Read the rows by the folder's name:
        ``pyarrow.parquet.read_table(folder)``, ``pandas.read_parquet(folder)``,
        ``polars.read_parquet(folder)`` or DuckDB's ``read_parquet('folder')``.

    Raises:
        EvalError: a bad setting, a camera set that cannot be read, a model
            that fails validation (parts finished before it are kept), a
            folder whose parts this job defines otherwise (other settings, a
            model of the same name with other content; the message names the
            old and new values), or a part computed from a model file whose
            content has changed since.
        EvalInterrupted: Ctrl-C (a ``KeyboardInterrupt``); its message
            says how many parts are saved, and the same call resumes.
    """
    from ._pmfile import PMFormatError, read_pm
    from ._refine import check_budget, check_tau

    if bool(len(taus)) == bool(len(budgets)):
        raise EvalError("give tolerances (taus) or face budgets, not " + ("both" if len(taus) else "neither"))
    # The rules of refine_batch and faces_for_budget: tau >= 0 (inf allowed), budgets whole >= 0.
    try:
        values = [check_tau(t) for t in taus] or [check_budget(b) for b in budgets]
    except ValueError as exc:
        raise EvalError(str(exc)) from None
    if not models:
        raise EvalError("no models")
    if chunk < 1 or batch_chunk < 1:
        raise EvalError("chunk and batch_chunk must be >= 1")
    if method not in ("auto", "front", "dense"):
        raise EvalError(f"method must be auto, front or dense, not {method!r}")
    if max_parts is not None and (isinstance(max_parts, bool) or not isinstance(max_parts, (int, np.integer))
                                  or max_parts < 1):
        raise EvalError(f"max_parts must be a whole number >= 1 or None, not {max_parts!r}")
    if not isinstance(camera_columns, (bool, np.bool_)):
        raise EvalError(f"camera_columns must be True or False, not {camera_columns!r}")
    camera_columns = bool(camera_columns)
    if not isinstance(fidelity, (bool, np.bool_)):
        raise EvalError(f"fidelity must be True or False, not {fidelity!r}")
    fidelity = bool(fidelity)
    if fidelity and not scheduler:
        # A missing renderer or FLIP is named before any work (on a cluster's workers, by the worker).
        try:
            from pmjax.render import pyrender_module
            from pmjax.render._fidelity import flip_module

            pyrender_module(offscreen=True)
            flip_module()
        except Exception as exc:
            raise EvalError(f"fidelity: {exc}") from None
    schema = _schema(camera_columns, fidelity)
    sets = [s if isinstance(s, CameraSet) else camera_set(s) for s in camera_sets]
    if not sets:
        raise EvalError("no camera sets")
    for m in models:
        if not os.path.exists(m):
            raise EvalError(f"model {m}: no such file")
    names = [_model_name(m) for m in models]
    if len(set(names)) < len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise EvalError(f"two models are named {twice!r} (the file name without .pmz names a model's rows)")
    if len({s.name for s in sets}) < len(sets):
        raise EvalError("two camera sets have the same name; give each file set a distinct file name")
    _check_dataset_folder(folder)
    kind = "taus" if len(taus) else "budgets"
    twice = next((x for i, x in enumerate(values) if x in values[:i]), None)
    if twice is not None:
        raise EvalError(f"{kind[:-1]} {twice!r} is given twice")
    start = time.perf_counter()
    # Camera files are read (and validated) once, before any work.
    tables = [read_camera_table(s.path) if s.kind == "file" else None for s in sets]
    counts = [len(t) if t is not None else s.count for s, t in zip(sets, tables)]
    # Models are known by their content: the path is where this command
    # finds them (a folder of models may move between runs).
    digests = [file_sha256(m) for m in models]
    described = [dict(s.describe(), count=n) for s, n in zip(sets, counts)]
    command = dict(format=FORMAT, models=[os.path.abspath(m) for m in models], model_sha256=digests,
                   camera_sets=described, taus=[float(t) for t in taus], budgets=[int(b) for b in budgets],
                   tests=_tests_dict(tests), method=method, chunk=int(chunk), batch_chunk=int(batch_chunk),
                   camera_columns=camera_columns, fidelity=fidelity,
                   fidelity_normals="view" if fidelity else None, columns=schema.names)
    total = len(models) * len(values) * sum(counts)
    n_parts = len(models) * len(values) * sum(-(-n // chunk) for n in counts)
    # The parts found done and verified (file name -> SHA-256 of the model
    # they came from), and the parts and rows written now.
    done, checked = {}, False
    written = rows_now = n_done = 0
    try:
        with contextlib.ExitStack() as stack:
            stack.enter_context(_lock_folder(folder))
            job, names = _open_folder(folder, command, schema)
            verified = _verify_folder(folder, names, job, schema)
            # The command's entries by their positions in the folder's job,
            # which name its part files.
            model_names = [_model_name(m) for m in job["models"]]
            set_names = [CameraSet(**{k: v for k, v in d.items() if k in CameraSet.__dataclass_fields__}).name
                         for d in job["camera_sets"]]
            at_model = [model_names.index(_model_name(m)) for m in models]
            at_set = {set_names.index(s.name): i for i, s in enumerate(sets)}
            at_value = {job[kind].index(x): i for i, x in enumerate(command[kind])}
            job_counts = [d["count"] for d in job["camera_sets"]]
            mine = {(m, c, v) for m in at_model for c in at_set for v in at_value}
            for name, model_sha in verified.items():
                m, c, v, _ = (int(g) for g in _PART_NAME.fullmatch(name).groups())
                if (m, c, v) in mine:
                    done[name] = model_sha
            checked = True
            n_done = sum(_rows_of(name, job_counts, chunk) for name in done)
            bar = stack.enter_context(_progress(progress, total, n_done))
            submitted = 0
            runner = _Runner(scheduler, workers)
            # Closed on the way out; quietly after Ctrl-C (see _Runner.close).
            stack.push(lambda kind, exc, tb: runner.close(quiet=kind is not None
                                                         and issubclass(kind, KeyboardInterrupt)))

            def store(finished_parts):
                nonlocal written, rows_now
                for finished, table in finished_parts:
                    _write_part(folder, finished, table)
                    written += 1
                    rows_now += table.num_rows
                    bar.update(table.num_rows)

            for model_path, mi, digest in zip(models, at_model, digests):
                if max_parts is not None and submitted >= max_parts:
                    break
                # The model is validated before its parts start; a bad one stops
                # the job with the parts before it kept.
                try:
                    data = read_pm(model_path)
                except PMFormatError as exc:
                    store(runner.drain())
                    raise EvalError(f"model {model_path}: {exc}") from exc
                vertices = data.vertices[: data.n_original_vertices]
                # The camera sets depend on the box alone: its two corners make
                # the same cameras, without a pass over every vertex per part.
                v64 = np.asarray(vertices, np.float64)
                vertices = np.stack([v64.min(0), v64.max(0)]) if len(v64) else vertices
                # The box centre and half diagonal: those the generated camera sets use.
                bounds = tuple(float(x) for x in np.append(*_bounds(vertices))) if camera_columns else None
                # Parts come one at a time from a generator: nothing is planned
                # ahead of the work, whatever the job's size.
                # Budgets in this process: a chunk's values one after the
                # other, the first part that runs answering the chunk's
                # budgets still to do at once (one guess traversal per camera
                # serves them all) and keeping the others' rows for their parts.
                together = bool(budgets) and runner.client is None
                for part in _model_parts(mi, sorted(at_set), sorted(at_value), job_counts, chunk, together):
                    if part.file in done:
                        if done[part.file] != digest:
                            raise EvalError(f"{os.path.join(folder, part.file)} was computed from another version "
                                            f"of {model_path} (its content changed); use another folder, or delete "
                                            "this one to start over")
                        continue
                    if max_parts is not None and submitted >= max_parts:
                        break
                    ci = at_set[part.cameras]
                    s, value = sets[ci], values[at_value[part.value]]
                    key = _part_key(job, part.model, part.cameras, part.value)
                    # The absolute path: a worker may run in another folder.
                    task = dict(model_path=os.path.abspath(model_path), model_sha256=digest,
                                model_shipped=runner.ship(model_path, digest),
                                model_name=_model_name(model_path),
                                set_name=s.name, rows=s.rows(vertices, part.lo, part.hi, tables[ci]),
                                lo=part.lo, hi=part.hi, tau=None if budgets else value,
                                budget=value if budgets else None, tests=_tests_dict(tests), method=method,
                                batch_chunk=int(batch_chunk), compile_cache=compile_cache, job_sha256=key,
                                part=part.file, bounds=bounds, fidelity=fidelity)
                    if together:
                        later = [v for v in sorted(at_value) if v >= part.value and
                                 _part(mi, part.cameras, v, part.chunk, job_counts, chunk).file not in done]
                        task["budgets_together"] = dict(
                            budgets=[values[at_value[v]] for v in later],
                            keys=[_part_key(job, part.model, part.cameras, v) for v in later])
                    submitted += 1
                    store(runner.submit(part, task))
                del data, vertices, v64
            store(runner.drain())
    except KeyboardInterrupt:
        if not checked:
            raise EvalInterrupted(os.fspath(folder), None, n_parts, n_done + rows_now, total) from None
        # Ctrl-C can fall between a part's rename and its count, so the parts
        # written now are read from the folder (each one there was written
        # whole); those found done may be in compacted files.
        try:
            new = [name for name in _part_files(folder) - done.keys() if (found := _PART_NAME.fullmatch(name))
                   and tuple(int(g) for g in found.groups()[:3]) in mine]
            written, rows_now = len(new), sum(_rows_of(name, job_counts, chunk) for name in new)
        except OSError:  # the folder cannot be listed: the parts this run counted
            pass
        raise EvalInterrupted(os.fspath(folder), len(done) + written, n_parts, n_done + rows_now, total) from None
    return EvalSummary(folder=os.fspath(folder), rows=n_done + rows_now, parts_written=written,
                       parts_skipped=len(done), cameras=rows_now, seconds=time.perf_counter() - start)


@dataclasses.dataclass(frozen=True)
class CompactSummary:
    """What :func:`compact` did.

    Attributes:
        folder: the dataset folder.
        parts: parts in the folder (verified), rows: their rows.
        files_before, files_after: part and compacted files before and after.
        seconds: wall time.
    """

    folder: str
    parts: int
    rows: int
    files_before: int
    files_after: int
    seconds: float


def compact(folder, *, rows_per_file: int = COMPACT_ROWS, row_group_rows: int = COMPACT_GROUP_ROWS) -> CompactSummary:
    """Rewrite the part files of an evaluation dataset ``folder`` into few
    large files, the same rows in the same order, resumable as before.

    Every file is verified first (as a resumed job does: a damaged part is
    set aside, to be computed by the next run of the job). Then each run of
    consecutive parts (in the job's row order: models, camera sets, values,
    chunks) is written into files of at most ``rows_per_file`` rows (a file
    is never cut inside a part), in row groups of ``row_group_rows``, each
    named after its first and last part (``part-m0000-c0000-v0000-0000000-to-
    m0001-c0002-v0003-0000012.parquet``), so lexical order stays row order.
    A compacted file records every part it holds (name, definition key,
    model checksum, rows, checksum over its rows): the job resumes from it,
    verifies each part in it, and sets aside a damaged one whole (its parts
    are computed again). Each file is written atomically, then the files it
    replaces are removed; files left by an interrupted compaction (rows also
    in a compacted file) are removed when the folder is next opened. A folder
    compacted while its job is unfinished resumes too: the missing parts come
    as part files, and a later compaction merges them.

    Args:
        folder: a dataset folder written by :func:`evaluate`.
        rows_per_file: rows per compacted file, at most (a part larger
            than this stays alone); a compacted file is read whole when
            verified, about 110 bytes a row (camera columns: about 170).
        row_group_rows: rows per Parquet row group.

    Returns:
        :class:`CompactSummary`.

    Raises:
        EvalError: not a dataset folder, one another run is writing into, or
            a bad argument.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    for name, value in (("rows_per_file", rows_per_file), ("row_group_rows", row_group_rows)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise EvalError(f"{name} must be a whole number >= 1, not {value!r}")
    if not os.path.isdir(folder):
        raise EvalError(f"{folder}: no such folder")
    if not os.path.exists(os.path.join(folder, JOB_FILE)):
        read_job(folder)  # raises: not a dataset folder (checked before the lock file is made)
    start = time.perf_counter()
    with _lock_folder(folder):
        job = read_job(folder)
        if job.get("format") == FORMAT_2:
            job = _from_format_2(job)
        if job.get("format") != FORMAT:
            raise EvalError(f"{folder} holds a job in format {job.get('format')!r}, this version compacts {FORMAT}")
        schema = _schema(job["camera_columns"], job.get("fidelity", False))
        _remove_temporaries(folder)
        names = _part_files(folder)
        counts, n_models, n_values = _job_shape(job)
        shape = (counts, n_models, n_values, job["chunk"])
        files = _verify_files(folder, names, job, schema)
        # Every part: where its rows are (file, first row) and its record.
        where, records, holds = {}, {}, {}
        for name, shas in files:
            info = json.loads((pq.read_schema(os.path.join(folder, name)).metadata or {})[b"pmjax"])
            listed = info["compacted"] if "compacted" in info else [info]
            offset = 0
            for record in listed:
                part = _part_named(record.get("part", name), counts, n_models, n_values, job["chunk"])
                where[part.file] = (part, name, offset)
                records[part.file] = record
                offset += part.hi - part.lo
            holds[name] = list(shas)
        # Runs of consecutive parts in the job's row order, cut into files of
        # at most rows_per_file rows (never inside a part).
        groups, current, rows = [], [], 0
        for part, _, _ in sorted(where.values(), key=lambda w: (w[0].model, w[0].cameras, w[0].value, w[0].chunk)):
            n = part.hi - part.lo
            if current and (_next_part(current[-1], *shape) != part or rows + n > rows_per_file):
                groups.append(current)
                current, rows = [], 0
            current.append(part)
            rows += n
        if current:
            groups.append(current)
        # A source file goes once every part it holds is written elsewhere.
        left = {name: len(parts) for name, parts in holds.items()}
        cached = [None, None]  # one source file's rows at a time
        for group in groups:
            target = group[0].file if len(group) == 1 else _compact_name(group[0].file, group[-1].file)
            if holds.get(target) == [p.file for p in group]:
                continue  # already this file
            body = []
            for part in group:
                record = records[part.file]
                # A part written without its name, rows or checksum: recorded in full.
                if not all(key in record for key in ("part", "rows", "sha256")):
                    record = dict(job=record["job"], model_sha256=record["model_sha256"], part=part.file,
                                  rows=part.hi - part.lo)
                    record["sha256"] = _table_sha256(_rows_in(folder, where[part.file], cached), record)
                body.append(record)
            metadata = {"pmjax": json.dumps(body[0] if len(group) == 1 else {"compacted": body})}
            with atomic_path(os.path.join(folder, target)) as tmp:
                with pq.ParquetWriter(tmp, schema.with_metadata(metadata)) as writer:
                    buffer, buffered = [], 0
                    for part in group:
                        for batch in _rows_in(folder, where[part.file], cached).to_batches():
                            buffer.append(batch)
                            buffered += batch.num_rows
                        while buffered >= row_group_rows:
                            table = pa.Table.from_batches(buffer, schema)
                            writer.write_table(table.slice(0, row_group_rows), row_group_size=row_group_rows)
                            rest = table.slice(row_group_rows)
                            buffer, buffered = rest.to_batches(), rest.num_rows
                    if buffered:
                        writer.write_table(pa.Table.from_batches(buffer, schema), row_group_size=row_group_rows)
            cached[:] = [None, None]
            # The new file is in place: sources whose every part it (or an
            # earlier new file) holds go; a source of the target's name was
            # replaced by it.
            for part in group:
                source = where[part.file][1]
                left[source] -= 1
                if left[source] == 0 and source != target and os.path.exists(os.path.join(folder, source)):
                    os.unlink(os.path.join(folder, source))
        after = _part_files(folder)
    return CompactSummary(folder=os.fspath(folder), parts=len(where),
                          rows=sum(p.hi - p.lo for p, _, _ in where.values()), files_before=len(names),
                          files_after=len(after), seconds=time.perf_counter() - start)


def _rows_in(folder, located, cached):
    """The rows of a part located at ``(part, file, first row)`` in ``folder``,
    without metadata; ``cached``: ``[file name, its table]``, the last file read."""
    import pyarrow.parquet as pq

    part, name, offset = located
    if cached[0] != name:
        cached[:] = [name, pq.read_table(os.path.join(folder, name)).replace_schema_metadata(None)]
    return cached[1].slice(offset, part.hi - part.lo)


def _part_files(folder) -> set:
    """The names of the part and compacted files in ``folder``."""
    return {name for name in os.listdir(folder) if name.startswith("part-") and name.endswith(".parquet")}


def _remove_temporaries(folder) -> None:
    """Temporary files and folders of killed writers in the dataset folder
    are debris (no part is half-written); a live writer's are left alone."""
    for name in os.listdir(folder):
        at = name.find(TEMP_MARK)
        if name.startswith(".") and at > 1:
            remove_stale_temporaries(os.path.join(folder, name[1:at]))


def _check_dataset_folder(folder) -> None:
    """Refuse an existing folder that holds files but no job description:
    eval moves the files it cannot verify aside, and another program's
    files are not its to move.

    Raises:
        EvalError: naming the folder and some of its files.
    """
    if not os.path.isdir(folder) or any(os.path.exists(os.path.join(folder, n)) for n in (JOB_FILE, OLD_JOB_FILE)):
        return
    foreign = sorted(n for n in os.listdir(folder) if n != ".lock" and TEMP_MARK not in n)
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise EvalError(f"{folder}: holds {len(foreign)} file(s) ({shown}) but no {JOB_FILE}, so it is not a pmjax "
                        "eval dataset folder: give a new or empty folder")


def _model_parts(m, sets, values, counts, chunk, chunk_major=False):
    """The parts of model ``m`` for the camera sets ``sets`` and values
    ``values`` (positions in the job's lists, increasing), in row order
    (``chunk_major``: a chunk's values one after the other), made as they
    are asked for."""
    for c in sets:
        if chunk_major:
            for k in range(-(-counts[c] // chunk)):
                for v in values:
                    yield _part(m, c, v, k, counts, chunk)
            continue
        for v in values:
            for k in range(-(-counts[c] // chunk)):
                yield _part(m, c, v, k, counts, chunk)


def _part(m, c, v, k, counts, chunk) -> _Part:
    """Part ``k`` (its chunk of cameras) of camera set ``c`` for model ``m`` and value ``v``."""
    n = counts[c]
    # Enough digits for the set's last chunk number, so names sort as rows do.
    digits = max(CHUNK_DIGITS, len(str(max(0, -(-n // chunk) - 1))))
    return _Part(m, c, v, k, k * chunk, min((k + 1) * chunk, n), digits)


_PART_NAME = re.compile(r"part-m(\d+)-c(\d+)-v(\d+)-(\d+)\.parquet")


def _part_named(name, counts, n_models, n_values, chunk) -> Optional[_Part]:
    """The part of the job whose file is ``name``, or ``None`` when no part
    of the job has that name."""
    match = _PART_NAME.fullmatch(name)
    if not match:
        return None
    m, c, v, k = (int(g) for g in match.groups())
    if not (m < n_models and c < len(counts) and v < n_values and k * chunk < counts[c]):
        return None
    part = _part(m, c, v, k, counts, chunk)
    return part if part.file == name else None


def _rows_of(name, counts, chunk) -> int:
    """Rows of the part file ``name`` (a name of the job's)."""
    m, c, v, k = (int(g) for g in _PART_NAME.fullmatch(name).groups())
    return min((k + 1) * chunk, counts[c]) - k * chunk


def _lock_folder(folder):
    """An exclusive lock on the dataset folder for this run (released when the
    returned file closes, also when the process dies): two runs writing into
    one folder would remove each other's temporary files."""
    import fcntl

    os.makedirs(folder, exist_ok=True)
    fh = open(os.path.join(folder, ".lock"), "a")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise EvalError(f"{folder}: another pmjax eval is writing into this folder") from None
    return fh


def damaged_folder(folder) -> str:
    """The folder that part files of the dataset ``folder`` failing
    verification are moved into: beside it, its name plus ``.damaged``."""
    return os.path.abspath(folder) + DAMAGED_SUFFIX


def read_job(folder) -> dict:
    """The job description of the dataset ``folder`` (what ``_job.parquet``
    holds: models (``models``, the paths where they were last seen;
    ``model_sha256``, their content), camera sets, values, tests, method,
    chunk sizes, columns), the union of every command run into the folder.

    Raises:
        EvalError: no job description there, or one that cannot be read.
    """
    import pyarrow.parquet as pq

    path = os.path.join(folder, JOB_FILE)
    try:
        metadata = pq.read_schema(path).metadata or {}
        return json.loads(metadata[JOB_KEY])
    except FileNotFoundError:
        raise EvalError(f"{folder}: no {JOB_FILE}, not a pmjax eval dataset folder") from None
    except Exception as exc:  # pyarrow raises several types for a damaged file
        raise EvalError(f"{path}: unreadable job description ({type(exc).__name__}: {exc}); "
                        "use another folder, or delete this one to start over") from None


def _open_folder(folder, command, schema) -> tuple[dict, set]:
    """Reopen (or start) the locked dataset folder for the job ``command``
    (whose rows have ``schema``): the folder's job, extended by the command
    (:func:`_merge_job`) and written back atomically when it changed, and the
    names of the part files there (not yet verified, see :func:`_verify_folder`)."""
    import pyarrow.parquet as pq

    path = os.path.join(folder, JOB_FILE)
    old_path = os.path.join(folder, OLD_JOB_FILE)
    if not os.path.exists(path) and os.path.exists(old_path):
        try:
            with open(old_path) as fh:
                form = json.load(fh).get("format", "unknown")
        except (OSError, ValueError, AttributeError):
            form = "unknown"
        raise EvalError(f"{folder} holds a job in format {form} (described by {OLD_JOB_FILE}), whose parts lack "
                        f"columns of format {FORMAT_2}; its rows stay readable, but it cannot be resumed: use "
                        "another folder, or delete this one to start over")
    job = _merge_job(folder, read_job(folder), command) if os.path.exists(path) else command
    if not os.path.exists(path) or read_job(folder) != job:
        empty = schema.empty_table().replace_schema_metadata({JOB_KEY: json.dumps(job, indent=1, sort_keys=True)})
        with atomic_path(path) as tmp:
            pq.write_table(empty, tmp)
    _remove_temporaries(folder)
    return job, _part_files(folder)


def _short(value):
    """A value for a message: SHA-256 digests cut to their first 12 digits."""
    if isinstance(value, str) and re.fullmatch(r"[0-9a-f]{64}", value):
        return value[:12]
    return value


def _from_format_2(job: dict) -> dict:
    """A description of format pmjax-eval/2 in this format: its models'
    digests and camera files' row counts unknown (``None``, taken from the
    next command that names them), its checksum kept as ``legacy_jobs``."""
    sha = hashlib.sha256(json.dumps(job, sort_keys=True).encode()).hexdigest()
    sets = [dict(d, count=None) if d.get("kind") == "file" else d for d in job.get("camera_sets", [])]
    return dict(job, format=FORMAT, model_sha256=[None] * len(job.get("models", [])), camera_sets=sets,
                legacy_jobs=[sha])


def _merge_job(folder, old: dict, new: dict) -> dict:
    """The job of ``folder`` (``old``) extended by a command's job ``new``.

    A job grows: models, camera sets and values (tolerances or budgets) the
    folder lacks are appended to its lists, so parts there keep their names
    (a part file is named by positions in these lists), and the folder's
    rows are those of every command run into it. What defines an existing
    part cannot change: the settings (:data:`SETTINGS`), tolerances against
    budgets, a model's content (SHA-256; its path is only where it was last
    seen, so a moved model resumes), a camera set's definition (a file's
    content; its path is a hint too).

    Raises:
        EvalError: a change to what defines the folder's parts, naming the
            old and new values; or a folder of another format.
    """
    if old.get("format") == FORMAT_2:
        old = _from_format_2(old)
    if old.get("format") != FORMAT:
        raise EvalError(f"{folder} holds a job in format {old.get('format')!r}, this version writes {FORMAT}; "
                        "use another folder, or delete this one to start over")
    # A folder written before the image metrics existed has none.
    old = dict(old, fidelity=old.get("fidelity", False))
    # Image metrics written before refinements were shaded with normals
    # fitted per view used the stored normals: their rows would not mix.
    old["fidelity_normals"] = old.get("fidelity_normals", "stored" if old["fidelity"] else None)
    changes = [f"{key}: {_short(old.get(key))!r} there, {_short(new[key])!r} here"
               for key in SETTINGS + ("fidelity", "fidelity_normals") if old.get(key) != new[key]
               # Normals follow fidelity: named once.
               and not (key == "fidelity_normals" and old["fidelity"] != new["fidelity"])
               # The columns follow camera_columns and fidelity: named once.
               and not (key == "columns" and (old.get("camera_columns") != new["camera_columns"]
                                              or old["fidelity"] != new["fidelity"]))]
    if bool(old["taus"]) != bool(new["taus"]):
        there = f"tolerances {old['taus']}" if old["taus"] else f"budgets {old['budgets']}"
        here = f"tolerances {new['taus']}" if new["taus"] else f"budgets {new['budgets']}"
        changes.append(f"values: {there} there, {here} here")
    job = json.loads(json.dumps(old))
    names = [_model_name(m) for m in job["models"]]
    for path, digest in zip(new["models"], new["model_sha256"]):
        name = _model_name(path)
        if name not in names:
            names.append(name)
            job["models"].append(path)
            job["model_sha256"].append(digest)
            continue
        i = names.index(name)
        if job["model_sha256"][i] not in (None, digest):
            changes.append(f"model {name!r}: content SHA-256 {_short(job['model_sha256'][i])} there (then at "
                           f"{job['models'][i]}), {_short(digest)} here ({path}; its content changed)")
        job["models"][i], job["model_sha256"][i] = path, digest
    set_names = [CameraSet(**{k: v for k, v in d.items() if k in CameraSet.__dataclass_fields__}).name
                 for d in job["camera_sets"]]
    for d in new["camera_sets"]:
        name = CameraSet(**{k: v for k, v in d.items() if k in CameraSet.__dataclass_fields__}).name
        if name not in set_names:
            set_names.append(name)
            job["camera_sets"].append(d)
            continue
        i = set_names.index(name)
        was = job["camera_sets"][i]
        differ = [f"{key} {_short(was.get(key))!r} there, {_short(d.get(key))!r} here"
                  for key in sorted(set(was) | set(d))
                  if key != "path" and was.get(key) != d.get(key) and not (key == "count" and was.get(key) is None)]
        if differ:
            changes.append(f"camera set {name!r}: " + ", ".join(differ))
        job["camera_sets"][i] = d
    kind = "taus" if new["taus"] else "budgets"
    if not changes:
        job[kind] = job[kind] + [x for x in new[kind] if x not in job[kind]]
    if changes:
        raise EvalError(f"{folder} holds parts that this command defines otherwise ({'; '.join(changes)}); a job "
                        "can gain models, camera sets and values, but its parts cannot change: use another folder, "
                        "or delete this one to start over")
    return job


def _part_key(job: dict, m: int, c: int, v: int) -> str:
    """SHA-256, hex, of what defines the rows of model ``m``, camera set ``c``
    and value ``v`` of ``job`` (positions in its lists): the settings, the
    model's name, the set's definition and the value; not the paths (hints)
    nor the job's other entries, so a part stays valid as its job grows or
    its files move. A part file records it (``job``); the model's content is
    recorded and checked apart (``model_sha256``)."""
    value = (job["taus"] or job["budgets"])[v]
    record = dict(format=FORMAT, model=_model_name(job["models"][m]),
                  camera_set={k: x for k, x in job["camera_sets"][c].items() if k != "path"},
                  tau=value if job["taus"] else None, budget=None if job["taus"] else value,
                  **{key: job[key] for key in SETTINGS})
    # Recorded when on only: parts without image metrics keep the key they had before the setting existed.
    if job.get("fidelity"):
        record["fidelity"] = True
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()


def _job_shape(job: dict):
    """Of the job: its camera sets' counts (``None`` where unknown: a camera
    file of a pmjax-eval/2 folder no command has named since), models and values."""
    return ([d["count"] for d in job["camera_sets"]], len(job["models"]), len(job["taus"] or job["budgets"]))


def _verify_folder(folder, names, job, schema=None) -> dict:
    """Verify the part files ``names`` of the dataset folder against its
    ``job`` (:func:`_verify_files`).

    Returns:
        ``{part file name: SHA-256 of the model the part was computed from}``
        for the parts that verify, those in compacted files included.
    """
    return {name: sha for _, shas in _verify_files(folder, names, job, schema) for name, sha in shas.items()}


def _set_aside(folder, name, problem) -> None:
    """Move the file ``name`` of ``folder`` into :func:`damaged_folder`, with a line on stderr."""
    path, aside = os.path.join(folder, name), os.path.join(damaged_folder(folder), name)
    os.makedirs(os.path.dirname(aside), exist_ok=True)
    os.replace(path, aside)
    what = "its parts are" if _COMPACT_NAME.fullmatch(name) else "the part is"
    print(f"pmjax eval: {path}: {problem}; moved to {aside}, {what} computed again", file=sys.stderr, flush=True)


def _verify_files(folder, names, job, schema=None) -> list:
    """Verify the files ``names`` of the dataset folder (part files and
    compacted files, :func:`compact`) against its ``job``; those that fail are
    moved into :func:`damaged_folder` (a line on stderr says which and why) so
    that the job computes their parts again. Parts of a camera file whose row
    count is unknown (:func:`_job_shape`) are left as they are, unverified,
    until a command names that file. A file whose parts are all in a larger
    compacted file that verifies is what an interrupted compaction left
    behind: it is removed (a line on stderr).

    Returns:
        ``[(file name, {part name: model SHA-256})]``, the files that verify.
    """
    from concurrent.futures import ThreadPoolExecutor

    counts, n_models, n_values = _job_shape(job)
    legacy = set(job.get("legacy_jobs", ()))

    def unknown(name):
        match = _PART_NAME.fullmatch(name)
        return bool(match) and int(match.group(2)) < len(counts) and counts[int(match.group(2))] is None

    def keys(part):
        return {_part_key(job, part.model, part.cameras, part.value)} | legacy

    singles, compacted = {}, {}
    for name in sorted(names):
        span = _COMPACT_NAME.fullmatch(name)
        if span is None:
            if not unknown(name):
                singles[name] = _part_named(name, counts, n_models, n_values, job["chunk"])
            continue
        first, last = (f"part-{span.group(i)}.parquet" for i in (1, 2))
        if unknown(first) or unknown(last):
            continue
        compacted[name] = [_part_named(n, counts, n_models, n_values, job["chunk"]) for n in (first, last)]
    outside = ("is not a part of this job (its name is outside the job's models, camera sets, values or chunks)",
               None)
    verified = []
    # Compacted files one at a time (each is read whole, up to its rows_per_file rows).
    def named(name):
        return None if unknown(name) else _part_named(name, counts, n_models, n_values, job["chunk"])

    for name, (first, last) in compacted.items():
        problem, shas = _verify_compacted(os.path.join(folder, name), first, last, named, keys, schema)
        if problem is None:
            verified.append((name, shas))
        else:
            _set_aside(folder, name, problem)
    # The largest first: a file whose parts it holds is left over from its compaction.
    claimed, kept = {}, []
    for name, shas in sorted(verified, key=lambda item: -len(item[1])):
        if all(part in claimed for part in shas):
            _remove_leftover(folder, name, claimed[next(iter(shas))])
        elif any(part in claimed for part in shas):
            _set_aside(folder, name, f"holds parts also in {claimed[next(p for p in shas if p in claimed)]}")
        else:
            claimed.update(dict.fromkeys(shas, name))
            kept.append((name, shas))
    for name in [n for n in singles if n in claimed]:
        _remove_leftover(folder, name, claimed[name])
        del singles[name]

    def check(name):
        part = singles[name]
        if part is None:
            return outside
        return _verify_part(os.path.join(folder, name), part, keys(part), schema)

    # Parquet decoding and hashing release the GIL: verify parts in parallel.
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
        for name, (problem, model_sha) in zip(singles, pool.map(check, singles)):
            if problem is None:
                kept.append((name, {name: model_sha}))
            else:
                _set_aside(folder, name, problem)
    return kept


# A compacted file (:func:`compact`): the rows of a run of consecutive parts,
# named after its first and last, so that lexical order stays row order.
_COMPACT_NAME = re.compile(r"part-(m\d+-c\d+-v\d+-\d+)-to-(m\d+-c\d+-v\d+-\d+)\.parquet")


def _next_part(part, counts, n_models, n_values, chunk) -> Optional[_Part]:
    """The part after ``part`` in the job's row order (models, camera sets,
    values, chunks; all the job's entries), or ``None`` after the last or
    before a camera set of unknown count."""
    m, c, v, k = part.model, part.cameras, part.value, part.chunk
    if (k + 1) * chunk < counts[c]:
        return _part(m, c, v, k + 1, counts, chunk)
    if v + 1 < n_values:
        return _part(m, c, v + 1, 0, counts, chunk)
    if c + 1 < len(counts):
        return None if counts[c + 1] is None else _part(m, c + 1, 0, 0, counts, chunk)
    if m + 1 < n_models:
        return None if counts[0] is None else _part(m + 1, 0, 0, 0, counts, chunk)
    return None


def _compact_name(first: str, last: str) -> str:
    """The name of the compacted file holding the parts ``first`` to ``last``."""
    return f"{first[:-len('.parquet')]}-to-{last[len('part-'):]}"


def _read_checked(path):
    """``(table, pmjax metadata, problem)`` of a Parquet file read in full:
    ``problem`` says why it is unreadable (a truncated file, a damaged page)
    or why its footer statistics disagree with its rows, else ``None``."""
    import pyarrow.parquet as pq

    try:
        with pq.ParquetFile(path) as pf:
            table = pf.read()
            # Damaged pages can decode into invalid arrays (a dictionary index out of range).
            table.validate(full=True)
            info = json.loads((table.schema.metadata or {}).get(b"pmjax", b"{}"))
            # Readers skip files by the footer's statistics: damaged ones would drop rows from a filtered read.
            wrong = _wrong_statistics(pf.metadata, table)
    except Exception as exc:  # pyarrow raises several types for a damaged file
        return None, None, f"unreadable ({type(exc).__name__}: {exc})"
    return table, info, wrong or None


def _verify_compacted(path, first, last, named, keys, schema=None):
    """Read a compacted file in full and check it: Arrow's validation, the
    footer statistics, the columns, and per part in its record, from
    ``first`` to ``last`` in the job's row order (``named(name)``: the job's
    part of that name or ``None``; ``keys(part)``: the definition keys its
    record may hold), its name, row count, checksum over its rows, job and
    model checksum.

    Returns:
        ``(problem, {part name: model SHA-256})``, ``problem`` ``None`` when it verifies.
    """
    if first is None or last is None:
        return ("is not a part of this job (its name is outside the job's models, camera sets, values or "
                "chunks)"), None
    table, info, problem = _read_checked(path)
    if problem:
        return problem, None
    records = info.get("compacted") if isinstance(info, dict) else None
    if not isinstance(records, list) or not records or not all(isinstance(r, dict) for r in records):
        return "has no pmjax record of the parts it holds", None
    if not table.schema.remove_metadata().equals(schema if schema is not None else _schema()):
        return f"has columns {table.schema.remove_metadata().to_string()!r}, not this job's", None
    if records[0].get("part") != first.file or records[-1].get("part") != last.file:
        return f"its records run from {records[0].get('part')!r} to {records[-1].get('part')!r}, its name says " \
               f"{first.file} to {last.file}", None
    shas, offset, before = {}, 0, None
    for i, record in enumerate(records):
        part = named(record.get("part")) if isinstance(record.get("part"), str) else None
        if part is None:
            return f"its record {i} names {record.get('part')!r}, not a part of this job", None
        order = (part.model, part.cameras, part.value, part.chunk)
        if before is not None and order <= before:
            return f"its record {i} names {part.file}, out of the job's row order", None
        before = order
        n = part.hi - part.lo
        if record.get("rows") != n or offset + n > table.num_rows:
            return f"holds {record.get('rows')!r} rows of {part.file} from row {offset}, expected {n}", None
        body = {k: v for k, v in record.items() if k != "sha256"}
        if record.get("sha256") != _table_sha256(table.slice(offset, n), body):
            return f"the rows of {part.file} do not match their checksum (damaged data)", None
        if record.get("job") not in keys(part):
            return f"{part.file} was written by another job", None
        if not isinstance(record.get("model_sha256"), str):
            return f"{part.file} has no model checksum", None
        shas[part.file] = record["model_sha256"]
        offset += n
    if offset != table.num_rows:
        return f"holds {table.num_rows} rows, its records {offset}", None
    return None, shas


def _remove_leftover(folder, name, holder) -> None:
    os.unlink(os.path.join(folder, name))
    print(f"pmjax eval: {os.path.join(folder, name)}: its rows are in {holder} (left over from an interrupted "
          "compaction); removed", file=sys.stderr, flush=True)


def _verify_part(path, part, job_sha, schema=None):
    """Read a part file in full and check it against its part of the job
    (``job_sha``: the key its record must hold, :func:`_part_key`, or a set
    of keys accepted; ``schema``: the job's columns, by default those
    without camera context).

    Returns:
        ``(problem, model_sha256)``: ``problem`` is ``None`` for a part that
        verifies, else says what is wrong: unreadable (a truncated file, a
        damaged page), footer statistics that disagree with the rows, a
        checksum that does not match (damaged data that still decodes),
        written by another job or for another part, other columns, the wrong
        row count or (parts written without a checksum) camera rows.
    """
    table, info, problem = _read_checked(path)
    if problem:
        return problem, None
    signed = isinstance(info, dict) and "sha256" in info
    try:
        digest = _table_sha256(table, {k: v for k, v in info.items() if k != "sha256"}) if signed else None
    except Exception as exc:  # a damaged record that still decodes
        return f"unreadable ({type(exc).__name__}: {exc})", None
    if not isinstance(info, dict) or not isinstance(info.get("model_sha256"), str):
        return "has no pmjax metadata (job and model checksums)", None
    # The checksum first: once it holds, the record (job, part, rows) is the one written.
    if signed and info["sha256"] != digest:
        return "its content does not match its checksum (damaged data)", None
    if info.get("job") not in ({job_sha} if isinstance(job_sha, str) else set(job_sha)):
        return "was written by another job", None
    name = os.path.basename(path)
    if info.get("part", name) != name:
        return f"holds the rows of {info['part']}, another part", None
    if not table.schema.remove_metadata().equals(schema if schema is not None else _schema()):
        return f"has columns {table.schema.remove_metadata().to_string()!r}, not this job's", None
    want = part.hi - part.lo
    if table.num_rows != want or info.get("rows", want) != want:
        return f"has {table.num_rows} rows (its metadata says {info.get('rows')!r}), expected {want}", None
    # Parts written without a checksum: the camera rows at least must be the part's.
    if not signed and not np.array_equal(table.column("camera").to_numpy(zero_copy_only=False),
                                         np.arange(part.lo, part.hi)):
        return f"its camera column is not {part.lo}..{part.hi - 1}", None
    return None, info["model_sha256"]


def _wrong_statistics(metadata, table) -> Optional[str]:
    """What in a Parquet file's column statistics (null count, min, max per
    row group) disagrees with its ``table`` as read, or ``None``."""
    import pyarrow as pa
    import pyarrow.compute as pc

    start = 0
    for r in range(metadata.num_row_groups):
        group = metadata.row_group(r)
        rows = table.slice(start, group.num_rows)
        start += group.num_rows
        for i in range(group.num_columns):
            chunk = group.column(i)
            # pyarrow aborts the process when asked for the statistics of a
            # column whose type in the footer was damaged: check it first.
            kind = metadata.schema.column(i).physical_type
            if chunk.physical_type != kind:
                return (f"the footer gives column {chunk.path_in_schema!r} type {chunk.physical_type}, "
                        f"its schema {kind}")
            stats = chunk.statistics
            if stats is None:
                continue
            column = rows.column(chunk.path_in_schema)
            if pa.types.is_dictionary(column.type):
                column = column.cast(column.type.value_type)
            if stats.has_null_count and stats.null_count != column.null_count:
                return (f"the statistics of column {chunk.path_in_schema!r} count {stats.null_count} nulls, "
                        f"the column holds {column.null_count}")
            if stats.has_min_max:
                got = pc.min_max(column)
                lo, hi = got["min"].as_py(), got["max"].as_py()
                if (stats.min, stats.max) != (lo, hi):
                    return (f"the statistics of column {chunk.path_in_schema!r} give {stats.min!r}..{stats.max!r}, "
                            f"the column holds {lo!r}..{hi!r}")
    return None


def _write_part(folder, part, table) -> None:
    import pyarrow.parquet as pq

    with atomic_path(os.path.join(folder, part.file)) as tmp:
        pq.write_table(table, tmp)


def _progress(on, total, done):
    from tqdm import tqdm

    return tqdm(total=total, initial=done, unit="camera", unit_scale=True, desc="eval", disable=not on,
                smoothing=0.1)


def _quiet_dask_logs() -> None:
    """Dask's logs at level ERROR and above only (run on workers)."""
    import logging

    logging.getLogger("distributed").setLevel(logging.ERROR)


class _Runner:
    """Runs parts in this process, or on Dask with a bounded number in flight
    (camera rows are made as parts are submitted, so memory stays flat)."""

    def __init__(self, scheduler, workers):
        self.client = self.cluster = None
        if scheduler or workers:
            from dask.distributed import Client, LocalCluster

            if scheduler:
                self.client = Client(scheduler, set_as_default=False)
            else:
                # Threads of this process, not worker processes: it has
                # imported pmjax already, and its threads share each loaded
                # model and compiled kernel, where each process would import,
                # load and compile on its own before its first part, and then
                # compete with this one for the cores (docs/eval.md measures
                # both). The engine's calls release the GIL and may run
                # concurrently. A free port for the scheduler's HTTP server:
                # in-process, it would take 8787 and warn when that is in use.
                self.cluster = LocalCluster(n_workers=1, threads_per_worker=int(workers), processes=False,
                                            dashboard_address=":0")
                self.client = Client(self.cluster, set_as_default=False)
            # Pending futures; each result is fetched with the future's own
            # result(), which waits for the scheduler to recompute a result
            # lost with its worker (as_completed(with_results=True) can wait
            # forever in that case).
            self.pending = []
            self.parts = {}
            # Model bytes shipped to the cluster (digest -> (dataset name,
            # future)), and the model of each pending part (future key -> digest).
            self.shipped, self.models = {}, {}
            threads = sum(self.client.nthreads().values()) or int(workers) or 1
            self.window = 2 * threads + 2

    def ship(self, path: str, digest: str) -> Optional[str]:
        """On a cluster given by its scheduler (whose workers may not share
        this file system): the name of a Dask dataset holding the model's
        bytes, put into the cluster once per job for workers that cannot read
        ``path`` (they fetch them, :func:`_model`); models no pending part
        needs are released. ``None`` in this process and on a local cluster
        (same files)."""
        if self.client is None or self.cluster is not None:
            return None
        if digest not in self.shipped:
            for old in set(self.shipped) - set(self.models.values()):
                name, future = self.shipped.pop(old)
                self.client.unpublish_dataset(name)
                future.release()
            with open(path, "rb") as fh:
                data = fh.read()
            if hashlib.sha256(data).hexdigest() != digest:
                raise EvalError(f"{path}: the model file changed while the job ran")
            # Named per client: jobs running at once on one cluster keep their own.
            name = f"pmjax-model-{digest[:16]}-{self.client.id}"
            future = self.client.scatter(data, hash=False)
            self.client.publish_dataset(future, name=name)
            self.shipped[digest] = name, future
        return self.shipped[digest][0]

    def submit(self, part, task):
        if self.client is None:
            return [(part, run_part(task))]
        future = self.client.submit(run_part_on_worker, task, key=f"pmjax-eval-{task['job_sha256'][:12]}-{part.file}",
                                    pure=False, retries=2)
        self.parts[future.key] = part
        self.models[future.key] = task["model_sha256"]
        self.pending.append(future)
        return self._collect(self.window)

    def _collect(self, keep):
        out = []
        while len(self.pending) > keep:
            # Polled: distributed.wait and as_completed use the process's
            # default client, which need not be this one.
            done = [f for f in self.pending if f.done()]
            if not done:
                time.sleep(0.01)
                continue
            for future in done:
                out.append((self.parts.pop(future.key), future.result()))
                self.models.pop(future.key, None)
            # Keep what was not collected. (Not "not done": a future whose
            # result lived on a worker that died goes back to pending, and
            # would be collected twice.)
            self.pending = [f for f in self.pending if f.key in self.parts]
        return out

    def drain(self):
        return [] if self.client is None else self._collect(0)

    def close(self, quiet=False):
        """Close the client (and the local cluster). ``quiet``: after Ctrl-C,
        Dask's warnings about the tasks cut short are expected, not news:
        they are silenced here and on the local cluster's workers (which
        write to this process's stderr)."""
        if self.client is not None and quiet:
            import logging

            logging.getLogger("distributed").setLevel(logging.ERROR)
            if self.cluster is not None:
                with contextlib.suppress(Exception):
                    self.client.run(_quiet_dask_logs)
        if self.client is not None:
            # Published data outlives its client: the shipped models are removed from the cluster.
            for name, _ in self.shipped.values():
                with contextlib.suppress(Exception):
                    self.client.unpublish_dataset(name)
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
