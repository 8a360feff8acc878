"""Compacting an evaluation dataset: the part files rewritten into few large
files hold the same rows in the same order for every reader, the folder
still resumes (and grows), damaged compacted files are set aside and their
parts computed again, and an interrupted compaction leaves no duplicate row."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

import pmjax
from pmjax._eval import EvalError, compact, damaged_folder, evaluate

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
ds = pytest.importorskip("pyarrow.dataset")

DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
                 "vertices", "executed"]
JOB = dict(chunk=4, compile_cache=None, progress=False)
SETS = ["orbit:20", "random:12:1"]


@pytest.fixture(scope="module")
def models(built, tmp_path_factory):
    folder = tmp_path_factory.mktemp("models")
    cow = str(folder / "cow.pmz")
    pmjax.save_pm(built("cow.ply"), cow)
    calf = str(folder / "calf.pmz")
    shutil.copy(cow, calf)
    return [cow, calf]


def files(folder):
    return sorted(n for n in os.listdir(folder) if n.startswith("part-"))


def whole(folder):
    return pq.read_table(folder)


def row_set(folder):
    table = ds.dataset(folder, format="parquet").to_table()
    return sorted(zip(*(table.column(c).to_pylist() for c in DETERMINISTIC)), key=repr)


def test_a_compacted_folder_reads_the_same_rows_and_resumes(models, tmp_path, capsys):
    out = str(tmp_path / "out")
    evaluate(models, SETS, out, taus=[1.0, 4.0], **JOB)
    before = whole(out)
    assert len(files(out)) == 32 and before.num_rows == 128
    # Parts of 4 rows: files of at most 50 rows hold 12 parts, in row groups of 16 rows.
    summary = compact(out, rows_per_file=50, row_group_rows=16)
    assert (summary.parts, summary.rows, summary.files_before, summary.files_after) == (32, 128, 32, 3)
    assert files(out) == ["part-m0000-c0000-v0000-0000000-to-m0000-c0001-v0000-0000001.parquet",
                          "part-m0000-c0001-v0000-0000002-to-m0001-c0000-v0001-0000002.parquet",
                          "part-m0001-c0000-v0001-0000003-to-m0001-c0001-v0001-0000002.parquet"]
    assert [pq.ParquetFile(os.path.join(out, n)).metadata.num_row_groups for n in files(out)] == [3, 3, 2]
    # Every column (times too: rows are copied) in the same order.
    assert whole(out).equals(before)
    assert pq.read_table(out).group_by(["model", "tau"]).aggregate([("faces", "count")]).num_rows == 4
    # The folder resumes from the compacted files: nothing computed, nothing reported.
    capsys.readouterr()
    again = evaluate(models, SETS, out, taus=[1.0, 4.0], **JOB)
    assert (again.parts_skipped, again.parts_written, again.rows) == (32, 0, 128)
    assert capsys.readouterr().err == "" and len(files(out)) == 3
    # Compacting again changes nothing.
    assert compact(out, rows_per_file=50, row_group_rows=16).files_after == 3 and whole(out).equals(before)


def test_every_reader_reads_a_compacted_folder_by_name(models, tmp_path):
    out = str(tmp_path / "out")
    evaluate(models, SETS, out, taus=[1.0, 4.0], **JOB)
    compact(out, rows_per_file=50, row_group_rows=16)
    reference = whole(out)
    want = {c: reference.column(c).to_pylist() for c in DETERMINISTIC}
    assert len(want["camera"]) == 128
    pd = _optional("pandas")
    if pd is not None:
        frame = pd.read_parquet(out)
        assert {c: [None if pd.isna(x) else x for x in frame[c].tolist()] for c in DETERMINISTIC} == want
    pl = _optional("polars")
    if pl is not None:
        frame = pl.read_parquet(out)
        assert {c: frame[c].to_list() for c in DETERMINISTIC} == want
    duckdb = _optional("duckdb")
    if duckdb is not None:
        got = duckdb.sql(f"select {', '.join(DETERMINISTIC)} from read_parquet('{out}', filename=true, "
                         "file_row_number=true) order by filename, file_row_number").fetchall()
        assert {c: [r[i] for r in got] for i, c in enumerate(DETERMINISTIC)} == want


def _optional(name):
    try:
        return __import__(name)
    except ImportError:
        return None


def test_a_compacted_folder_grows_and_compacts_again(models, tmp_path):
    out = str(tmp_path / "out")
    # Unfinished: 10 of the 16 parts of one model, compacted.
    evaluate(models[:1], SETS, out, taus=[1.0, 4.0], max_parts=10, **JOB)
    compact(out, rows_per_file=1000)
    assert files(out) == ["part-m0000-c0000-v0000-0000000-to-m0000-c0000-v0001-0000004.parquet"]
    # The job finishes and grows (a value between the others, a model): new parts as part files.
    summary = evaluate(models, SETS, out, taus=[1.0, 4.0, 2.0], **JOB)
    assert (summary.parts_skipped, summary.parts_written) == (10, 48 - 10)
    reference = str(tmp_path / "reference")
    evaluate(models, SETS, reference, taus=[1.0, 4.0, 2.0], **JOB)
    assert row_set(out) == row_set(reference)
    # Compacting again restores the job's row order (the new value's parts
    # come before the second camera set's): the rows of one uninterrupted run.
    compact(out, rows_per_file=1000)
    assert files(out) == ["part-m0000-c0000-v0000-0000000-to-m0001-c0001-v0002-0000002.parquet"]
    got, want = whole(out), whole(reference)
    assert got.select(DETERMINISTIC).equals(want.select(DETERMINISTIC))
    assert evaluate(models, SETS, out, taus=[1.0, 4.0, 2.0], **JOB).parts_written == 0
    # Smaller files split a compacted one (parts of 4 rows, files of 8); then
    # files of 47 parts merge them again, the last part alone as its own file.
    for rows_per_file, count in ((8, 24), (188, 2)):
        compact(out, rows_per_file=rows_per_file)
        assert len(files(out)) == count
        assert whole(out).select(DETERMINISTIC).equals(want.select(DETERMINISTIC))
        assert evaluate(models, SETS, out, taus=[1.0, 4.0, 2.0], **JOB).parts_written == 0
    assert files(out)[1] == "part-m0001-c0001-v0002-0000002.parquet"


def test_a_damaged_compacted_file_is_set_aside_and_its_parts_computed_again(models, tmp_path, capsys):
    out = str(tmp_path / "out")
    evaluate(models[:1], SETS, out, taus=[1.0], **JOB)
    reference = whole(out)
    compact(out, rows_per_file=20)
    names = files(out)
    assert len(names) == 2
    # A value changed in a file that still decodes, its record kept.
    path = os.path.join(out, names[0])
    table = pq.read_table(path)
    faces = table.column("faces").to_numpy().copy()
    faces[7] += 1
    pq.write_table(table.set_column(table.schema.get_field_index("faces"), "faces", pa.array(faces)), path)
    capsys.readouterr()
    summary = evaluate(models[:1], SETS, out, taus=[1.0], **JOB)
    err = capsys.readouterr().err
    assert (summary.parts_skipped, summary.parts_written) == (3, 5)
    aside = os.path.join(damaged_folder(out), names[0])
    assert (f"pmjax eval: {path}: the rows of part-m0000-c0000-v0000-0000001.parquet do not match their checksum "
            f"(damaged data); moved to {aside}, its parts are computed again") in err
    assert whole(out).select(DETERMINISTIC).equals(reference.select(DETERMINISTIC))


def test_an_interrupted_compaction_leaves_no_duplicate_row(models, tmp_path, capsys):
    out = str(tmp_path / "out")
    evaluate(models[:1], SETS, out, taus=[1.0], **JOB)
    reference = whole(out)
    singles = {n: open(os.path.join(out, n), "rb").read() for n in files(out)}
    compact(out, rows_per_file=1000)
    (merged,) = files(out)
    # As if the process died after writing the compacted file, before removing its sources.
    for name, data in singles.items():
        open(os.path.join(out, name), "wb").write(data)
    capsys.readouterr()
    summary = evaluate(models[:1], SETS, out, taus=[1.0], **JOB)
    assert (summary.parts_skipped, summary.parts_written) == (8, 0)
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 8 and all(line.endswith(f"its rows are in {merged} (left over from an interrupted "
                                               "compaction); removed") for line in err)
    assert files(out) == [merged] and whole(out).equals(reference)


@pytest.mark.slow
def test_compact_arguments_and_the_command_line(models, tmp_path):
    for bad in (0, 1.5, True):
        with pytest.raises(EvalError, match=f"rows_per_file must be a whole number >= 1, not {bad!r}"):
            compact(str(tmp_path), rows_per_file=bad)
    with pytest.raises(EvalError, match=f"{tmp_path / 'none'}: no such folder"):
        compact(str(tmp_path / "none"))
    with pytest.raises(EvalError, match=f"{tmp_path}: no _job.parquet, not a pmjax eval dataset folder"):
        compact(str(tmp_path))
    out = str(tmp_path / "out")
    evaluate(models[:1], ["orbit:12"], out, taus=[1.0], **JOB)
    reference = whole(out)
    r = subprocess.run([sys.executable, "-m", "pmjax", "eval", "--compact", out], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"{out}: 12 rows in 3 parts; 3 files compacted into 1 (")
    assert whole(out).equals(reference)
    r = subprocess.run([sys.executable, "-m", "pmjax", "eval", models[0], "--compact", out], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 2 and "--compact takes the dataset folder alone: give no models and no -o" in r.stderr
    r = subprocess.run([sys.executable, "-m", "pmjax", "eval", models[0]], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "give the models (.pmz files) and -o FOLDER, or --compact FOLDER" in r.stderr
    assert json.loads(pq.read_schema(os.path.join(out, files(out)[0])).metadata[b"pmjax"])["compacted"][0]["part"] \
        == "part-m0000-c0000-v0000-0000000.parquet"
