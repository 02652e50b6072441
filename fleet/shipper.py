"""Copies committed records from the local SQLite file to PostgreSQL, on a thread of its own.

The local file stays the source of truth: the shipper reads only what the record writer has
committed (a read-only connection of its own), so the loop never waits for it and a database
outage loses nothing. Batches go in cycle order, one transaction each, by COPY into a temporary
table and `INSERT ... ON CONFLICT (rig, cycle) DO NOTHING`: a batch sent twice (a connection lost
during COMMIT) is harmless. Where to resume is read from the database at every (re)connect: the
highest cycle it holds for this rig, whose stamps must match the local row (a database holding
another file's strokes under this rig's name is refused, never merged). Failures are kept in
`error`, logged once each, and retried with backoff. Tables: fleet/pg_schema.py, docs/fleet.md.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TextIO
from urllib.parse import quote

import structlog

from usmswitch.protocol.record import LATER_RUN_FIELDS, RUN_FIELDS
from usmswitch.protocol.records_schema import COLUMNS, SCHEMA_VERSION

from .pg_schema import (
    ADDITIONS,
    COPY_STAGE,
    CREATE_STAGE,
    INSERT_FROM_STAGE,
    LAST_SHIPPED,
    MIGRATIONS,
    MISSING_ADDITIONS,
    PG_SCHEMA_VERSION,
    RUNS_FROM,
    SCHEMA,
    SCHEMA_LOCK_KEY,
    SELECT_VERSION,
    SET_VERSION,
    UPSERT_RUN,
    pg_cycle,
    pg_run,
    redact_url,
)

log = structlog.get_logger("usmswitch.shipper")

#: How often the shipper process says its status on its stdout (when it changed).
STATUS_EVERY_S = 0.2
#: Runs shipped per pass at most (a pass with a long backlog of runs goes on at the next).
MAX_RUNS_PER_PASS = 500
#: An idle shipper checks its connection this often, so `connected` tells the truth when idle.
IDLE_CHECK_NS = 5_000_000_000
#: Rows read from the file per wait_turn; every row copied waits its turn too: a backlog is caught
#: up in slices of a few microseconds of Python, none begun while the loop is about to start a
#: stroke (a thread that is not parked in wait_turn competes for the GIL the spinning loop holds).
READ_CHUNK = 64
#: While catching up, the shipper rests after each batch for this share of the time the batch
#: took: the loop's core and the GIL stay mostly free even through a long backlog (an hour of
#: strokes still ships in well under a minute).
REST_SHARE = 1.0
_RUN_END = RUN_FIELDS.index("end_reason")


class ShipperError(Exception):
    """Shipping cannot go on as things are (a schema too new, a rig name taken); the message says why."""


class LocalRecords:
    """The committed rows of the records file as plain tuples, read-only (no record objects are
    built: a catch-up of a large backlog leaves little for the collector, which runs in the loop's
    slack). The file is the daemon's, so of the current schema."""

    def __init__(self, path: Path) -> None:
        uri = f"file:{quote(str(path.resolve()))}?mode=ro"
        self.db = sqlite3.connect(uri, uri=True, check_same_thread=False)
        self.db.execute("PRAGMA busy_timeout = 200")
        (version,) = self.db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        if version != str(SCHEMA_VERSION):
            self.db.close()
            raise ShipperError(f"records file {path}: schema {version}, the shipper reads {SCHEMA_VERSION}")

    def last_cycle(self) -> int:
        """The highest cycle committed (0 when none)."""
        return self.db.execute("SELECT coalesce(max(cycle), 0) FROM cycles").fetchone()[0]

    def stamps(self, cycle: int) -> tuple[int, int] | None:
        """(t_cmd_ns, wall_ns) of one stroke, or None."""
        return self.db.execute("SELECT t_cmd_ns, wall_ns FROM cycles WHERE cycle = ?", (cycle,)).fetchone()

    def cycles_after(self, cycle: int, n: int, gate: Callable[[], object]) -> Iterator[tuple[Any, ...]]:
        """Up to `n` rows (FIELDS order) after `cycle`, in cycle order, read in chunks, each after
        `gate()`."""
        sql = f"SELECT {COLUMNS} FROM cycles WHERE cycle > ? ORDER BY cycle LIMIT ?"
        cur = self.db.execute(sql, (cycle, n))
        try:
            while True:
                gate()
                chunk = cur.fetchmany(READ_CHUNK)
                if not chunk:
                    return
                yield from chunk
        finally:
            cur.close()

    def runs_from(self, run_id: int, n: int) -> list[tuple[Any, ...]]:
        """Up to `n` runs (RUN_FIELDS order, settings as JSON text) from `run_id` on."""
        sql = f"SELECT {', '.join(RUN_FIELDS)} FROM runs WHERE run_id >= ? ORDER BY run_id LIMIT ?"
        return self.db.execute(sql, (run_id, n)).fetchall()

    def edited_runs(self, after_event: int) -> tuple[int, list[tuple[Any, ...]]]:
        """Runs whose label or notes were edited (events `notes`) after event id `after_event`: (the
        last such event's id, their rows as `runs_from` gives them)."""
        edits = "SELECT id, json_extract(data, '$.run_id') FROM events WHERE kind = 'notes' AND id > ?"
        rows = self.db.execute(edits, (after_event,)).fetchall()
        if not rows:
            return after_event, []
        ids = sorted({r[1] for r in rows})
        sql = f"SELECT {', '.join(RUN_FIELDS)} FROM runs WHERE run_id IN ({', '.join('?' * len(ids))})"
        return max(r[0] for r in rows), self.db.execute(sql, ids).fetchall()

    def close(self) -> None:
        """Close the read-only connection."""
        self.db.close()


def _import_psycopg() -> Any:
    try:
        import psycopg
    except ImportError:
        raise RuntimeError(
            "records.postgres_url needs psycopg 3: pip install 'usmswitch[postgres]'"
        ) from None
    return psycopg


class PostgresShipper:
    """Ships the records of one SQLite file to the PostgreSQL database at `url`, as rig `rig`."""

    def __init__(
        self,
        records_path: str | Path,
        url: str,
        rig: str,
        *,
        gate: Callable[[], object] = lambda: None,
        batch: int = 2000,
        retry_ns: tuple[int, int] = (250_000_000, 10_000_000_000),
        poll_ns: int = 1_000_000_000,
        connect_timeout_s: int = 5,
    ) -> None:
        self._psycopg = _import_psycopg()
        self.records_path = Path(records_path)
        self.url = url
        self.where = redact_url(url)
        self.rig = rig
        #: Called before each batch's Python work: the daemon passes the loop's `wait_turn`.
        self.gate = gate
        self._batch = batch
        self._retry_ns = retry_ns
        self._poll_ns = poll_ns
        self._connect_timeout_s = connect_timeout_s
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._drain_until_ns: int | None = None
        self._thread: threading.Thread | None = None
        #: The highest cycle the database holds for this rig (as far as this shipper knows).
        self.shipped_cycle = 0
        #: The highest cycle committed locally that the shipper has been told of or has read.
        self.committed_cycle = 0
        #: Strokes this shipper inserted, and those the database already had (a resent batch).
        self.shipped = 0
        self.duplicates = 0
        self.runs_shipped = 0
        self.error_count = 0
        self.error: str | None = None
        self.connected = False
        self._run_from = 1
        self._runs_sent: dict[int, tuple[Any, ...]] = {}  # run_id -> the row shipped, while it may change
        # The last edit of a run's label or notes (an event id) shipped: an ended run edited later is
        # sent again. From 0 at each connect: every edited run once (edits are few).
        self._edits_after = 0

    # -- the daemon's side -----------------------------------------------------------------------
    def start(self) -> None:
        """Start the shipping thread (it connects, creates the tables and catches up by itself)."""
        self._thread = threading.Thread(target=self._run, name="usmswitch-shipper", daemon=True)
        self._thread.start()

    def wake(self, records: list[Any] | None = None) -> None:
        """New records are committed (the record writer's on_commit): ship them soon. O(1)."""
        if records:
            self.committed_cycle = max(self.committed_cycle, records[-1].cycle)
        self._wake.set()

    def stop(self, drain_timeout_ns: int = 2_000_000_000) -> bool:
        """Ship what is committed for up to `drain_timeout_ns`, then stop; True when caught up."""
        thread = self._thread
        if thread is None:
            return self.lag == 0
        self._drain_until_ns = time.monotonic_ns() + drain_timeout_ns
        self._stop.set()
        self._wake.set()
        thread.join(drain_timeout_ns / 1e9 + self._connect_timeout_s + 1)
        self._thread = None
        return self.lag == 0 and self.error is None

    @property
    def lag(self) -> int:
        """Strokes committed locally and not yet known to be in the database."""
        return max(0, self.committed_cycle - self.shipped_cycle)

    def status(self) -> dict[str, Any]:
        """Plain figures for the status reply and the metrics."""
        return {
            "url": self.where,
            "connected": self.connected,
            "shipped_cycle": self.shipped_cycle,
            "lag": self.lag,
            "shipped": self.shipped,
            "duplicates": self.duplicates,
            "runs_shipped": self.runs_shipped,
            "error": self.error,
            "error_count": self.error_count,
        }

    # -- the thread -------------------------------------------------------------------------------
    def _run(self) -> None:
        # At SCHED_OTHER: the shipper's process drops the real-time class it was started from before
        # it starts this thread (usmswitch.daemon.shipper_process), and threads inherit it.
        try:
            self._ship_until_stopped()
        except BaseException as exc:  # a bug: said in status and the log, never silent
            self.error = f"shipper thread died: {type(exc).__name__}: {exc}"
            log.exception("postgres shipper thread died", url=self.where)
            raise

    def _stopping(self) -> bool:
        if not self._stop.is_set():
            return False
        until = self._drain_until_ns
        return until is None or time.monotonic_ns() >= until or (self.connected and self.lag == 0)

    def _ship_until_stopped(self) -> None:
        reader: LocalRecords | None = None
        conn = None
        backoff = self._retry_ns[0]
        idle_since = time.monotonic_ns()
        while True:
            if reader is not None and self._stop.is_set():
                # Told to stop: caught up means up to the file's last commit, not to the last wake
                # (the final commits' wakes may not have come: their strokes were left silently).
                with contextlib.suppress(sqlite3.Error):
                    self.committed_cycle = max(self.committed_cycle, reader.last_cycle())
            if self._stopping():
                break
            try:
                if reader is None:
                    reader = LocalRecords(self.records_path)
                self.committed_cycle = max(self.committed_cycle, reader.last_cycle())
                if conn is None:
                    self.gate()
                    conn = self._connect(reader)
                    backoff = self._retry_ns[0]
                self.gate()
                began = time.monotonic_ns()
                moved = self._ship_batch(conn, reader)
                if moved and not self._stop.is_set():
                    self._stop.wait(REST_SHARE * (time.monotonic_ns() - began) / 1e9)
                if not moved:
                    if self._stop.is_set():
                        break  # caught up: nothing left to drain
                    now = time.monotonic_ns()
                    if now - idle_since >= IDLE_CHECK_NS:
                        idle_since = now
                        conn.execute("SELECT 1")
                    self._wake.wait(self._poll_ns / 1e9)
                    self._wake.clear()
                else:
                    idle_since = time.monotonic_ns()
            except (self._psycopg.Error, OSError, ShipperError, sqlite3.Error) as exc:
                self._fail(exc)
                if conn is not None:
                    conn.close()
                    conn = None
                self.connected = False
                if self._stop.wait(backoff / 1e9):
                    # Not reachable now: the rest ships at the next start. Told to stop before
                    # (or while) waiting to try again, not a try in the drain: a database that does
                    # not answer a connect held it for the connect timeout, past any exit budget.
                    break
                backoff = min(2 * backoff, self._retry_ns[1])
        if conn is not None:
            conn.close()
        self.connected = False
        if reader is not None:
            reader.close()

    def _fail(self, exc: BaseException) -> None:
        text = " ".join(str(exc).split()) or type(exc).__name__
        message = f"postgres {self.where}: {text}"
        self.error_count += 1
        if message != self.error:
            log.warning(
                "postgres shipping failing: records stay in SQLite and are shipped when it works",
                error=message,
                shipped_cycle=self.shipped_cycle,
                lag=self.lag,
            )
        self.error = message

    def _connect(self, reader: LocalRecords) -> Any:
        """Connect, create or check the tables, and find where to resume."""
        conn = self._psycopg.connect(
            self.url,
            connect_timeout=self._connect_timeout_s,
            autocommit=True,  # transactions only where asked: an idle shipper holds none open
            application_name=f"usmswitchd {self.rig}"[:63],
        )
        try:
            with conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (SCHEMA_LOCK_KEY,))
                self._ensure_schema(conn)
            with conn.transaction():
                conn.execute(CREATE_STAGE)
                last = conn.execute(LAST_SHIPPED, (self.rig,)).fetchone()
                self._run_from = conn.execute(RUNS_FROM, (self.rig,)).fetchone()[0]
            self._runs_sent = {}
            self._edits_after = 0
            shipped = 0 if last is None else last[0]
            if last is not None:
                self._check_same_file(reader, last)
        except BaseException:
            conn.close()
            raise
        self.shipped_cycle = shipped
        self.committed_cycle = max(self.committed_cycle, reader.last_cycle())
        self.connected = True
        if self.error is not None:
            log.info("postgres shipping works again", url=self.where, after=self.error)
            self.error = None
        log.info("postgres shipping", url=self.where, rig=self.rig, resume_after_cycle=shipped, lag=self.lag)
        return conn

    def _ensure_schema(self, conn: Any) -> None:
        exists = conn.execute("SELECT to_regclass(%s)", ("usmswitch_meta",)).fetchone()[0]
        row = conn.execute(SELECT_VERSION).fetchone() if exists else None
        version = None if row is None else int(row[0])
        if version is not None and version > PG_SCHEMA_VERSION:
            raise ShipperError(
                f"the database has usmswitch schema {version}; this daemon writes {PG_SCHEMA_VERSION}"
                " (upgrade usmswitch on this rig)"
            )
        if version != PG_SCHEMA_VERSION:
            for statement in SCHEMA:
                conn.execute(statement)
            for v in range((version or PG_SCHEMA_VERSION) + 1, PG_SCHEMA_VERSION + 1):
                for statement in MIGRATIONS[v]:
                    conn.execute(statement)
            conn.execute(SET_VERSION, (str(PG_SCHEMA_VERSION),))
            log.info(
                "postgres schema ready", url=self.where, schema_from=version, schema_to=PG_SCHEMA_VERSION
            )
        if conn.execute(MISSING_ADDITIONS).fetchone()[0] < len(LATER_RUN_FIELDS):
            for statement in ADDITIONS:
                conn.execute(statement)
            log.info("postgres schema gained columns", url=self.where, columns=list(LATER_RUN_FIELDS))

    def _check_same_file(self, reader: LocalRecords, last: tuple[int, int, int]) -> None:
        cycle, t_cmd_ns, wall_ns = last
        if reader.stamps(cycle) != (t_cmd_ns, wall_ns):
            raise ShipperError(
                f"the database holds strokes of rig {self.rig!r} up to cycle {cycle} that are not this"
                f" records file's ({self.records_path}): another daemon, or an earlier state directory,"
                " ships as this rig. Give this daemon its own [daemon] rig, or delete that rig's rows"
            )

    def _ship_batch(self, conn: Any, reader: LocalRecords) -> bool:
        """One transaction: the next strokes and the runs that changed. False when nothing was new."""
        fresh = [pg_run(r, self.rig) for r in reader.runs_from(self._run_from, MAX_RUNS_PER_PASS)]
        fresh = [row for row in fresh if self._runs_sent.get(row[0]) != row]  # an open run: once a change
        edits_after, edited = reader.edited_runs(self._edits_after)
        listed = {row[0] for row in fresh}
        runs = fresh + [row for row in (pg_run(r, self.rig) for r in edited) if row[0] not in listed]
        if reader.last_cycle() <= self.shipped_cycle and not runs:
            return False
        sent = inserted = last = 0
        rig = self.rig
        gate = self.gate
        with conn.transaction(), conn.cursor() as cur:
            with cur.copy(COPY_STAGE) as copy:
                for row in reader.cycles_after(self.shipped_cycle, self._batch, gate):
                    gate()
                    copy.write_row(pg_cycle(row, rig))
                    last = row[0]
                    sent += 1
            gate()
            if sent:
                cur.execute(INSERT_FROM_STAGE)
                inserted = cur.rowcount
            if runs:
                cur.executemany(UPSERT_RUN, runs)
        if sent:
            self.shipped_cycle = last
            self.committed_cycle = max(self.committed_cycle, last)
            self.shipped += inserted
            self.duplicates += sent - inserted
        self._edits_after = edits_after
        for row in runs:
            self._runs_sent[row[0]] = row
        self.runs_shipped += len(runs)
        if fresh:
            still_open = [row[0] for row in fresh if row[_RUN_END] is None]
            self._run_from = min(still_open) if still_open else fresh[-1][0] + 1
            self._runs_sent = {k: v for k, v in self._runs_sent.items() if k >= self._run_from}
        return True


def serve(settings: dict[str, Any], lines: Iterable[str], out: TextIO) -> None:
    """The shipper process's work: ship per `settings`, woken by `w` lines, until a `stop NS` line
    (drain for at most NS ns) or the end of `lines`; its status to `out` as JSON lines when it
    changed (at most every STATUS_EVERY_S) and once more at the end."""
    shipper = PostgresShipper(settings["records"], settings["url"], settings["rig"])
    shipper.start()
    said: dict[str, Any] = {}
    done = threading.Event()
    lock = threading.Lock()

    def report() -> None:
        nonlocal said
        with lock:
            status = shipper.status()
            if status != said:
                said = status
                out.write(json.dumps(status) + "\n")
                out.flush()

    def reporter() -> None:
        while not done.wait(STATUS_EVERY_S):
            report()

    threading.Thread(target=reporter, name="status", daemon=True).start()
    drain_ns = 0
    for line in lines:
        word, _, arg = line.strip().partition(" ")
        if word == "w":
            shipper.wake()
        elif word == "stop":
            drain_ns = int(arg or 0)
            break
    shipper.stop(drain_timeout_ns=drain_ns)
    done.set()
    report()
