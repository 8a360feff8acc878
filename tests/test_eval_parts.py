"""Evaluation parts: a job of any size starts at once and resumes; part files
are verified when a folder is reopened, and a damaged one is set aside and
computed again."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from pmjax._eval import (EvalError, _model_parts, _part, _part_named, _table_sha256, _verify_part, damaged_folder,
                         evaluate)

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
ds = pytest.importorskip("pyarrow.dataset")

DETERMINISTIC = ["model", "camera_set", "camera", "path_id", "frame", "budget", "budget_met", "tau", "faces",
                 "vertices", "executed"]
HUGE = 10 ** 12
# Generous limit against a hang; a job that plans its parts lazily takes seconds.
HANG = 300


def rows(folder, columns=DETERMINISTIC):
    table = ds.dataset(folder, format="parquet").to_table()
    return {c: table.column(c).to_pylist() for c in columns}


def parts(folder):
    return sorted(n for n in os.listdir(folder) if n.startswith("part-"))


def test_part_names_sort_as_rows_for_any_job_size():
    # A set of 10^12 cameras in chunks of 16 has 6.25e10 chunks: 11 digits.
    counts, chunk = [HUGE], 16
    a, b = _part(0, 0, 0, 9_999_999, counts, chunk), _part(0, 0, 0, 10_000_000, counts, chunk)
    assert a.file == "part-m0000-c0000-v0000-00009999999.parquet" < b.file
    assert (b.lo, b.hi) == (160_000_000, 160_000_016)
    last = _part(0, 0, 0, HUGE // chunk - 1, counts, chunk)
    assert last.file == "part-m0000-c0000-v0000-62499999999.parquet" and last.hi == HUGE
    # Up to 10^7 chunks the names keep their 7 digits (folders written before stay resumable).
    assert _part(0, 0, 0, 3, [100], 8).file == "part-m0000-c0000-v0000-0000003.parquet"
    # Names map back to their parts; names of no part of the job map to None.
    assert _part_named(b.file, counts, 1, 1, chunk) == b
    assert _part_named("part-m0000-c0000-v0000-0000003.parquet", counts, 1, 1, chunk) is None  # too few digits
    assert _part_named("part-m0000-c0000-v0000-0000013.parquet", [100], 1, 1, 8) is None  # past the last chunk
    assert _part_named("part-m0001-c0000-v0000-0000003.parquet", [100], 1, 1, 8) is None  # no model 1
    # Parts are made as they are asked for.
    first = next(_model_parts(0, [0], [0, 1], counts, chunk))
    assert (first.lo, first.hi, first.file) == (0, 16, "part-m0000-c0000-v0000-00000000000.parquet")


def test_max_parts_is_checked(cow, tmp_path):
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(EvalError, match=rf"max_parts must be a whole number >= 1 or None, not {bad!r}"):
            evaluate([cow], ["orbit:4"], str(tmp_path / "never"), taus=[1.0], compile_cache=None, progress=False,
                     max_parts=bad)
    assert not (tmp_path / "never").exists()


def _in_thread(fn):
    """``fn()``'s result, failing if it runs past :data:`HANG` seconds."""
    out = {}

    def run():
        try:
            out["value"] = fn()
        except BaseException as exc:  # re-raised in the test
            out["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(HANG)
    assert not thread.is_alive(), f"still running after {HANG} s"
    if "error" in out:
        raise out["error"]
    return out["value"]


def test_a_huge_job_writes_its_first_parts_at_once_and_resumes(cow, tmp_path):
    out = str(tmp_path / "huge")
    job = dict(taus=[1.0], chunk=16, compile_cache=None, progress=False)
    first = _in_thread(lambda: evaluate([cow], [f"random:{HUGE}:3"], out, max_parts=2, **job))
    assert (first.parts_written, first.parts_skipped, first.cameras, first.rows) == (2, 0, 32, 32)
    assert parts(out) == [f"part-m0000-c0000-v0000-{k:011d}.parquet" for k in range(2)]
    again = _in_thread(lambda: evaluate([cow], [f"random:{HUGE}:3"], out, max_parts=1, **job))
    assert (again.parts_written, again.parts_skipped, again.rows) == (1, 2, 48)
    # A random view's camera depends on its index and the seed alone: the
    # first 48 rows are those of a 48-view job.
    reference = str(tmp_path / "reference")
    evaluate([cow], ["random:48:3"], reference, **job)
    got, want = rows(out), rows(reference)
    assert set(got.pop("camera_set")) == {f"random-{HUGE}-seed3"}
    want.pop("camera_set")
    assert got == want


@pytest.mark.slow
def test_a_killed_huge_cli_job_resumes(cow, tmp_path):
    out = tmp_path / "huge"
    log = open(tmp_path / "log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "pmjax", "eval", cow, "--random", str(HUGE), "--chunk", "16",
                             "--no-compile-cache", "-o", str(out)], stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.time() + HANG
        while time.time() < deadline and proc.poll() is None and not (out.is_dir() and parts(out)):
            time.sleep(0.05)
        assert proc.poll() is None, open(tmp_path / "log").read()
        assert parts(out), f"no part written after {HANG} s"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    before = parts(out)
    assert before[0] == "part-m0000-c0000-v0000-00000000000.parquet"
    summary = _in_thread(lambda: evaluate([cow], [f"random:{HUGE}"], str(out), taus=[1.0], chunk=16,
                                          compile_cache=None, progress=False, max_parts=1))
    assert (summary.parts_skipped, summary.parts_written) == (len(before), 1)
    assert parts(out) == [f"part-m0000-c0000-v0000-{k:011d}.parquet" for k in range(len(before) + 1)]
    got = rows(str(out), ["camera"])["camera"]
    assert got == list(range(16 * (len(before) + 1)))


def _signed(table, info):
    """``info`` with the checksum of ``table`` and ``info``."""
    info = {k: v for k, v in info.items() if k != "sha256"}
    return dict(info, sha256=_table_sha256(table, info))


def _rewrite(path, table, info):
    """Write ``table`` to the part file ``path`` with the pmjax record ``info``."""
    pq.write_table(table.replace_schema_metadata({"pmjax": json.dumps(info)}), path)


def test_damaged_parts_are_set_aside_and_computed_again(cow, tmp_path, capsys):
    job = dict(taus=[1.0], chunk=8, compile_cache=None, progress=False)
    reference, out = str(tmp_path / "reference"), str(tmp_path / "out")
    evaluate([cow], ["orbit:56"], reference, **job)
    evaluate([cow], ["orbit:56"], out, **job)
    names = parts(out)
    assert len(names) == 7
    path = [os.path.join(out, n) for n in names]
    # 1: truncated. 2: a byte flipped among the camera column's values (the
    # end of its dictionary page, just before its data page).
    data = open(path[1], "rb").read()
    open(path[1], "wb").write(data[: len(data) // 2])
    data = bytearray(open(path[2], "rb").read())
    camera = pq.ParquetFile(path[2]).metadata.row_group(0).column(2)
    assert camera.path_in_schema == "camera" and camera.has_dictionary_page
    data[camera.data_page_offset - 4] ^= 0x5A
    open(path[2], "wb").write(bytes(data))
    # 3: a value changed in a file that still decodes (its record kept).
    table = pq.read_table(path[3])
    info = json.loads(table.schema.metadata[b"pmjax"])
    faces = table.column("faces").to_numpy().copy()
    faces[5] += 1
    _rewrite(path[3], table.set_column(table.schema.get_field_index("faces"), "faces", pa.array(faces)), info)
    # 4: rows of another part (record and checksum consistent, but not this part's rows).
    other = pq.read_table(path[0])
    _rewrite(path[4], other, json.loads(other.schema.metadata[b"pmjax"]))
    # 5: written by another job. 6: kept. A stray name past the last chunk.
    table = pq.read_table(path[5])
    _rewrite(path[5], table, _signed(table, dict(json.loads(table.schema.metadata[b"pmjax"]), job="0" * 64)))
    stray = os.path.join(out, "part-m0000-c0000-v0000-0000099.parquet")
    open(stray, "wb").write(open(path[6], "rb").read())
    capsys.readouterr()
    summary = evaluate([cow], ["orbit:56"], out, **job)
    err = capsys.readouterr().err
    assert (summary.parts_skipped, summary.parts_written, summary.rows) == (2, 5, 56)
    damaged = damaged_folder(out)
    lines = [line for line in err.splitlines() if line.startswith("pmjax eval: ")]
    assert len(lines) == 6, err
    why = {}
    for line in lines:
        name = line.split(": ")[1]
        assert line.endswith(f"; moved to {os.path.join(damaged, os.path.basename(name))}, the part is computed again")
        why[os.path.basename(name)] = line[len(f"pmjax eval: {name}: "):line.index("; moved to")]
    assert why[names[1]].startswith("unreadable (")
    assert why[names[2]].startswith(("unreadable (", "the statistics of column 'camera' give 16..")), why
    assert why[names[3]] == "its content does not match its checksum (damaged data)"
    assert why[names[4]] == f"holds the rows of {names[0]}, another part"
    assert why[names[5]] == "was written by another job"
    assert why[os.path.basename(stray)].startswith("is not a part of this job")
    assert sorted(os.listdir(damaged)) == sorted(names[1:6] + [os.path.basename(stray)])
    # The folder reads as the uninterrupted job; the set-aside files are not read.
    assert rows(out) == rows(reference)
    assert parts(out) == names
    # Reopened again: every part verifies.
    capsys.readouterr()
    again = evaluate([cow], ["orbit:56"], out, **job)
    assert (again.parts_skipped, again.parts_written) == (7, 0) and capsys.readouterr().err == ""


@pytest.mark.slow
def test_no_flipped_byte_is_taken_with_other_content(cow, tmp_path):
    """Every single-byte change to a part file is refused, or leaves the rows,
    the record and the footer statistics (readers skip files by them) as
    they were."""
    out = str(tmp_path / "out")
    evaluate([cow], ["orbit:8"], out, taus=[1.0], chunk=8, compile_cache=None, progress=False)
    name = parts(out)[0]
    data = open(os.path.join(out, name), "rb").read()
    table = pq.read_table(os.path.join(out, name))
    job = json.loads(table.schema.metadata[b"pmjax"])["job"]
    part = _part(0, 0, 0, 0, [8], 8)

    def statistics(path):
        md = pq.ParquetFile(path).metadata
        return [str(md.row_group(0).column(i).statistics) for i in range(md.num_columns)]

    stats = statistics(os.path.join(out, name))
    flipped = str(tmp_path / "flipped.parquet")
    refused = 0
    for pos in range(0, len(data), 2):
        damaged = bytearray(data)
        damaged[pos] ^= 0x10
        open(flipped, "wb").write(bytes(damaged))
        problem, _ = _verify_part(flipped, part, job)
        if problem is None:
            back = pq.read_table(flipped)
            assert back.equals(table) and back.schema.metadata == table.schema.metadata, pos
            assert statistics(flipped) == stats, pos
        refused += problem is not None
    assert refused > len(data) // 4


def test_a_part_of_a_changed_model_is_refused(cow, tmp_path):
    job = dict(taus=[1.0], chunk=8, compile_cache=None, progress=False)
    out = str(tmp_path / "out")
    evaluate([cow], ["orbit:16"], out, **job)
    path = os.path.join(out, parts(out)[1])
    table = pq.read_table(path)
    info = json.loads(table.schema.metadata[b"pmjax"])
    _rewrite(path, table, _signed(table, dict(info, model_sha256="f" * 64)))
    with pytest.raises(EvalError, match=f"{path} was computed from another version of {cow}"):
        evaluate([cow], ["orbit:16"], out, **job)


def test_parts_written_without_a_checksum_are_read_and_kept(cow, tmp_path, capsys):
    job = dict(taus=[1.0], chunk=8, compile_cache=None, progress=False)
    out = str(tmp_path / "out")
    evaluate([cow], ["orbit:16"], out, **job)
    path = os.path.join(out, parts(out)[0])
    table = pq.read_table(path)
    info = json.loads(table.schema.metadata[b"pmjax"])
    _rewrite(path, table, dict(job=info["job"], model_sha256=info["model_sha256"]))
    capsys.readouterr()
    summary = evaluate([cow], ["orbit:16"], out, **job)
    assert (summary.parts_skipped, summary.parts_written) == (2, 0) and capsys.readouterr().err == ""
    # Without a checksum, the rows are still checked: the camera column must be the part's.
    cameras = table.column("camera").to_numpy() + 8
    _rewrite(path, table.set_column(table.schema.get_field_index("camera"), "camera", pa.array(cameras)),
             dict(job=info["job"], model_sha256=info["model_sha256"]))
    summary = evaluate([cow], ["orbit:16"], out, **job)
    assert (summary.parts_skipped, summary.parts_written) == (1, 1)
    assert f"{path}: its camera column is not 0..7; moved to" in capsys.readouterr().err
