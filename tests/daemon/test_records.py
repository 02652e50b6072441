"""CycleRecord and RecordStore on real SQLite files, including a writer process killed with SIGKILL."""

from __future__ import annotations

import csv
import dataclasses
import errno
import io
import os
import signal
import sqlite3
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from usmswitch.daemon.records import RecordStore, RecordStoreError
from usmswitch.protocol.record import FIELDS, UNUSABLE, CycleRecord, Flag
from usmswitch.protocol.records_schema import SCHEMA_VERSION


def make_record(cycle: int, *, operating_ns: int | None = 10_500_000, flags: int = 0) -> CycleRecord:
    """A plausible closed-loop stroke: direction alternates, times derived from the cycle number."""
    t_cmd = cycle * 50_000_000
    delay = 1_500_000
    t_start = t_cmd + delay + 200
    arrive = None if operating_ns is None else t_start + operating_ns
    return CycleRecord.build(
        cycle=cycle,
        direction=(cycle - 1) % 2,
        mode="closed",
        target_ns=12_000_000,
        order=1,
        coefficients=(0.99 + cycle * 1e-9,),
        t_hat_ns=10_500_000,
        delay_ns=delay,
        t_cmd_ns=t_cmd,
        t_start_ns=t_start,
        t_depart_ns=t_start + 300_000,
        t_arrive_ns=arrive,
        lateness_ns=200,
        temperature_c=25.5,
        frequency_hz=40_000.0,
        flags=flags,
        wall_ns=1_700_000_000_000_000_000 + cycle,
    )


# -- CycleRecord --------------------------------------------------------------------------------------
def test_build_derives_durations_from_stamps():
    r = make_record(7, operating_ns=10_400_000)
    assert r.operating_ns == 10_400_000
    assert r.total_ns == r.t_arrive_ns - r.t_cmd_ns == 1_500_200 + 10_400_000
    assert r.error_ns == r.total_ns - 12_000_000
    assert r.dead_ns == 300_000
    stalled = make_record(8, operating_ns=None, flags=Flag.STALL)
    assert (stalled.operating_ns, stalled.total_ns, stalled.error_ns) == (None, None, None)
    assert stalled.dead_ns == 300_000
    assert stalled.flags == Flag.STALL and type(stalled.flags) is int


def test_record_round_trips_through_dict_row_and_csv():
    r = make_record(3, flags=Flag.LATE | Flag.CLAMPED)
    d = r.to_dict()
    assert list(d) == list(FIELDS)
    assert d["coefficients"] == [r.coefficients[0]] and type(d["flags"]) is int
    assert CycleRecord.from_row(d) == r
    assert CycleRecord.from_row(r.to_row()) == r
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=FIELDS)
    writer.writeheader()
    writer.writerow(d)
    buf.seek(0)
    (row,) = list(csv.DictReader(buf))
    assert CycleRecord.from_row(row) == r


def test_a_stroke_that_never_started_round_trips():
    """An estop or a shutdown before the start leaves every stamp after the command empty."""
    r = dataclasses.replace(
        make_record(4, operating_ns=None, flags=Flag.ESTOP | Flag.FAULT),
        t_start_ns=None,
        t_depart_ns=None,
        dead_ns=None,
        lateness_ns=None,
    )
    assert CycleRecord.from_row(r.to_dict()) == r
    assert CycleRecord.from_row(r.to_row()) == r


def test_from_row_names_the_bad_field():
    d = make_record(1).to_dict()
    with pytest.raises(ValueError, match="mode='sideways'"):
        CycleRecord.from_row(d | {"mode": "sideways"})
    with pytest.raises(ValueError, match=r"target_ns=1\.5"):
        CycleRecord.from_row(d | {"target_ns": 1.5})
    with pytest.raises(ValueError, match="lacks field"):
        CycleRecord.from_row({k: v for k, v in d.items() if k != "flags"})
    with pytest.raises(ValueError, match="3 values"):
        CycleRecord.from_row((1, 2, 3))


def test_flag_bits_are_distinct_and_unusable_covers_lost_strokes():
    values = [f.value for f in Flag]
    assert len(set(values)) == len(values) and all(v & (v - 1) == 0 for v in values)
    assert UNUSABLE == (
        Flag.STALL | Flag.FAULT | Flag.ESTOP | Flag.ABORTED | Flag.PARTIAL | Flag.IMPLAUSIBLE | Flag.MISMATCH
    )
    assert not UNUSABLE & Flag.NOISE  # chatter counted, the stroke still learned when nothing else is wrong


# -- RecordStore -------------------------------------------------------------------------------------
def test_store_writes_reads_and_continues_after_restart(tmp_path: Path):
    path = tmp_path / "state" / "records.sqlite"
    with RecordStore(path) as store:
        assert store.last_cycle() == 0
        for i in range(1, 11):
            store.submit(make_record(i, operating_ns=10_000_000 + i))
        store.record_event("target", target_ns=24_000_000, direction="both")
        assert store.flush()
        assert store.count() == 10 and store.last_cycle() == 10
        # On strokes are the odd cycles, oldest first.
        assert store.last_strokes(0, 3) == [10_000_005, 10_000_007, 10_000_009]
        assert store.last_strokes(1, 100) == [10_000_000 + i for i in range(2, 11, 2)]
        hist = store.history(4)
        assert [r.cycle for r in hist] == [7, 8, 9, 10]
        assert hist[-1] == make_record(10, operating_ns=10_000_010)
        assert [r.cycle for r in store.history(2, direction=0)] == [7, 9]
        (ev,) = store.events()
        assert ev["kind"] == "target" and ev["after_cycle"] == 10 and ev["target_ns"] == 24_000_000
        assert store.stats()["written"] == 10 and store.backlog == 0
    assert store.close()  # a second close is harmless
    with RecordStore(path) as store:
        assert store.last_cycle() == 10
        store.record_event("mode", mode="open")
        store.submit(make_record(11))
        store.flush()
        assert [r.cycle for r in store.iter_records(first=9)] == [9, 10, 11]
        assert [e["kind"] for e in store.events()] == ["target", "mode"]
        assert store.events("mode")[0]["after_cycle"] == 10
    con = sqlite3.connect(path)
    assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    con.close()


def test_warm_start_skips_lost_strokes(tmp_path: Path):
    with RecordStore(tmp_path / "r.sqlite") as store:
        store.submit(make_record(1, operating_ns=10_100_000))
        store.submit(make_record(3, operating_ns=None, flags=Flag.STALL))
        store.submit(make_record(5, operating_ns=9_000_000, flags=Flag.FAULT))
        store.submit(make_record(7, operating_ns=10_300_000, flags=Flag.LATE | Flag.BOUNCE))
        store.flush()
        assert store.last_strokes(0, 10) == [10_100_000, 10_300_000]
        assert store.last_strokes(0, 10, exclude_flags=0) == [10_100_000, 9_000_000, 10_300_000]
        with pytest.raises(ValueError, match="direction"):
            store.last_strokes(2, 10)


def test_bad_input_is_refused_by_name(tmp_path: Path):
    with RecordStore(tmp_path / "r.sqlite") as store:
        with pytest.raises(TypeError, match="dict"):
            store.submit(make_record(1).to_dict())  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="reserved"):
            store.record_event("target", kind="x")
        with pytest.raises(ValueError, match="'Target!'"):
            store.record_event("Target!")
        with pytest.raises(ValueError, match="not plain JSON"):
            store.record_event("fault", detail=object())
    with pytest.raises(RecordStoreError, match="closed"):
        store.submit(make_record(1))


def test_duplicate_cycle_is_rejected_counted_and_the_rest_lands(tmp_path: Path):
    with RecordStore(tmp_path / "r.sqlite") as store:
        store.submit(make_record(1))
        store.flush()
        for i in (2, 1, 3):
            store.submit(make_record(i))
        store.flush()
        assert store.count() == 3
        assert (store.written, store.rejected) == (3, 1)
        assert "cycle 1 rejected" in (store.last_error or "")
        # Past SQLite's 64-bit integers, and a field that is not a number: rejected, named, counted.
        huge = make_record(4)
        huge.t_cmd_ns = 2**70
        store.submit(huge)
        odd = make_record(5)
        odd.coefficients = ("a",)  # type: ignore[assignment]
        store.submit(odd)
        store.submit(make_record(6))
        store.flush()
        assert [r.cycle for r in store.iter_records()] == [1, 2, 3, 6]
        assert (store.written, store.rejected, store.backlog) == (4, 3, 0)
        assert "cycle 5 rejected" in (store.last_error or "")
        assert store.writer_error is None


def wait_for(predicate, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def test_writer_failure_is_surfaced_retried_and_loses_nothing(tmp_path: Path):
    path = tmp_path / "r.sqlite"
    store = RecordStore(path, busy_timeout_ns=20_000_000, retry_ns=(10_000_000, 50_000_000))
    blocker = sqlite3.connect(path, isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")  # another writer holds the lock: every commit fails "locked"
    try:
        for i in range(1, 21):
            store.submit(make_record(i))
        assert wait_for(lambda: store.writer_error is not None)
        assert "locked" in store.writer_error
        assert store.count() == 0  # reads do not wait on the stuck writer
        assert not store.flush(timeout_ns=50_000_000)
        assert store.backlog == 20
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
    assert store.flush()
    assert store.count() == 20 and store.writer_error is None and store.error_count >= 1
    assert store.close()


def test_backlog_past_max_pending_drops_the_oldest_and_counts_them(tmp_path: Path):
    path = tmp_path / "r.sqlite"
    store = RecordStore(
        path, max_batch=2, max_pending=5, busy_timeout_ns=5_000_000, retry_ns=(5_000_000, 20_000_000)
    )
    blocker = sqlite3.connect(path, isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")
    try:
        for i in range(1, 9):
            store.submit(make_record(i))
        assert wait_for(lambda: store.dropped == 3)
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
    assert store.close()
    ro = RecordStore(path, readonly=True)
    assert [r.cycle for r in ro.iter_records()] == [4, 5, 6, 7, 8]
    ro.close()


def test_readonly_store_and_bad_files(tmp_path: Path):
    with pytest.raises(RecordStoreError, match="does not exist"):
        RecordStore(tmp_path / "missing.sqlite", readonly=True)
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not a database" * 100)
    with pytest.raises(RecordStoreError, match=str(junk)):
        RecordStore(junk)
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
    con.execute("INSERT INTO meta VALUES ('schema_version', '99')")
    con.commit()
    con.close()
    with pytest.raises(RecordStoreError, match="schema version 99"):
        RecordStore(other)
    with RecordStore(tmp_path / "ok.sqlite") as store:
        store.submit(make_record(1))
    ro = RecordStore(tmp_path / "ok.sqlite", readonly=True)
    assert ro.last_cycle() == 1
    with pytest.raises(RecordStoreError, match="read-only"):
        ro.submit(make_record(2))
    ro.close()


CHILD = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {tests!r})
    from test_records import make_record
    from usmswitch.daemon.records import RecordStore
    store = RecordStore({path!r})
    i = 0
    while True:
        i += 1
        store.submit(make_record(i))
        print(i, flush=True)  # acknowledged: the loop has handed the record over
        time.sleep(0.001)
    """
)


def test_kill_9_loses_nothing_acknowledged_and_leaves_a_sound_file(tmp_path: Path):
    path = tmp_path / "records.sqlite"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD.format(tests=str(Path(__file__).parent), path=str(path))],
        stdout=subprocess.PIPE,
        text=True,
    )
    acked: list[tuple[int, int]] = []  # (cycle, when the parent saw the acknowledgement)
    try:
        assert child.stdout is not None
        for line in child.stdout:
            acked.append((int(line), time.monotonic_ns()))
            if len(acked) >= 400:
                break
    finally:
        kill_ns = time.monotonic_ns()
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
    assert child.returncode == -signal.SIGKILL
    # "A moment": anything acknowledged 200 ms before the kill must be committed. The writer
    # commits within about a millisecond; the margin is for a loaded, shared machine.
    due = [c for c, t in acked if t < kill_ns - 200_000_000]
    assert due, "the child acknowledged nothing early enough to check"
    con = sqlite3.connect(path)
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    cycles = [r[0] for r in con.execute("SELECT cycle FROM cycles ORDER BY cycle")]
    con.close()
    assert cycles == list(range(1, len(cycles) + 1)), "committed records are a gap-free prefix"
    assert max(due) <= len(cycles)
    print(f"\nkill -9: {len(acked)} acknowledged, {len(due)} due, {len(cycles)} on disk")
    # The file opens for a new daemon, which continues the numbering.
    with RecordStore(path) as store:
        assert store.last_cycle() == len(cycles)


def _rss_kib() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def test_100k_records_are_all_written(tmp_path: Path):
    path = tmp_path / "records.sqlite"
    n = 100_000
    rss0 = _rss_kib()
    t0 = time.perf_counter()
    store = RecordStore(path)
    for i in range(1, n + 1):
        store.submit(make_record(i))
    t1 = time.perf_counter()
    assert store.flush(timeout_ns=60_000_000_000)
    t2 = time.perf_counter()
    rss1 = _rss_kib()
    assert store.close()
    assert RecordStore(path, readonly=True).count() == n
    print(
        f"\n100k records: submit {t1 - t0:.2f} s ({(t1 - t0) / n * 1e6:.1f} us each, building included),"
        f" all committed after {t2 - t0:.2f} s; RSS {rss0 // 1024} -> {rss1 // 1024} MiB;"
        f" file {path.stat().st_size // 1024} KiB"
    )


# -- where a record came from (schema 2) ----------------------------------------------------------
def test_store_stamps_driver_and_rig_and_the_warm_start_uses_only_its_own(tmp_path: Path):
    path = tmp_path / "r.sqlite"
    with RecordStore(path, driver="sim", rig="bench") as sim:
        for i in range(1, 7):
            rec = make_record(i, operating_ns=9_000_000 + i)
            sim.submit(rec)
            assert (rec.driver, rec.rig) == ("sim", "bench")  # stamped at submit: subscribers see it
        assert sim.flush()
    with RecordStore(path, driver="serial", rig="bench") as real:
        real.submit(make_record(7, operating_ns=10_000_007))
        # A record that says where it came from keeps it.
        real.submit(dataclasses.replace(make_record(9, operating_ns=10_000_009), rig="other"))
        assert real.flush()
        assert real.last_strokes(0, 100, driver="serial", rig="bench") == [10_000_007]
        assert real.last_strokes(0, 100, driver="sim", rig="bench") == [9_000_001, 9_000_003, 9_000_005]
        assert real.last_strokes(0, 100, driver="serial") == [10_000_007, 10_000_009]
        assert real.last_strokes(0, 100, driver="usb", rig="bench") == []
        assert len(real.last_strokes(0, 100)) == 5  # no filter: every usable stroke
        hist = real.history(4)
        assert [(r.cycle, r.driver, r.rig) for r in hist] == [
            (5, "sim", "bench"),
            (6, "sim", "bench"),
            (7, "serial", "bench"),
            (9, "serial", "other"),
        ]
        assert [r.to_dict()["driver"] for r in real.iter_records(first=6)] == ["sim", "serial", "serial"]
    con = sqlite3.connect(path)
    assert con.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone() == (
        str(SCHEMA_VERSION),
    )
    con.close()


SCHEMA_V1 = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
CREATE TABLE cycles (
    cycle INTEGER PRIMARY KEY CHECK (cycle >= 1),
    direction INTEGER NOT NULL CHECK (direction IN (0, 1)),
    mode TEXT NOT NULL CHECK (mode IN ('closed', 'open')),
    target_ns INTEGER NOT NULL, "order" INTEGER NOT NULL, coefficients TEXT NOT NULL,
    t_hat_ns INTEGER NOT NULL, delay_ns INTEGER NOT NULL CHECK (delay_ns >= 0), t_cmd_ns INTEGER NOT NULL,
    t_start_ns INTEGER, t_depart_ns INTEGER, t_arrive_ns INTEGER,
    operating_ns INTEGER, total_ns INTEGER, error_ns INTEGER, dead_ns INTEGER, lateness_ns INTEGER,
    temperature_c REAL, frequency_hz REAL, flags INTEGER NOT NULL DEFAULT 0, wall_ns INTEGER NOT NULL
);
CREATE INDEX cycles_direction ON cycles (direction, cycle);
CREATE TABLE events (id INTEGER PRIMARY KEY, wall_ns INTEGER NOT NULL, after_cycle INTEGER,
    kind TEXT NOT NULL, data TEXT NOT NULL);
CREATE INDEX events_kind ON events (kind, id);
INSERT INTO meta VALUES ('schema_version', '1'), ('created_wall_ns', '1');
"""


def test_a_schema_1_file_is_read_as_is_and_migrated_keeping_every_row(tmp_path: Path):
    path = tmp_path / "old.sqlite"
    con = sqlite3.connect(path)
    con.executescript(SCHEMA_V1)
    old = [make_record(i, operating_ns=10_000_000 + i) for i in range(1, 301)]
    v1_fields = [f for f in FIELDS if f not in ("driver", "rig", "run_id")]
    columns, marks = ", ".join(f'"{f}"' for f in v1_fields), ", ".join("?" * len(v1_fields))
    con.executemany(
        f"INSERT INTO cycles ({columns}) VALUES ({marks})", [r.to_row()[: len(v1_fields)] for r in old]
    )
    con.execute("INSERT INTO events (wall_ns, after_cycle, kind, data) VALUES (1, 300, 'stop', '{}')")
    con.commit()
    con.close()
    # Read-only (usmswitchctl export from an old file): read as it is, the source unknown.
    ro = RecordStore(path, readonly=True)
    assert ro.schema_version == 1 and list(ro.iter_records()) == old
    assert ro.last_strokes(0, 5, driver="sim") == []
    ro.close()
    # A writer migrates it: every row kept, source NULL, new rows stamped.
    with RecordStore(path, driver="serial", rig="bench") as store:
        assert store.count() == 300 and store.last_cycle() == 300
        assert list(store.iter_records(last=300)) == old  # driver and rig None: unknown
        assert store.last_strokes(0, 5, driver="serial", rig="bench") == []  # unknown never warms
        assert store.last_strokes(0, 2) == [10_000_297, 10_000_299]
        store.submit(make_record(301))
        assert store.flush()
        assert store.history(1)[0].driver == "serial"
        assert store.events("stop")[0]["after_cycle"] == 300
    con = sqlite3.connect(path)
    assert con.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone() == (
        str(SCHEMA_VERSION),
    )
    assert con.execute("SELECT count(*), count(driver) FROM cycles").fetchone() == (301, 1)
    assert con.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    con.close()


# -- permissions ---------------------------------------------------------------------------------
def _mode(p: Path) -> int:
    return stat.S_IMODE(os.stat(p).st_mode)


def test_record_files_are_not_world_readable(tmp_path: Path):
    old = os.umask(0o022)  # a permissive umask: the store must not rely on the caller's
    try:
        path = tmp_path / "r.sqlite"
        with RecordStore(path) as store:
            store.submit(make_record(1))
            assert store.flush()
            for suffix in ("", "-wal", "-shm"):
                assert _mode(Path(f"{path}{suffix}")) == 0o640, suffix
        private = tmp_path / "p.sqlite"
        with RecordStore(private, file_mode=0o600) as store:
            store.submit(make_record(1))
            assert store.flush()
            assert {_mode(Path(f"{private}{s}")) for s in ("", "-wal", "-shm")} == {0o600}
        # A file left world-readable by an older version is tightened at open.
        os.chmod(path, 0o644)
        with RecordStore(path) as store:
            assert _mode(path) == 0o640 and _mode(Path(f"{path}-wal")) == 0o640
        with pytest.raises(ValueError, match="beyond read and write"):
            RecordStore(tmp_path / "x.sqlite", file_mode=0o750)
    finally:
        os.umask(old)


# -- the file deleted or replaced under the writer ----------------------------------------------------
def test_a_deleted_file_is_a_writer_error_and_the_records_stay_pending(tmp_path: Path):
    path = tmp_path / "r.sqlite"
    store = RecordStore(path, retry_ns=(10_000_000, 50_000_000))
    for i in range(1, 11):
        store.submit(make_record(i))
    assert store.flush()
    path.unlink()
    # Idle, the writer notices within its check period, before anything more is submitted.
    assert wait_for(lambda: store.writer_error is not None, timeout_s=2.0)
    assert "deleted" in store.writer_error and str(path) in store.writer_error
    for i in range(11, 21):
        store.submit(make_record(i))
    time.sleep(0.2)
    assert store.backlog == 10 and store.written == 10  # kept in memory, not written into the void
    assert not store.flush(timeout_ns=100_000_000)
    assert not store.close(timeout_ns=300_000_000)  # close says records were left
    assert store.backlog == 10 and store.dropped == 0


def test_a_replaced_file_is_a_writer_error_and_a_commit_into_the_old_one_is_not_counted(tmp_path: Path):
    path = tmp_path / "r.sqlite"
    store = RecordStore(path, retry_ns=(10_000_000, 50_000_000))
    store.submit(make_record(1))
    assert store.flush()
    path.rename(tmp_path / "moved.sqlite")
    path.write_bytes(b"")  # another file where ours was
    for i in range(2, 6):
        store.submit(make_record(i))  # may land in the moved file; still counted unwritten
    assert wait_for(lambda: store.writer_error is not None, timeout_s=2.0)
    assert "replaced" in store.writer_error
    time.sleep(0.1)
    assert store.written == 1 and store.backlog == 4
    assert not store.close(timeout_ns=200_000_000)


# -- a real full file system (tmpfs) ------------------------------------------------------------------
@pytest.fixture
def small_fs(tmp_path: Path):
    """A 1 MiB tmpfs mounted under tmp_path (needs root and mount permission)."""
    mnt = tmp_path / "fs"
    mnt.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m,mode=0755", "tmpfs", str(mnt)], capture_output=True, text=True
    )
    if r.returncode != 0:
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI must allow a tmpfs mount for the full-disk test: {r.stderr.strip()}")
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip() or r.returncode}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def fill(directory: Path) -> Path:
    """Write a file until the file system is full; returns it (delete it to make room again)."""
    filler = directory / "filler"
    chunk = b"\0" * 4096
    with filler.open("wb", buffering=0) as f:
        while True:
            try:
                f.write(chunk)
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
                return filler


def test_a_full_disk_is_a_writer_error_and_nothing_is_lost_when_space_returns(small_fs: Path):
    path = small_fs / "r.sqlite"
    store = RecordStore(path, retry_ns=(10_000_000, 50_000_000))
    for i in range(1, 6):
        store.submit(make_record(i))
    assert store.flush()
    filler = fill(small_fs)
    i = 5
    while store.writer_error is None and i < 5000:  # the WAL grows by a page or two per commit
        i += 1
        store.submit(make_record(i))
        store.flush(timeout_ns=20_000_000)
    assert store.writer_error is not None and "full" in store.writer_error.lower()
    for j in range(i + 1, i + 21):
        store.submit(make_record(j))
    assert not store.flush(timeout_ns=100_000_000) and store.backlog >= 20
    filler.unlink()
    assert store.flush()
    assert store.writer_error is None and store.backlog == 0 and store.dropped == 0
    assert store.count() == i + 20 and store.close()


def test_a_write_runs_in_order_with_the_records_and_a_refused_one_undoes_only_itself(tmp_path: Path) -> None:
    """`RecordStore.write` (run edits, the queue of runs): run by the writer with what was queued
    before it in the file, its result once committed; one that raises leaves nothing of its own
    and the batch around it still lands."""
    store = RecordStore(tmp_path / "records.sqlite")
    try:
        store.submit(make_record(1))
        seen = store.write(lambda conn: conn.execute("SELECT max(cycle) FROM cycles").fetchone()[0])

        def refused(conn: sqlite3.Connection) -> None:
            conn.execute("INSERT INTO meta (key, value) VALUES ('half', 'done')")
            raise ValueError("no such run")

        failed = store.write(refused)
        store.submit(make_record(2))
        assert seen.result(10) >= 1  # record 1, queued before it, is there
        with pytest.raises(ValueError, match="no such run"):
            failed.result(10)
        assert store.flush() and store.last_cycle() == 2
        meta = store._reader().execute("SELECT count(*) FROM meta WHERE key = 'half'").fetchone()[0]
        assert meta == 0
    finally:
        store.close()
