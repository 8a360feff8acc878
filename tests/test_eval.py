"""Evaluation jobs: Parquet rows equal refine_batch, camera tables are
validated, a killed job resumes to the same rows, Dask gives the same rows
(also when a worker dies), a changed job or a bad model is refused clearly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from pmjax._atomic import TEMP_MARK

import pmjax
from pmjax._camera_table import (CameraError, fly_rows, orbit_rows, random_rows, read_camera_table,
                                 table_from_cameras, write_camera_table)
from pmjax._eval import EvalError, evaluate

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
ds = pytest.importorskip("pyarrow.dataset")

DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces", "vertices", "executed"]


def rows(folder):
    """The dataset's deterministic columns as NumPy arrays (strings decoded)."""
    table = ds.dataset(folder, format="parquet").to_table()
    out = {}
    for c in DETERMINISTIC:
        values = table.column(c).to_pylist()
        out[c] = np.asarray(values, dtype=object if None in values or c in ("model", "camera_set") else None)
    return out


def assert_same_rows(a, b):
    for c in DETERMINISTIC:
        x, y = a[c], b[c]
        assert x.shape == y.shape, c
        assert x.tolist() == y.tolist(), c


def test_generated_sets_do_not_depend_on_chunking():
    v = np.random.default_rng(0).normal(size=(60, 3))
    for make in (lambda lo, hi: random_rows(v, 5, lo, hi), lambda lo, hi: orbit_rows(v, 9000, lo, hi),
                 lambda lo, hi: fly_rows(v, 9000, lo, hi)):
        whole = make(0, 9000)
        pieces = [make(lo, min(lo + 1500, 9000)) for lo in range(0, 9000, 1500)]
        for field in ("eye", "rotation", "near", "far"):
            assert np.array_equal(getattr(whole, field), np.concatenate([getattr(p, field) for p in pieces]))
        r = whole.rotation
        assert np.allclose(np.einsum("nji,njk->nik", r, r), np.eye(3), atol=1e-12)
    # The orbit generator is the standard orbit.
    orbit = pmjax.standard_orbit(v, 40)
    assert np.array_equal(np.asarray(orbit.eye), np.asarray(orbit_rows(v, 40, 0, 40).camera().eye))


@pytest.mark.parametrize("spec, message", [
    ("random:5:-1", "camera set 'random:5:-1': the seed must be a whole number >= 0, not -1"),
    ("orbit:0", "camera set 'orbit:0': expected orbit:N with N >= 1"),
    ("fly:3:1", "camera set 'fly:3:1': expected fly:N with N >= 1"),
    ("random:x", "camera set 'random:x': expected random:N[:SEED]"),
])
def test_bad_camera_set_specs_are_refused_naming_the_spec(spec, message):
    with pytest.raises(EvalError) as info:
        pmjax.camera_set(spec)
    assert str(info.value) == message


@pytest.mark.parametrize("suffix", [".npz", ".parquet"])
def test_camera_table_round_trip(tmp_path, suffix):
    v = np.random.default_rng(1).normal(size=(30, 3))
    table = table_from_cameras(pmjax.random_views(v, 20, seed=2), path_id=np.arange(20) // 5, frame=np.arange(20) % 5)
    path = tmp_path / f"cams{suffix}"
    write_camera_table(table, path)
    back = read_camera_table(path)
    for field in ("eye", "rotation", "fov_y", "near", "far", "width", "height", "path_id", "frame"):
        assert np.allclose(getattr(back, field), getattr(table, field), rtol=0, atol=1e-12), field


def _write_columns(path, cols):
    if str(path).endswith(".npz"):
        np.savez(path, **cols)
    else:
        pq.write_table(pa.table(cols), path)


@pytest.mark.parametrize("suffix", [".npz", ".parquet"])
def test_bad_camera_tables_are_refused_by_row_and_column(tmp_path, suffix):
    good = dict(eye_x=np.zeros(4), eye_y=np.zeros(4), eye_z=np.full(4, 5.0),
                target_x=np.zeros(4), target_y=np.zeros(4), target_z=np.zeros(4))
    cases = [
        (dict(eye_x=None), "column 'eye_x' is missing"),
        (dict(eye_y=np.array(["a", "b", "c", "d"])), "column 'eye_y' has dtype"),
        (dict(eye_z=np.array([5.0, 5.0, np.nan, 5.0])), "row 2: column 'eye_z' is nan"),
        (dict(eyes=np.zeros(4)), "unknown column 'eyes'"),
        (dict(width=np.array([800, 0, 800, 800])), "row 1: column 'width'"),
        (dict(height=np.array([600.0, 600.5, 600.0, 600.0])), "row 1: column 'height' is 600.5"),
        (dict(fov_y_deg=np.array([45.0, 45.0, 45.0, 180.0])), "row 3: column 'fov_y_deg'"),
        (dict(near=np.full(4, 2.0), far=np.array([10.0, 10.0, 1.0, 10.0])), "row 2: column 'far'"),
        (dict(eye_z=np.array([5.0, 0.0, 5.0, 5.0])), "row 1: eye and target coincide"),
        (dict(orthographic=np.array([0, 2, 0, 0])), "row 1: column 'orthographic'"),
        (dict(width=np.array([800.0, 800.0, np.inf, 800.0])), "row 2: column 'width' is inf, expected an integer"),
        (dict(path_id=np.zeros(4), frame=np.array([0.0, 1e30, 2.0, 3.0])),
         "row 1: column 'frame' is 1e+30, expected an integer within int64"),
        (dict(path_id=np.array([0, 0, 2 ** 64 - 1, 0], np.uint64), frame=np.arange(4)),
         "row 2: column 'path_id' is 18446744073709551615, expected an integer within int64"),
    ]
    for change, message in cases:
        cols = {k: v for k, v in {**good, **change}.items() if v is not None}
        path = tmp_path / f"bad{suffix}"
        _write_columns(path, cols)
        with pytest.raises(CameraError) as info:
            read_camera_table(path)
        assert message in str(info.value) and str(path) in str(info.value), (message, str(info.value))
    # A reflection given as a rotation.
    cols = {**{k: good[k] for k in ("eye_x", "eye_y", "eye_z")},
            **{f"r{i}{j}": np.full(4, (-1.0 if i == 0 else 1.0) if i == j else 0.0) for i in range(3) for j in range(3)}}
    _write_columns(tmp_path / f"flip{suffix}", cols)
    with pytest.raises(CameraError, match="row 0: r00..r22 is a reflection"):
        read_camera_table(tmp_path / f"flip{suffix}")


@pytest.mark.slow
def test_rows_equal_refine_batch(cow, tmp_path):
    data = pmjax.read_pm(cow)
    v0 = data.vertices[: data.n_original_vertices]
    pm = pmjax.load(cow)
    # A camera file with two image sizes and paths, beside two generated sets.
    a, b = pmjax.random_views(v0, 70, seed=4), pmjax.random_views(v0, 30, seed=5, width=320, height=200)
    ta, tb = table_from_cameras(a, 1, np.arange(70)), table_from_cameras(b, 2, np.arange(30))
    mixed = pmjax._camera_table.CameraTable(**{f: np.concatenate([getattr(ta, f), getattr(tb, f)])
                                                for f in ta.__dataclass_fields__})
    write_camera_table(mixed, tmp_path / "mixed.parquet")
    out = tmp_path / "out"
    summary = evaluate([cow], ["orbit:50", "random:300:2", str(tmp_path / "mixed.parquet")], str(out),
                       taus=[0.5, 2.0], chunk=128, compile_cache=None, progress=False)
    assert summary.rows == summary.cameras == 2 * (50 + 300 + 100) and summary.parts_skipped == 0
    table = ds.dataset(str(out), format="parquet").to_table()
    assert [(f.name, str(f.type)) for f in table.schema] == [
        ("model", "string"), ("camera_set", "string"),
        ("camera", "int64"), ("path_id", "int64"), ("frame", "int64"), ("budget", "int64"),
        ("budget_met", "bool"), ("tau", "float"),
        ("faces", "int64"), ("vertices", "int64"), ("executed", "int64"), ("refine_ms", "double"),
        ("compile_ms", "double")]
    got = rows(str(out))
    assert set(got["model"]) == {"cow"}
    start = 0
    for name, cams, paths in [("orbit-50", pmjax.standard_orbit(v0, 50), (np.zeros(50), np.arange(50))),
                              ("random-300-seed2", pmjax.random_views(v0, 300, seed=2), None),
                              ("mixed.parquet", None, (mixed.path_id, mixed.frame))]:
        for tau in (0.5, 2.0):
            n = 100 if cams is None else pmjax.camera_count(cams)
            sl = slice(start, start + n)
            assert np.all(got["camera_set"][sl] == name) and np.all(got["tau"][sl] == np.float32(tau))
            assert np.array_equal(got["camera"][sl], np.arange(n))
            if cams is None:  # two image sizes: one batch each
                expect = {k: np.concatenate([pmjax.refine_batch(pm, c, tau)[k] for c in (a, b)])
                          for k in ("faces", "vertices", "executed_count")}
            else:
                expect = pmjax.refine_batch(pm, cams, tau)
            assert np.array_equal(got["faces"][sl], expect["faces"])
            assert np.array_equal(got["vertices"][sl], expect["vertices"])
            assert np.array_equal(got["executed"][sl], expect["executed_count"])
            if paths is None:
                assert all(x is None for x in got["path_id"][sl])
            else:
                assert np.array_equal(got["path_id"][sl].astype(int), paths[0])
                assert np.array_equal(got["frame"][sl].astype(int), paths[1])
            start += n
    assert start == len(got["camera"])
    assert all(x is None for x in got["budget_met"])  # tau jobs have no budget
    # Same job again: nothing recomputed. Parts defined otherwise: refused, folder intact.
    again = evaluate([cow], ["orbit:50", "random:300:2", str(tmp_path / "mixed.parquet")], str(out),
                     taus=[0.5, 2.0], chunk=128, compile_cache=None, progress=False)
    assert again.parts_written == 0 and again.parts_skipped == summary.parts_written
    with pytest.raises(EvalError, match=r"holds parts that this command defines otherwise \(chunk: 128 there, "
                                        r"64 here\)"):
        evaluate([cow], ["orbit:50", "random:300:2", str(tmp_path / "mixed.parquet")], str(out), taus=[0.5, 2.0],
                 chunk=64, compile_cache=None, progress=False)
    assert_same_rows(rows(str(out)), got)


@pytest.mark.slow
def test_budgets(cow, tmp_path):
    data = pmjax.read_pm(cow)
    pm = pmjax.load(cow)
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 6)
    base = int(pmjax.refine(pm, pmjax.index_camera(cams, 0), np.inf).n_faces)  # the coarsest mesh
    # A budget below the coarsest mesh cannot be met: tau inf, faces above it, budget_met false.
    low = base - 1
    evaluate([cow], ["orbit:6"], str(tmp_path / "b"), budgets=[low, 400, 3000], compile_cache=None,
             progress=False)
    got = rows(str(tmp_path / "b"))
    k = 0
    for budget in (low, 400, 3000):
        for i in range(6):
            cam = pmjax.index_camera(cams, i)
            tau, faces = pmjax.faces_for_budget(pm, cam, budget)
            assert got["budget"][k] == budget and got["tau"][k] == tau and got["faces"][k] == faces
            assert bool(got["budget_met"][k]) == (faces <= budget) == (budget != low)
            if budget == low:
                assert tau == np.inf and faces == base
            assert got["executed"][k] == int(pmjax.refine(pm, cam, float(tau)).n_executed)
            k += 1


def test_a_bad_model_stops_the_job_and_keeps_earlier_parts(cow, tmp_path):
    bad = tmp_path / "broken.pmz"
    bad.write_bytes(open(cow, "rb").read()[:5000])
    out = str(tmp_path / "out")
    with pytest.raises(EvalError, match=f"model {bad}"):
        evaluate([cow, str(bad)], ["orbit:20"], out, taus=[1.0], chunk=8, compile_cache=None, progress=False)
    got = rows(out)
    assert np.array_equal(got["camera"], np.arange(20)) and set(got["model"]) == {"cow"}
    assert not [n for n in os.listdir(out) if TEMP_MARK in n]
    # While a run holds the folder, a second run is refused.
    with pmjax._eval._lock_folder(out):
        with pytest.raises(EvalError, match="another pmjax eval is writing into this folder"):
            evaluate([cow], ["orbit:20"], out, taus=[1.0], chunk=8, compile_cache=None, progress=False)


def test_a_folder_of_other_files_is_refused_and_left_as_it_was(cow, tmp_path):
    """eval moves files it cannot verify aside: a folder that is not a
    dataset (no _job.parquet) but holds files is refused before any work,
    and --compact of it writes nothing there."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "part-00000-1b2c.snappy.parquet").write_bytes(b"someone else's")
    (out / "notes.txt").write_text("keep")
    before = sorted(os.listdir(out))
    with pytest.raises(EvalError, match="not a pmjax eval dataset folder"):
        evaluate([cow], ["orbit:4"], str(out), taus=[1.0], chunk=4, compile_cache=None, progress=False)
    with pytest.raises(EvalError, match="not a pmjax eval dataset folder"):
        pmjax._eval.compact(str(out))
    assert sorted(os.listdir(out)) == before and not os.path.exists(str(out) + ".damaged")


def test_a_killed_writers_temporaries_in_the_dataset_go_a_live_ones_stay(cow, tmp_path):
    out = str(tmp_path / "out")
    evaluate([cow], ["orbit:4"], out, taus=[1.0], chunk=4, compile_cache=None, progress=False)
    # A killed render's temporary folder (its process gone) and a live writer's file.
    dead = os.path.join(out, f".frames{TEMP_MARK}999999999-abc")
    os.mkdir(dead)
    open(os.path.join(dead, "frame_00000.png"), "w").write("x")
    live = os.path.join(out, f".cams.parquet{TEMP_MARK}{os.getpid()}-def.parquet")
    open(live, "w").write("being written")
    evaluate([cow], ["orbit:4"], out, taus=[1.0, 2.0], chunk=4, compile_cache=None, progress=False)
    assert not os.path.exists(dead) and os.path.exists(live)
    assert sorted(rows(out)["tau"].tolist()) == [1.0] * 4 + [2.0] * 4


def _run_cli(args, **kw):
    return subprocess.Popen([sys.executable, "-m", "pmjax", "eval", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, **kw)


@pytest.mark.slow
def test_kill_and_resume_gives_the_uninterrupted_rows(cow, tmp_path):
    job = [cow, "--random", "2000", "--seed", "3", "--tau", "1", "--tau", "3", "--chunk", "50", "-q",
           "--compile-cache", str(tmp_path / "xla")]
    out = str(tmp_path / "killed")
    proc = _run_cli(job + ["-o", out])
    # Kill once a few parts are written, in the middle of the job.
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if len([n for n in os.listdir(out) if n.startswith("part-")] if os.path.isdir(out) else []) >= 5:
            break
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()[0]
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    parts_before = len([n for n in os.listdir(out) if n.startswith("part-")])
    assert 5 <= parts_before < 80
    resumed = _run_cli(job + ["-o", out])
    text = resumed.communicate()[0]
    assert resumed.returncode == 0, text
    assert f"{parts_before} parts found done" in text
    reference = str(tmp_path / "reference")
    evaluate([cow], ["random:2000:3"], reference, taus=[1.0, 3.0], chunk=50, compile_cache=None, progress=False)
    assert_same_rows(rows(out), rows(reference))
    assert sorted(os.listdir(out)) == sorted(os.listdir(reference))  # no temporary files left


@pytest.mark.slow
def test_dask_cluster_gives_the_same_rows_even_when_a_worker_dies(cow, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    reference = str(tmp_path / "reference")
    job = dict(taus=[1.0], chunk=100, compile_cache=str(tmp_path / "xla"), progress=False)
    evaluate([cow], ["random:3000:7"], reference, **job)
    psutil = pytest.importorskip("psutil")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        out = str(tmp_path / "dask")
        killed, stop = [], threading.Event()

        def kill_one_worker():
            # Once parts come back, kill a worker process outright (the
            # cluster's worker processes are children of this process).
            while not stop.is_set():
                if os.path.isdir(out) and len([n for n in os.listdir(out) if n.startswith("part-")]) >= 3:
                    workers = [p for p in psutil.Process().children()
                               if any("spawn_main" in arg for arg in p.cmdline())]
                    os.kill(workers[0].pid, signal.SIGKILL)
                    killed.append(workers[0].pid)
                    return
                time.sleep(0.05)

        killer = threading.Thread(target=kill_one_worker, daemon=True)
        killer.start()
        try:
            summary = evaluate([cow], ["random:3000:7"], out, scheduler=cluster.scheduler_address, **job)
        finally:
            stop.set()
            killer.join()
        assert killed, "no worker was killed: the job ended first"
        assert summary.parts_written == 30
        assert_same_rows(rows(out), rows(reference))


@pytest.mark.slow
def test_one_compilation_serves_every_image_size(cow, tmp_path):
    import jax

    compiles = []

    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    # Start cold: no model kept loaded, no kernel compiled.
    pmjax._eval._LOADED.clear()
    jax.clear_caches()
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        sizes = [(800, 600), (320, 240), (1920, 1080)]
        sets = [pmjax.camera_set("orbit:40", width=w, height=h) for w, h in sizes]
        assert [s.name for s in sets] == ["orbit-40", "orbit-40-320x240", "orbit-40-1920x1080"]
        evaluate([cow], sets[:1], str(tmp_path / "one"), taus=[1.0], compile_cache=None, progress=False)
        first = len(compiles)
        assert first > 0  # the listener sees compilations
        evaluate([cow], sets, str(tmp_path / "three"), taus=[1.0], compile_cache=None, progress=False)
        assert len(compiles) == first  # the other sizes reuse the compiled kernels
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    got = rows(str(tmp_path / "three"))
    pm, data = pmjax.load(cow), pmjax.read_pm(cow)
    v0 = data.vertices[: data.n_original_vertices]
    for k, (w, h) in enumerate(sizes):
        # A smaller image sees less detail: the same cameras, fewer faces.
        expect = pmjax.refine_batch(pm, pmjax.standard_orbit(v0, 40, width=w, height=h), 1.0)["faces"]
        assert np.array_equal(got["faces"][40 * k:40 * (k + 1)], expect)
    assert got["faces"][40:80].sum() < got["faces"][:40].sum() < got["faces"][80:].sum()


def test_path_runs_follow_each_path_in_frame_order():
    """Rows of a table part as paths for the coherent engine: one run per path
    and image size, frames in order, short runs and rows off any path left
    to the batch."""
    from pmjax._eval import MIN_PATH_FRAMES, path_runs

    n = MIN_PATH_FRAMES
    rng = np.random.default_rng(0)
    path_id = np.concatenate([np.full(2 * n, 7), np.full(n, 3), np.full(5, 9)])
    frame = np.concatenate([rng.permutation(2 * n), np.arange(n)[::-1], np.arange(5)])
    width = np.concatenate([np.full(n, 800), np.full(n, 320), np.full(n + 5, 800)])
    rows = len(path_id)
    table = pmjax._camera_table.CameraTable(
        eye=np.zeros((rows, 3)), rotation=np.tile(np.eye(3), (rows, 1, 1)), fov_y=np.ones(rows),
        near=np.ones(rows), far=np.ones(rows), ortho_height=np.ones(rows), width=width.astype(np.int32),
        height=np.full(rows, 600, np.int32), orthographic=np.zeros(rows, bool), path_id=path_id, frame=frame)
    idx = np.arange(rows)
    runs, rest = path_runs(table, idx)
    # Path 7 is split by its image size into two runs of n frames each, then path 3.
    assert sorted(len(r) for r in runs) == [n, n, n]
    for run in runs:
        assert len(set(path_id[run])) == 1 and len(set(width[run])) == 1
        assert np.all(np.diff(frame[run]) > 0)
    assert np.array_equal(rest, np.arange(3 * n, rows))  # path 9: 5 frames
    assert sorted(np.concatenate(runs + [rest]).tolist()) == list(range(rows))
    # A table without paths: everything to the batch.
    no_paths = pmjax._camera_table.CameraTable(**{**table.__dict__, "path_id": None, "frame": None})
    assert path_runs(no_paths, idx)[0] == [] and np.array_equal(path_runs(no_paths, idx)[1], idx)


def test_ctrl_c_right_after_a_part_is_renamed_counts_that_part(cow, tmp_path, monkeypatch):
    """Ctrl-C between a part's rename and the run's count of it: the message
    still counts every part file in the folder, and resuming finds them all."""
    import pmjax._eval as ev

    write = ev._write_part
    calls = []

    def write_then_interrupt(folder, part, table):
        write(folder, part, table)
        calls.append(part.file)
        if len(calls) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(ev, "_write_part", write_then_interrupt)
    out = str(tmp_path / "out")
    with pytest.raises(ev.EvalInterrupted) as info:
        evaluate([cow], ["random:500:1"], out, taus=[1.0], chunk=50, compile_cache=None, progress=False)
    saved = sorted(n for n in os.listdir(out) if n.startswith("part-"))
    assert saved == sorted(calls)
    assert (info.value.parts_saved, info.value.parts_total) == (2, 10)
    assert (info.value.rows_saved, info.value.rows_total) == (100, 500)
    monkeypatch.setattr(ev, "_write_part", write)
    summary = evaluate([cow], ["random:500:1"], out, taus=[1.0], chunk=50, compile_cache=None, progress=False)
    assert (summary.parts_skipped, summary.parts_written) == (2, 8)
