"""Evaluation jobs that grow and move: a folder gains models, camera sets and
values without touching its parts; a part defined otherwise is refused with
the old and new values; models and camera files are known by their content,
so a moved folder of data resumes."""

from __future__ import annotations

import hashlib
import json
import os
import shutil

import pytest

import pmjax
from pmjax._eval import FORMAT_2, JOB_FILE, JOB_KEY, EvalError, _table_sha256, evaluate, read_job

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
ds = pytest.importorskip("pyarrow.dataset")

DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
                 "vertices", "executed"]
JOB = dict(chunk=8, compile_cache=None, progress=False)


def parts(folder):
    return sorted(n for n in os.listdir(folder) if n.startswith("part-"))


def row_set(folder):
    """The folder's rows (deterministic columns) as a sorted list of tuples."""
    table = ds.dataset(folder, format="parquet").to_table()
    return sorted(zip(*(table.column(c).to_pylist() for c in DETERMINISTIC)), key=repr)


def snapshot(folder):
    """Every file of the folder with its bytes."""
    return {n: open(os.path.join(folder, n), "rb").read() for n in sorted(os.listdir(folder)) if n != ".lock"}


@pytest.mark.slow
def test_a_job_grows_by_values_models_and_camera_sets(cow, tmp_path):
    calf = str(tmp_path / "calf.pmz")
    shutil.copy(cow, calf)
    out = str(tmp_path / "out")
    first = evaluate([cow], ["orbit:16"], out, taus=[1.0], **JOB)
    assert (first.parts_written, first.parts_skipped) == (2, 0)
    before = snapshot(out)
    # A new value (given first), a new model and a new camera set: the
    # folder's parts keep their names and bytes, new entries take the next
    # positions in the job's lists.
    grown = evaluate([calf, cow], ["random:8:1", "orbit:16"], out, taus=[2.0, 1.0], **JOB)
    assert (grown.parts_written, grown.parts_skipped, grown.rows) == (2 * 2 * 3 - 2, 2, 2 * 2 * 24)
    after = snapshot(out)
    assert {n: after[n] for n in before if n.startswith("part-")} == {n: b for n, b in before.items()
                                                                       if n.startswith("part-")}
    assert parts(out) == sorted(f"part-m{m:04d}-c{c:04d}-v{v:04d}-{k:07d}.parquet"
                                for m in (0, 1) for v in (0, 1) for c, chunks in ((0, 2), (1, 1))
                                for k in range(chunks))
    job = read_job(out)
    assert job["taus"] == [1.0, 2.0] and job["models"] == [os.path.abspath(cow), os.path.abspath(calf)]
    assert [d["kind"] for d in job["camera_sets"]] == ["orbit", "random"]
    # The rows are those of the same job computed at once.
    reference = str(tmp_path / "reference")
    evaluate([calf, cow], ["random:8:1", "orbit:16"], reference, taus=[2.0, 1.0], **JOB)
    assert row_set(out) == row_set(reference)
    # A command naming part of the job: its parts found done, the folder unchanged.
    again = evaluate([cow], ["orbit:16"], out, taus=[1.0], **JOB)
    assert (again.parts_written, again.parts_skipped, again.rows) == (0, 2, 16)
    assert snapshot(out) == after


def test_a_part_defined_otherwise_is_refused_naming_old_and_new(cow, tmp_path):
    views = tmp_path / "views.parquet"
    data = pmjax.read_pm(cow)
    table = pmjax.table_from_cameras(pmjax.random_views(data.vertices[: data.n_original_vertices], 8, seed=1))
    pmjax.write_camera_table(table, views)
    out = str(tmp_path / "out")
    evaluate([cow], ["orbit:8", str(views)], out, taus=[1.0], **JOB)
    before = snapshot(out)
    head = f"{out} holds parts that this command defines otherwise \\("
    tail = ("\\); a job can gain models, camera sets and values, but its parts cannot change: use another folder, "
            "or delete this one to start over")

    def refused(why, models=(cow,), sets=("orbit:8", str(views)), **kw):
        job = dict(JOB, taus=[1.0])
        job.update(kw)
        with pytest.raises(EvalError, match=head + why + tail):
            evaluate(list(models), list(sets), out, **job)
        assert snapshot(out) == before

    refused("chunk: 8 there, 16 here", chunk=16)
    refused("method: 'auto' there, 'dense' here; batch_chunk: 256 there, 64 here", method="dense", batch_chunk=64)
    refused(r"tests: \{'frustum': True, 'orientation': True, 'screen': True\} there, "
            r"\{'frustum': False, 'orientation': True, 'screen': True\} here",
            tests=pmjax.Tests(frustum=False, orientation=True, screen=True))
    refused(r"values: tolerances \[1.0\] there, budgets \[500\] here", taus=[], budgets=[500])
    # A model of the same name with other content.
    changed = tmp_path / "changed" / "cow.pmz"
    changed.parent.mkdir()
    changed.write_bytes(open(cow, "rb").read() + b"\0")
    old_sha = hashlib.sha256(open(cow, "rb").read()).hexdigest()[:12]
    new_sha = hashlib.sha256(changed.read_bytes()).hexdigest()[:12]
    refused(f"model 'cow': content SHA-256 {old_sha} there \\(then at {cow}\\), {new_sha} here \\({changed}; "
            "its content changed\\)", models=[str(changed)])
    # A camera file of the same name with other content.
    other = tmp_path / "other" / "views.parquet"
    other.parent.mkdir()
    pmjax.write_camera_table(pmjax.table_from_cameras(pmjax.random_views(data.vertices, 8, seed=2)), other)
    old_sha = hashlib.sha256(views.read_bytes()).hexdigest()[:12]
    new_sha = hashlib.sha256(other.read_bytes()).hexdigest()[:12]
    refused(f"camera set 'views.parquet': sha256 '{old_sha}' there, '{new_sha}' here", sets=["orbit:8", str(other)])
    # Values given twice are refused before any work.
    with pytest.raises(EvalError, match="tau 1.0 is given twice"):
        evaluate([cow], ["orbit:8"], out, taus=[1.0, 2.0, 1.0], **JOB)


def test_a_moved_data_folder_resumes(cow, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    shutil.copy(cow, data / "cow.pmz")
    pm = pmjax.read_pm(cow)
    views = pmjax.table_from_cameras(pmjax.random_views(pm.vertices[: pm.n_original_vertices], 12, seed=3))
    pmjax.write_camera_table(views, data / "views.npz")
    out = str(tmp_path / "out")
    job = dict(JOB, taus=[1.0], max_parts=3)
    first = evaluate([str(data / "cow.pmz")], ["orbit:16", str(data / "views.npz")], out, **job)
    assert first.parts_written == 3
    moved = tmp_path / "moved"
    os.rename(data, moved)
    job.pop("max_parts")
    rest = evaluate([str(moved / "cow.pmz")], ["orbit:16", str(moved / "views.npz")], out, **job)
    assert (rest.parts_written, rest.parts_skipped) == (1, 3)
    # The description now says where the files were seen last.
    described = read_job(out)
    assert described["models"] == [str(moved / "cow.pmz")]
    assert described["camera_sets"][1]["path"] == str(moved / "views.npz")
    reference = str(tmp_path / "reference")
    evaluate([cow], ["orbit:16", str(moved / "views.npz")], reference, **job)
    assert row_set(out) == row_set(reference)


def test_a_folder_of_format_2_resumes_and_grows(cow, tmp_path):
    """A folder whose description names models by path alone, and whose
    parts carry the checksum of that description, resumes: its parts are
    kept, and the job can grow."""
    out = str(tmp_path / "out")
    evaluate([cow], ["orbit:16"], out, taus=[1.0], **JOB)
    reference = row_set(out)
    # The folder as that format wrote it.
    job = read_job(out)
    old = {k: v for k, v in job.items() if k != "model_sha256"}
    old["format"] = FORMAT_2
    sha = hashlib.sha256(json.dumps(old, sort_keys=True).encode()).hexdigest()
    schema = pq.read_schema(os.path.join(out, JOB_FILE))
    pq.write_table(schema.empty_table().replace_schema_metadata({JOB_KEY: json.dumps(old)}),
                   os.path.join(out, JOB_FILE))
    for name in parts(out):
        table = pq.read_table(os.path.join(out, name))
        info = {k: v for k, v in json.loads(table.schema.metadata[b"pmjax"]).items() if k != "sha256"}
        info["job"] = sha
        info["sha256"] = _table_sha256(table, info)
        pq.write_table(table.replace_schema_metadata({"pmjax": json.dumps(info)}), os.path.join(out, name))
    before = snapshot(out)
    grown = evaluate([cow], ["orbit:16"], out, taus=[1.0, 3.0], **JOB)
    assert (grown.parts_written, grown.parts_skipped) == (2, 2)
    assert {n: b for n, b in snapshot(out).items() if n in before and n.startswith("part-")} == \
        {n: b for n, b in before.items() if n.startswith("part-")}
    assert read_job(out)["legacy_jobs"] == [sha]
    fresh = str(tmp_path / "fresh")
    evaluate([cow], ["orbit:16"], fresh, taus=[1.0, 3.0], **JOB)
    assert row_set(out) == row_set(fresh) and set(reference) < set(row_set(out))
