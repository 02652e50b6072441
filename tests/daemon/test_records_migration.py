"""Schema 3's additions (run labels and notes) on a records file the daemon wrote at 7f3fa01.

The fixture (tests/daemon/fixtures/records_7f3fa01.sqlite, made by make_records_7f3fa01.py beside
it) is the old daemon's file: three runs, a switch stroke, their events, no `run_aggregates`. The new
writer opens it: every old row stays as it was, the runs gain `label` and `notes` (and their index),
and the version stays 3, so the readers of 7f3fa01 (its `RecordsFile` and its read-only
`RecordStore`, run from that commit's own source as a subprocess) still read it, the new run too.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import subprocess
import sys
import sysconfig
import tarfile
from pathlib import Path
from typing import Any

import pytest

from usmswitch.client import RecordsFile
from usmswitch.daemon.records import RecordStore
from usmswitch.protocol.record import CycleRecord, RunRecord

FIXTURE = Path(__file__).parent / "fixtures" / "records_7f3fa01.sqlite"
OLD_COMMIT = "7f3fa01"
#: What the fixture holds (make_records_7f3fa01.py): runs 1-3, and strokes 1..137 (41 a switch).
OLD_RUNS = 3
OLD_STROKES = 137
NOTES = "written by the new code\nover two lines, with a µ and a 'quote'"


def _dump(path: Path) -> dict[str, Any]:
    """Every row of the old tables, in the old columns, as plain SQLite reads them."""
    db = sqlite3.connect(path)
    try:
        out: dict[str, Any] = {}
        for table, key in (("cycles", "cycle"), ("runs", "run_id"), ("events", "id"), ("meta", "key")):
            cols = [r[1] for r in db.execute(f"PRAGMA table_info({table})") if r[1] not in ("label", "notes")]
            quoted = ", ".join(f'"{c}"' for c in cols)
            out[table] = db.execute(f"SELECT {quoted} FROM {table} ORDER BY {key}").fetchall()
        return out
    finally:
        db.close()


def _columns(path: Path, table: str) -> list[str]:
    db = sqlite3.connect(path)
    try:
        return [r[1] for r in db.execute(f"PRAGMA table_info({table})")]
    finally:
        db.close()


def _migrated(tmp: Path) -> Path:
    """The fixture opened by the new writer, with a fourth run written by it (labelled, with notes)."""
    tmp.mkdir(exist_ok=True)
    path = tmp / "records.sqlite"
    shutil.copyfile(FIXTURE, path)
    store = RecordStore(path)
    old = store.history(3, run_id=2)  # strokes of an old run, renumbered as the new run's
    run = RunRecord(
        run_id=4,
        kind="cycling",
        first_cycle=OLD_STROKES + 1,
        started_wall_ns=old[0].wall_ns,
        settings={"period_ns": 30_000_000, "count": 3},
        label="migration-test",
        notes=NOTES,
    )
    store.submit_run(run)
    for i, rec in enumerate(old):
        fields = rec.to_dict()
        fields.update(cycle=OLD_STROKES + 1 + i, run_id=4)
        store.submit(CycleRecord.from_row(fields))
    run.last_cycle, run.ended_wall_ns, run.end_reason = OLD_STROKES + 3, old[-1].wall_ns, "done"
    store.submit_run(run)
    assert store.close()
    return path


def test_the_old_file_gains_labels_and_notes_and_keeps_every_row(tmp_path: Path) -> None:
    path = tmp_path / "records.sqlite"
    shutil.copyfile(FIXTURE, path)
    before = _dump(path)
    assert "label" not in _columns(path, "runs")
    assert len(before["runs"]) == OLD_RUNS and len(before["cycles"]) == OLD_STROKES

    RecordStore(path).close()
    assert _columns(path, "runs")[-2:] == ["label", "notes"]
    db = sqlite3.connect(path)
    indexes = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'index'")}
    version = db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0]
    aggregates = db.execute("SELECT count(*) FROM run_aggregates").fetchone()[0]
    db.close()
    assert "runs_label" in indexes
    assert version == "3"  # an addition, not a new version: readers of 3 read it
    assert aggregates == OLD_RUNS  # built at the open, as for any file from before them
    assert _dump(path) == before  # every old row, every old column, as it was

    RecordStore(path).close()  # a second open finds nothing to add
    assert _dump(path) == before

    migrated = _migrated(tmp_path / "again")
    runs = RecordsFile(migrated).runs()
    assert [(r["run_id"], r["label"], r["notes"]) for r in runs] == [
        (1, None, None),
        (2, None, None),
        (3, None, None),
        (4, "migration-test", NOTES),
    ]
    store = RecordStore(migrated, readonly=True)
    assert store.run(4).label == "migration-test" and store.run(1).notes is None
    store.close()


def test_the_new_readers_read_the_old_file_as_it_is(tmp_path: Path) -> None:
    """Read-only, the new code reads the unmigrated file (no label or notes: None) and changes nothing."""
    path = tmp_path / "records.sqlite"
    shutil.copyfile(FIXTURE, path)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    with RecordsFile(path) as f:
        runs = [(r["run_id"], r["label"], r["notes"]) for r in f.runs()]
        assert runs == [(i, None, None) for i in (1, 2, 3)]
        assert len(f) == OLD_STROKES
    store = RecordStore(path, readonly=True)
    assert [(r.run_id, r.label) for r in store.runs()] == [(1, None), (2, None), (3, None)]
    store.close()
    assert hashlib.sha256(path.read_bytes()).hexdigest() == digest
    assert "label" not in _columns(path, "runs")


# What 7f3fa01's readers say of a file: run as a subprocess from that commit's own source.
_OLD_READ = """
import json, sys
from usmswitch.client import records
from usmswitch.daemon.records import RecordStore
assert records.__file__.startswith(sys.argv[1]), records.__file__  # the old code, not this checkout's
with records.RecordsFile(sys.argv[2]) as f:
    file_runs = f.runs()
    strokes = [r["cycle"] for r in f.records()]
    run4 = [r["cycle"] for r in f.records(run=4)]
    errors = [r["error_ns"] for r in f.records()]
store = RecordStore(sys.argv[2], readonly=True)
store_runs = [r.to_dict() for r in store.runs(100)]
history = [r.cycle for r in store.history(5, run_id=4)]
store.close()
print(json.dumps({"file_runs": file_runs, "store_runs": store_runs, "strokes": strokes,
                  "run4": run4, "errors": errors, "history": history}))
"""


def _old_source(tmp: Path, repo_root: Path) -> Path:
    """7f3fa01's packages, laid out as the installed `usmswitch` package (from git, not a worktree)."""
    have = subprocess.run(
        ["git", "-C", str(repo_root), "cat-file", "-e", f"{OLD_COMMIT}^{{commit}}"], capture_output=True
    )
    if have.returncode != 0:
        why = f"commit {OLD_COMMIT} is not in this clone (a shallow one?): its readers cannot be run"
        if os.environ.get("CI") == "true":
            pytest.fail(why, pytrace=False)
        pytest.skip(why)
    parts = ["usmswitch", "client", "protocol", "fleet", "daemon", "runtime"]
    archive = subprocess.run(
        ["git", "-C", str(repo_root), "archive", "--format=tar", OLD_COMMIT, *parts],
        capture_output=True,
        check=True,
    ).stdout
    src = tmp / "old-src"
    src.mkdir()
    tar = tmp / "old.tar"
    tar.write_bytes(archive)
    with tarfile.open(tar) as t:
        t.extractall(src, filter="data")
    root = tmp / "old-pkg"
    (root / "usmswitch").mkdir(parents=True)
    shutil.copyfile(src / "usmswitch" / "__init__.py", root / "usmswitch" / "__init__.py")
    for part in parts[1:]:
        (root / "usmswitch" / part).symlink_to(src / part)
    return root


def test_the_readers_of_7f3fa01_still_read_the_migrated_file(tmp_path: Path, repo_root: Path) -> None:
    migrated = _migrated(tmp_path)
    old = _old_source(tmp_path, repo_root)
    # -S: no site, so no .pth and not this checkout's editable install; the venv's libraries by path.
    libs = sysconfig.get_paths()["purelib"]
    code = f"import sys; sys.path[:0] = [{str(old)!r}]; sys.path.append({libs!r})\n"
    done = subprocess.run(
        [sys.executable, "-S", "-c", code + _OLD_READ, str(old / "usmswitch"), str(migrated)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    said = json.loads(done.stdout)

    with RecordsFile(migrated) as f:
        runs = f.runs()
        strokes = [r["cycle"] for r in f.records()]
        errors = [r["error_ns"] for r in f.records()]
    without_new = [{k: v for k, v in r.items() if k not in ("label", "notes")} for r in runs]
    assert said["file_runs"] == without_new  # every run, the new one too, as the new code reads it
    assert said["store_runs"] == without_new
    assert said["strokes"] == strokes == list(range(1, OLD_STROKES + 4))
    assert said["errors"] == errors
    assert said["run4"] == said["history"] == [OLD_STROKES + 1, OLD_STROKES + 2, OLD_STROKES + 3]


def test_an_archive_from_before_the_additions_takes_runs_that_have_them(tmp_path: Path) -> None:
    """Retention copies a run's row with `SELECT *`: an archive the old daemon made (its runs
    without label and notes) gains the columns before the first run moves in."""
    import time

    from usmswitch.daemon.retention import ARCHIVE_FILE, Retention, RetentionPolicy

    sys.path.insert(0, str(Path(__file__).parent))
    from test_loop import make_loop

    archive = tmp_path / ARCHIVE_FILE
    shutil.copyfile(FIXTURE, archive)  # a records file of 7f3fa01's schema, emptied
    db = sqlite3.connect(archive)
    db.executescript("DELETE FROM cycles; DELETE FROM runs; DELETE FROM events;")
    db.close()
    path = tmp_path / "records.sqlite"
    store = RecordStore(path)
    store.retention = Retention(RetentionPolicy(keep_strokes=50), path, check_every_ns=0)
    try:
        loop, _daq, _ = make_loop(sink=store.submit, seed=4)
        loop.run_sink = store.submit_run
        for _ in range(3):
            loop.run_cycles(30_000_000, 40)
        assert store.flush(30_000_000_000)
        end = time.monotonic() + 60
        while store.retention.runs_archived < 2:
            assert time.monotonic() < end, "no run moved to the archive (see the log: retention failed)"
            time.sleep(0.02)
    finally:
        store.close()
    assert _columns(archive, "runs")[-2:] == ["label", "notes"]
    with RecordsFile(archive) as f:
        assert [r["run_id"] for r in f.runs()] == [1, 2] and len(f) == 80
