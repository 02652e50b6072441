"""Records shipped to a real PostgreSQL 15: once each, resumed from what the database holds,
nothing lost or doubled across a server outage, clear errors for a wrong URL or password."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import daemonproc
import pgserver
import pytest

from usmswitch.client import Client
from usmswitch.daemon.records import RecordStore
from usmswitch.daemon.shipper_process import DRAIN_PRIORITY, ShipperProcess
from usmswitch.fleet.pg_schema import CYCLE_COLUMNS, CYCLES_TABLE, RUN_COLUMNS, RUNS_TABLE
from usmswitch.fleet.shipper import PostgresShipper
from usmswitch.protocol.record import RUN_FIELDS, CycleRecord, RunRecord
from usmswitch.runtime.realtime import fifo_refusal

FAST = {"retry_ns": (20_000_000, 200_000_000), "poll_ns": 50_000_000, "connect_timeout_s": 2}


def wait_for(predicate: Any, timeout_s: float = 20.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


@pytest.fixture
def ship(pg: Any) -> Any:
    """Start a shipper (fast retries) on a records file; every one is stopped after the test."""
    started: list[PostgresShipper] = []

    def start(path: Path, url: str, rig: str = "rigA", **kw: Any) -> PostgresShipper:
        shipper = PostgresShipper(path, url, rig, **{**FAST, **kw})
        shipper.start()
        started.append(shipper)
        return shipper

    yield start
    for shipper in started:
        shipper.stop(drain_timeout_ns=0)


def pg_records(server: Any, db: str, rig: str) -> list[CycleRecord]:
    import psycopg
    from psycopg.rows import dict_row

    with psycopg.connect(server.url(db), row_factory=dict_row) as conn:
        rows = conn.execute(
            f"SELECT {CYCLE_COLUMNS} FROM {CYCLES_TABLE} WHERE rig = %s ORDER BY cycle", (rig,)
        ).fetchall()
    return [CycleRecord.from_row(r) for r in rows]


def sqlite_records(path: Path) -> list[CycleRecord]:
    store = RecordStore(path, readonly=True)
    try:
        return list(store.iter_records())
    finally:
        store.close()


def write(path: Path, records: list[CycleRecord], rig: str = "rigA", runs: list[RunRecord] = ()) -> None:
    store = RecordStore(path, driver="sim", rig=rig)
    for run in runs:
        store.submit_run(run)
    for rec in records:
        store.submit(rec)
    assert store.close()


def test_records_arrive_once_each_field_for_field_and_resume_from_the_database(pg, ship, tmp_path: Path):
    server, db, url = pg
    path = tmp_path / "records.sqlite"
    run = RunRecord(run_id=1, kind="cycling", first_cycle=1, started_wall_ns=5, settings={"count": 700})
    write(path, pgserver.synthetic_records(1, 500, run_id=1), runs=[run])
    shipper = ship(path, url, "rigA", batch=128)
    wait_for(lambda: shipper.shipped_cycle == 500, what="500 strokes shipped")
    assert shipper.shipped == 500 and shipper.duplicates == 0 and shipper.error is None
    assert pg_records(server, db, "rigA") == sqlite_records(path)  # every field, in 4 batches
    # The run, still open, is there; once it ends its row is updated.
    assert server.query(db, f"SELECT run_id, end_reason, settings FROM {RUNS_TABLE}") == [
        (1, None, {"count": 700})
    ]
    assert shipper.stop()

    # More strokes while no shipper ran: a new one resumes after cycle 500, sends nothing twice.
    ended = RunRecord(**{**run.to_dict(), "last_cycle": 700, "ended_wall_ns": 9, "end_reason": "done"})
    write(path, pgserver.synthetic_records(501, 200, run_id=1), runs=[ended])
    again = ship(path, url, "rigA")
    wait_for(lambda: again.shipped_cycle == 700, what="the rest shipped")
    assert (again.shipped, again.duplicates) == (200, 0)
    assert pg_records(server, db, "rigA") == sqlite_records(path)
    wait_for(lambda: again.runs_shipped >= 1, what="the run's end shipped")
    rows = server.query(db, f"SELECT {RUN_COLUMNS} FROM {RUNS_TABLE} ORDER BY run_id")
    assert [r[:8] for r in rows] == [(1, "cycling", 1, 5, {"count": 700}, 700, 9, "done")]
    assert rows[0][RUN_FIELDS.index("rig")] == "rigA"

    # A batch sent again (as after a connection lost during COMMIT) inserts nothing twice.
    again.shipped_cycle = 300
    again.wake()
    wait_for(lambda: again.shipped_cycle == 700 and again.duplicates == 400, what="the resend")
    assert again.shipped == 200
    assert server.query(db, f"SELECT count(*), count(DISTINCT cycle) FROM {CYCLES_TABLE}") == [(700, 700)]
    assert again.stop()


def test_a_database_holding_another_files_strokes_under_this_rig_is_refused(pg, ship, tmp_path: Path):
    server, db, url = pg
    first, second = tmp_path / "a.sqlite", tmp_path / "b.sqlite"
    write(first, pgserver.synthetic_records(1, 50, seed=1))
    write(second, pgserver.synthetic_records(1, 80, seed=2))  # an earlier state dir, the same name
    one = ship(first, url, "rigA")
    wait_for(lambda: one.shipped_cycle == 50)
    one.stop()
    two = ship(second, url, "rigA")
    wait_for(lambda: two.error is not None, what="the refusal")
    assert "holds strokes of rig 'rigA' up to cycle 50 that are not this records file's" in two.error
    assert two.shipped == 0 and not two.connected
    two.stop(drain_timeout_ns=0)
    # Under its own name it ships, beside the other rig's strokes (its rows say rigA in the file:
    # in the database they are the strokes of the daemon that ships them).
    three = ship(second, url, "rigB")
    wait_for(lambda: three.shipped_cycle == 80)
    three.stop()
    assert server.query(db, f"SELECT rig, count(*) FROM {CYCLES_TABLE} GROUP BY rig ORDER BY rig") == [
        ("rigA", 50),
        ("rigB", 80),
    ]


@pytest.mark.parametrize(
    ("make_url", "expected"),
    [
        (
            lambda s, db: s.url(db, password="wrong-password"),
            'password authentication failed for user "usmswitch"',
        ),
        (lambda s, db: s.url("no_such_db"), 'database "no_such_db" does not exist'),
        (lambda s, db: s.url(db).replace(f":{s.port}/", ":1/"), "Connection refused"),
    ],
    ids=["password", "database", "port"],
)
def test_a_wrong_url_or_password_is_a_clear_error_retried_and_never_shows_the_password(
    pg, ship, tmp_path: Path, make_url: Any, expected: str
):
    server, db, _ = pg
    path = tmp_path / "records.sqlite"
    write(path, pgserver.synthetic_records(1, 10))
    shipper = ship(path, make_url(server, db))
    wait_for(lambda: shipper.error_count >= 3, what="three failed attempts")
    assert expected in shipper.error
    assert shipper.error.startswith("postgres postgresql://usmswitch:***@127.0.0.1:")
    assert pgserver.PASSWORD not in shipper.error and "wrong-password" not in shipper.error
    assert not shipper.connected and shipper.lag == 10
    assert not shipper.stop(drain_timeout_ns=0)


def test_a_database_of_a_newer_schema_is_refused(pg, ship, tmp_path: Path):
    server, db, url = pg
    server.query(db, "CREATE TABLE usmswitch_meta (key text PRIMARY KEY, value text NOT NULL)")
    server.query(db, "INSERT INTO usmswitch_meta VALUES ('schema_version', '99')")
    server.query(db, f"ALTER TABLE usmswitch_meta OWNER TO {pgserver.ROLE}")
    path = tmp_path / "records.sqlite"
    write(path, pgserver.synthetic_records(1, 5))
    shipper = ship(path, url, "rigA")
    wait_for(lambda: shipper.error is not None)
    assert "the database has usmswitch schema 99; this daemon writes 1" in shipper.error
    shipper.stop(drain_timeout_ns=0)


# -- the daemon ------------------------------------------------------------------------------------
def _status(sock: Path) -> dict[str, Any]:
    with Client(str(sock), timeout=5) as c:
        return c.status()


@contextlib.contextmanager
def shipping_daemon(
    tmp_path: Path, url: str, shipped: int = 0
) -> Iterator[tuple[Path, subprocess.Popen[bytes], list[str]]]:
    """usmswitchd cycling every 20 ms as rigA, shipping to `url` (up to cycle `shipped` before
    the body runs); stopped after it, exit 0, its log in the list."""
    sock = tmp_path / "d.sock"
    args = daemonproc.daemon_args(tmp_path, "--rig", "rigA", "--period", "20ms", "--postgres", url)
    proc = daemonproc.spawn(args)
    log: list[str] = []
    try:
        daemonproc.wait_serving(sock, proc)
        if shipped:
            wait_for(
                lambda: _status(sock)["records"]["postgres"]["shipped_cycle"] >= shipped, what="shipping"
            )
        yield sock, proc, log
    finally:
        log.append(daemonproc.stop(proc).decode())
    assert proc.returncode == 0, log[0][-2000:]


def ship_the_rest(tmp_path: Path, url: str, log: str) -> None:
    """What a stop's drain left behind (a busy machine gives it less than its 2 s) ships at the next
    start, as docs/fleet.md says: the daemon that stopped behind said so, and one started idle on
    the same state directory catches up."""
    if "postgres shipping stopped behind" not in log:
        return  # the drain shipped everything: the comparison says whether it did
    sock = tmp_path / "d.sock"
    args = daemonproc.daemon_args(tmp_path, "--rig", "rigA", "--no-autostart", "--postgres", url)
    proc = daemonproc.spawn(args)
    try:
        daemonproc.wait_serving(sock, proc)
        # An idle daemon commits nothing: its shipper's own word says when the file's last is in.
        last = sqlite_records(tmp_path / "state" / "records.sqlite")[-1].cycle
        wait_for(
            lambda: (_status(sock)["records"]["postgres"]["shipped_cycle"] or 0) >= last,
            what="the rest shipped",
        )
    finally:
        daemonproc.stop(proc)


def test_server_stopped_mid_run_and_restarted_loses_and_doubles_nothing(pg, tmp_path: Path):
    server, db, url = pg
    with shipping_daemon(tmp_path, url, shipped=20) as (sock, _, log):
        server.stop()  # the database goes away mid-run
        down_at = _status(sock)["cycle"]
        wait_for(lambda: _status(sock)["records"]["postgres"]["error"] is not None, what="the outage seen")
        time.sleep(1.0)
        status = _status(sock)
        assert status["state"] == "cycling" and status["cycle"] > down_at + 20  # the loop went on
        assert not status["records"]["postgres"]["connected"] and status["records"]["postgres"]["lag"] > 20
        server.start()
        wait_for(lambda: _status(sock)["records"]["postgres"]["lag"] == 0, what="the catch-up")
        assert _status(sock)["records"]["postgres"]["error"] is None
    local = sqlite_records(tmp_path / "state" / "records.sqlite")
    assert len(local) > 60
    ship_the_rest(tmp_path, url, log[0])
    assert pg_records(server, db, "rigA") == local  # all of them, once each, equal field for field
    lines = [json.loads(x) for x in log[0].splitlines() if x.startswith("{")]
    failing = [x for x in lines if x.get("event", "").startswith("postgres shipping failing")]
    assert 1 <= len(failing) <= 3, failing  # said once per distinct error, not once per retry


def test_a_refused_password_leaves_the_daemon_controlling(pg, tmp_path: Path):
    server, db, _ = pg
    with shipping_daemon(tmp_path, server.url(db, password="not-it")) as (sock, _, log):
        wait_for(lambda: _status(sock)["records"]["postgres"]["error"] is not None, what="the error")
        first = _status(sock)
        time.sleep(0.5)
        later = _status(sock)
    pgst = later["records"]["postgres"]
    assert "password authentication failed" in pgst["error"] and "not-it" not in pgst["error"]
    assert later["state"] == "cycling" and later["cycle"] > first["cycle"] + 10
    assert "not-it" not in log[0]  # nor in the log (the start event's config is redacted too)
    assert server.query(db, "SELECT to_regclass('usmswitch_cycles')") == [(None,)]


def test_shipping_without_psycopg_refuses_to_start_saying_what_to_install(tmp_path: Path):
    code = (
        "import sys; sys.modules['psycopg'] = None\n"
        "from usmswitch.daemon.cli import main\n"
        f"sys.exit(main({daemonproc.daemon_args(tmp_path, '--postgres', 'postgresql://db/x')[3:]!r}))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert "records.postgres_url needs psycopg 3: pip install 'usmswitch[postgres]'" in proc.stderr


def test_a_shipper_process_that_dies_is_started_again_and_catches_up(pg, tmp_path: Path):
    server, db, url = pg
    with shipping_daemon(tmp_path, url, shipped=10) as (sock, proc, log):
        os.kill(daemonproc.child_pid(proc, "usmswitch.daemon.shipper_process"), signal.SIGKILL)
        wait_for(
            lambda: "exited" in (_status(sock)["records"]["postgres"]["error"] or ""), what="the death seen"
        )
        killed_at = _status(sock)["cycle"]
        wait_for(
            lambda: (
                (p := _status(sock)["records"]["postgres"])["error"] is None
                and p["shipped_cycle"] > killed_at
            ),
            timeout_s=30,
            what="a new shipper shipping",
        )
        assert _status(sock)["state"] == "cycling"
    ship_the_rest(tmp_path, url, log[0])
    assert pg_records(server, db, "rigA") == sqlite_records(tmp_path / "state" / "records.sqlite")


def test_a_frozen_shipper_does_not_hold_the_exit_and_the_rest_ships_next_time(pg, ship, tmp_path: Path):
    """At SIGTERM the shipper is given until 50 ms after the signal: one that cannot ship (here
    SIGSTOPped; in life, a slow database or a starved process) is killed, the daemon exits at once
    saying it stopped behind, and what was not shipped ships, once, at the next start."""
    server, db, url = pg
    args = daemonproc.daemon_args(tmp_path, "--rig", "rigA", "--period", "20ms", "--postgres", url)
    proc = daemonproc.spawn(args)
    try:
        sock = tmp_path / "d.sock"
        daemonproc.wait_serving(sock, proc)
        wait_for(lambda: _status(sock)["records"]["postgres"]["shipped_cycle"] >= 10, what="shipping")
        os.kill(daemonproc.child_pid(proc, "usmswitch.daemon.shipper_process"), signal.SIGSTOP)
        time.sleep(0.3)  # strokes committed that it cannot ship
        logged, took = daemonproc.stop_timed(proc)
        err = logged.decode()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-2000:]
    assert took < 2.0, f"exit took {took:.2f} s"  # the drain was 2 s, and a frozen shipper 12 s
    behind = [json.loads(x) for x in err.splitlines() if "postgres shipping stopped behind" in x]
    assert behind and behind[0]["lag"] > 0, err[-2000:]
    path = tmp_path / "state" / "records.sqlite"
    local = sqlite_records(path)
    assert len(pg_records(server, db, "rigA")) < len(local)
    again = ship(path, url, "rigA")
    wait_for(lambda: again.shipped_cycle == local[-1].cycle, what="the rest shipped")
    assert again.duplicates == 0
    assert pg_records(server, db, "rigA") == local


def test_label_and_notes_reach_postgresql_an_edit_after_the_run_too(pg, ship, tmp_path: Path) -> None:
    """Issue 38: a database the shipper made before labels (no label, no notes) gains the columns
    at the next connect, its rows kept, at the same schema version; a run's label and notes ship
    with it, and notes edited after the run ended (annotate_run: an event `notes`) ship again."""
    import psycopg

    from usmswitch.client.pgrecords import PostgresRecords
    from usmswitch.daemon import run_notes
    from usmswitch.fleet.pg_schema import SCHEMA, SET_VERSION

    server, db, url = pg
    with psycopg.connect(url, autocommit=True) as conn:  # as the shipper of 7f3fa01 left it
        for statement in SCHEMA:
            conn.execute(statement)
        conn.execute(SET_VERSION, ("1",))
        conn.execute(f"ALTER TABLE {RUNS_TABLE} DROP COLUMN label, DROP COLUMN notes")
        conn.execute(
            f"INSERT INTO {RUNS_TABLE} (run_id, kind, first_cycle, started_wall_ns, settings, rig)"
            " VALUES (1, 'cycling', 1, 5, '{}', 'oldrig')"
        )
    path = tmp_path / "records.sqlite"
    run = RunRecord(
        run_id=1, kind="cycling", first_cycle=1, started_wall_ns=5, label="pg-test", notes="first"
    )
    ended = RunRecord(**{**run.to_dict(), "last_cycle": 50, "ended_wall_ns": 9, "end_reason": "done"})
    write(path, pgserver.synthetic_records(1, 50, run_id=1), runs=[run, ended])
    shipper = ship(path, url, "rigA")
    runs = f"SELECT rig, run_id, label, notes, end_reason FROM {RUNS_TABLE} ORDER BY rig"

    def shipped() -> list[tuple[Any, ...]]:
        try:
            return server.query(db, runs)
        except psycopg.errors.UndefinedColumn:  # the shipper has not connected yet
            return [()]

    wait_for(lambda: shipped()[-1][-1:] == ("done",), what="the ended run shipped")
    assert shipped() == [
        ("oldrig", 1, None, None, None),
        ("rigA", 1, "pg-test", "first", "done"),
    ]
    assert server.query(db, "SELECT value FROM usmswitch_meta WHERE key = 'schema_version'") == [("1",)]

    store = RecordStore(path, driver="sim", rig="rigA")  # the daemon's annotate_run, after the end
    store.record_event("notes", run_id=1, label=None, notes="second look: drift", by="test")
    store.write(run_notes.edit(1, None, "second look: drift")).result(10)
    assert store.close()
    shipper.wake()
    wait_for(lambda: shipped()[-1][3] == "second look: drift", what="the edit shipped")
    with PostgresRecords(url, rig="rigA") as copy:
        assert [(r["run_id"], r["label"]) for r in copy.runs(label="pg-test")] == [(1, "pg-test")]
        assert copy.runs(label="nothing") == []
        assert len(list(copy.records(label="pg-test"))) == 50


def test_a_stop_while_the_database_does_not_answer_ends_at_once_without_another_connect(tmp_path: Path):
    """A database that takes a connect and never answers (a listener nobody accepts from) holds
    each try for the connect timeout. A stop that comes while the shipper waits to try again ends
    it there: before, the drain tried once more and the stop lasted that timeout (2 s here)."""
    path = tmp_path / "records.sqlite"
    write(path, pgserver.synthetic_records(1, 10))
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        url = f"postgresql://usmswitch@127.0.0.1:{silent.getsockname()[1]}/x"
        retry = (30_000_000_000, 30_000_000_000)  # no second try before the stop
        shipper = PostgresShipper(path, url, "rigA", retry_ns=retry, connect_timeout_s=2)
        shipper.start()
        wait_for(lambda: shipper.error_count == 1, what="the first try timed out")
        assert not shipper.stop(drain_timeout_ns=10_000_000_000)
    assert shipper.error_count == 1, shipper.error  # no try in the drain: no connect timeout waited
    assert "timeout" in shipper.error


def test_the_shipper_process_drains_at_real_time_priority_when_the_daemon_may(tmp_path: Path):
    """The drain is the exit's last work: the child leaves nice 10 for SCHED_FIFO 1 at the stop
    (a loaded machine starved it for its whole budget), when the daemon is allowed real-time."""
    path = tmp_path / "records.sqlite"
    write(path, pgserver.synthetic_records(1, 10))
    handle = ShipperProcess(path, "postgresql://usmswitch@127.0.0.1:9/x", "rigA")
    handle.start()
    proc = handle._proc
    assert proc is not None
    wait_for(lambda: handle.status()["error"] is not None, what="the first refusal")
    os.kill(proc.pid, signal.SIGSTOP)  # it cannot end: its policy can be read while stop() waits
    seen: list[set[tuple[int, int]]] = []

    def read_policies() -> None:
        time.sleep(0.05)
        seen.append(
            {
                (os.sched_getscheduler(int(tid)), os.sched_getparam(int(tid)).sched_priority)
                for tid in os.listdir(f"/proc/{proc.pid}/task")
            }
        )

    reader = threading.Thread(target=read_policies)
    reader.start()
    assert not handle.stop(drain_timeout_ns=2_000_000_000)  # killed after its drain and grace
    reader.join()
    before = {(os.SCHED_OTHER, 0)}
    expected = {(os.SCHED_FIFO, DRAIN_PRIORITY)} if fifo_refusal(DRAIN_PRIORITY) is None else before
    assert seen == [expected]
    assert proc.wait(10) == -signal.SIGKILL  # its teardown may outlast stop()'s short wait for it
