"""The cycle records: one SQLite (WAL) row per stroke, written off the loop by a background thread.

The loop calls `submit(record)`: a put on a queue.SimpleQueue, no I/O, no lock held for long. The
writer thread drains the queue and commits a transaction whenever the queue runs dry (or every
`max_batch` rows under a flood), so a stroke is on disk within about a millisecond of its submit.

Durability: journal_mode=WAL with synchronous=NORMAL. A commit has then been written to the WAL
file by write(2) before COMMIT returns, so the process dying (kill -9, a crash) loses nothing
committed, and WAL recovery keeps the file consistent. What NORMAL gives up against FULL is only
the last transactions on a power cut or kernel crash (the file still opens, consistent): an fsync
per stroke would cost milliseconds on slow storage and buy little for a record of strokes.

Writer failures (disk full, read-only, locked, and the file deleted or replaced under the writer,
which would otherwise swallow every commit into an unlinked inode) are kept in `writer_error`,
logged, and retried with backoff; the records wait in memory (up to `max_pending`, past which the
oldest are dropped and counted), so the loop never stalls and nothing is lost silently. The store
stamps each record with its `driver` and `rig`. Reads use their own read-only connection per
thread and never wait on the writer. Schema: docs/records.md.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import re
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import structlog

from usmswitch.protocol.record import CycleRecord, RunRecord
from usmswitch.protocol.records_schema import (
    INSERT_CYCLE,
    INSERT_EVENT,
    MIGRATIONS,
    READABLE_VERSIONS,
    SCHEMA,
    SCHEMA_VERSION,
    SELECT_BY_VERSION,
    SELECT_CYCLES,
    UPSERT_RUN,
    add_to_schema,
)
from usmswitch.runtime.realtime import drop_realtime

from .records_queries import RecordQueries, RecordStoreError
from .retention import Retention
from .run_aggregates import AggregateKeeper
from .wal import settle_wal

log = structlog.get_logger("usmswitch.records")

#: How often an idle writer checks that its file is still the one at its path.
FILE_CHECK_NS = 200_000_000

_EVENT_KIND = re.compile(r"^[a-z][a-z0-9_]{0,31}$")
_EVENT_RESERVED = frozenset({"id", "wall_ns", "after_cycle", "kind"})


class RecordFileGone(Exception):
    """The file at the store's path is no longer the one it writes (deleted or replaced)."""


class _Flush:
    """A marker in the queue: set once everything queued before it is committed."""

    __slots__ = ("done",)

    def __init__(self) -> None:
        self.done = threading.Event()


_STOP = object()


class _Write:
    """A marker in the queue: `fn(conn)` run in the batch's transaction (a savepoint of its own, so
    a refusal undoes only itself), its result or error given to `done` once the batch is committed."""

    __slots__ = ("done", "error", "fn", "result")

    def __init__(self, fn: Callable[[sqlite3.Connection], Any]) -> None:
        self.fn = fn
        self.done: Future[Any] = Future()
        self.result: Any = None
        self.error: BaseException | None = None


class RecordStore(RecordQueries):
    """The cycle records and events in one SQLite file; `submit` is safe to call from the loop."""

    def __init__(
        self,
        path: str | Path,
        *,
        readonly: bool = False,
        synchronous: str = "NORMAL",
        max_batch: int = 2000,
        max_pending: int = 1_000_000,
        busy_timeout_ns: int = 200_000_000,
        retry_ns: tuple[int, int] = (50_000_000, 2_000_000_000),
        driver: str | None = None,
        rig: str | None = None,
        file_mode: int = 0o640,
        wait_when_behind: int = 0,
    ) -> None:
        """`wait_when_behind`: past this many records not yet written, `submit` waits for the writer
        to catch up to half of it (0: never waits). For a loop in virtual time, which makes strokes
        faster than SQLite takes them: waiting costs it nothing, piling them up costs memory and,
        past `max_pending`, records."""
        self.path = Path(path)
        self.readonly = readonly
        #: Stamped on every record submitted without its own (the daemon's driver and rig).
        self.driver = driver
        self.rig = rig
        if file_mode & ~0o666:
            raise ValueError(f"file_mode {oct(file_mode)} has bits beyond read and write")
        self._file_mode = file_mode
        self._identity: tuple[int, int] | None = None  # (st_dev, st_ino) of the file the writer opened
        self._select = SELECT_CYCLES
        self.schema_version = SCHEMA_VERSION
        if synchronous.upper() not in ("OFF", "NORMAL", "FULL", "EXTRA"):
            raise ValueError(f"synchronous must be OFF, NORMAL, FULL or EXTRA, got {synchronous!r}")
        if max_batch < 1 or max_pending < max_batch:
            raise ValueError(f"need 1 <= max_batch <= max_pending, got {max_batch} and {max_pending}")
        self._max_batch = max_batch
        self._max_pending = max_pending
        self._busy_timeout_ms = max(1, busy_timeout_ns // 1_000_000)
        self._retry_ns = retry_ns
        self._local = threading.local()
        self._readers: list[sqlite3.Connection] = []
        self._readers_lock = threading.Lock()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        if wait_when_behind < 0 or (wait_when_behind and wait_when_behind >= max_pending):
            raise ValueError(f"wait_when_behind must be in 0..max_pending-1, got {wait_when_behind}")
        self._wait_when_behind = wait_when_behind
        self._caught_up = threading.Condition()
        #: Times `submit` waited for the writer (wait_when_behind), and for how long in all.
        self.waits = 0
        self.waited_ns = 0
        self._closed = False
        self._last_submitted_cycle: int | None = None
        #: Records handed to `submit`.
        self.submitted = 0
        #: Records committed to the file by this store.
        self.written = 0
        #: Events committed to the file by this store.
        self.events_written = 0
        #: Run rows (opens and ends) committed to the file by this store.
        self.runs_written = 0
        #: Records the database refused for good (a duplicate cycle number, a violated CHECK).
        self.rejected = 0
        #: Records dropped because the writer failed for so long that `max_pending` was reached.
        self.dropped = 0
        #: Failed write attempts since the store opened.
        self.error_count = 0
        self._writer_error: str | None = None
        self.last_error: str | None = None
        #: Called on the writer thread with each batch of records once committed (and not
        #: rejected): what the daemon publishes, so a subscriber never sees a stroke the file lacks.
        self.on_commit: Callable[[list[CycleRecord]], None] | None = None
        #: Called on the writer thread with each run row once committed, in order with the records:
        #: a run's end reaches it after every stroke of the run has reached `on_commit`.
        self.on_run: Callable[[RunRecord], None] | None = None
        #: The retention policy the writer applies (daemon/retention.py; None: keep all).
        self.retention: Retention | None = None
        #: Called before each batch is written: the daemon makes it wait while the loop is about
        #: to start a stroke (the writer's Python work would hold the GIL the loop needs).
        self.gate: Callable[[], object] = lambda: None
        self._thread: threading.Thread | None = None
        if readonly:
            if not self.path.exists():
                raise RecordStoreError(f"record file {self.path} does not exist")
            self._writer = None
            self._closed = True  # nothing may be submitted to a read-only store
            self.schema_version = self._check_schema(self._reader())
            self._select = SELECT_BY_VERSION.get(self.schema_version, SELECT_CYCLES)
            return
        self._writer = self._open_writer(synchronous.upper())
        row = self._writer.execute("SELECT max(cycle) FROM cycles").fetchone()
        self._last_submitted_cycle = row[0]
        self._thread = threading.Thread(target=self._run, name="usmswitch-records", daemon=True)
        self._thread.start()

    # -- the loop's side ---------------------------------------------------------------------
    def submit(self, record: CycleRecord) -> None:
        """Queue one stroke's record for writing; never blocks, never touches the disk."""
        self._stamp(record, CycleRecord, "submit")
        self.submitted += 1
        self._last_submitted_cycle = record.cycle
        self._queue.put(record)
        if self._wait_when_behind and self.backlog > self._wait_when_behind:
            self._wait_for_writer()

    def _wait_for_writer(self) -> None:
        """Block until the backlog is half the limit (or the writer fails: then records wait in
        memory as they would in real time, bounded by max_pending)."""
        t0 = time.monotonic_ns()
        self.waits += 1
        with self._caught_up:
            while (
                self.backlog > self._wait_when_behind // 2 and self._writer_error is None and not self._closed
            ):
                self._caught_up.wait(0.1)
        self.waited_ns += time.monotonic_ns() - t0

    def record_event(self, kind: str, /, **fields: Any) -> None:
        """Queue an event (target or mode change, fault, reset, estop ...) in order with the records."""
        if self._closed:
            raise RecordStoreError(f"record store {self.path} is closed (or read-only)")
        if not isinstance(kind, str) or not _EVENT_KIND.match(kind):
            raise ValueError(f"event kind must be a lower-case word like 'target', got {kind!r}")
        clash = _EVENT_RESERVED.intersection(fields)
        if clash:
            raise ValueError(f"event field name(s) {sorted(clash)} are reserved")
        try:
            data = json.dumps(fields, allow_nan=False, sort_keys=True)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"event {kind!r} fields {fields!r} are not plain JSON values: {exc}") from None
        self._queue.put((time.time_ns(), self._last_submitted_cycle, kind, data))

    def submit_run(self, run: RunRecord) -> None:
        """Queue a run's row (at its open, and again at its end), in order with the records."""
        self._stamp(run, RunRecord, "submit_run")
        self._queue.put(RunRecord(**run.to_dict()))  # a copy: the loop goes on changing its own

    def write(self, fn: Callable[[sqlite3.Connection], Any]) -> Future[Any]:
        """Queue `fn(conn)` for the writer (run edits, the queue of runs): run in the transaction of
        its batch, after the batch's strokes and run rows, so it sees everything queued before it;
        the future has its result once committed, or the exception it raised."""
        if self._closed:
            raise RecordStoreError(f"record store {self.path} is closed (or read-only)")
        item = _Write(fn)
        self._queue.put(item)
        return item.done

    def _stamp(self, item: CycleRecord | RunRecord, kind: type, call: str) -> None:
        """Refuse what cannot be queued; stamp the store's driver and rig where the item has none."""
        if self._closed:
            raise RecordStoreError(f"record store {self.path} is closed (or read-only)")
        if type(item) is not kind:
            raise TypeError(f"{call} takes a {kind.__name__}, got {type(item).__name__}")
        if item.driver is None:
            item.driver = self.driver
        if item.rig is None:
            item.rig = self.rig

    def flush(self, timeout_ns: int = 5_000_000_000) -> bool:
        """Wait until everything submitted so far is committed; False if that took over `timeout_ns`."""
        if self._thread is None or not self._thread.is_alive():
            return self._queue.empty()
        marker = _Flush()
        self._queue.put(marker)
        return marker.done.wait(timeout_ns / 1e9)

    def close(self, timeout_ns: int | None = 10_000_000_000) -> bool:
        """Write everything still queued, stop the writer, close the file; False if records were left.

        A writer not done within `timeout_ns` (None: however long it takes) is left running, holding
        the file: its -wal and -shm stay until it ends, and for good if the process exits first."""
        if self._closed and self._thread is None:
            self._close_readers()  # opened since (a count after the close)
            if not self.readonly:
                settle_wal(self.path)
            return True
        self._closed = True
        left = True
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join(None if timeout_ns is None else timeout_ns / 1e9)
            left = not self._thread.is_alive()
            if not left:
                log.error("record writer did not finish in time", path=str(self.path), backlog=self.backlog)
            else:
                self._thread = None
        self._close_readers()
        if left and not self.readonly:
            settle_wal(self.path)  # no -wal and -shm left beside the file (daemon/wal.py)
        return left and self.backlog == 0

    def __enter__(self) -> RecordStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def writer_error(self) -> str | None:
        """The error the writer is failing with now (None when writing works)."""
        return self._writer_error

    @property
    def backlog(self) -> int:
        """Records submitted but not yet committed, rejected or dropped."""
        return self.submitted - self.written - self.rejected - self.dropped

    def stats(self) -> dict[str, Any]:
        """Counters for the status reply and the summary log line."""
        return {
            "path": str(self.path),
            "submitted": self.submitted,
            "written": self.written,
            "events_written": self.events_written,
            "runs_written": self.runs_written,
            "backlog": self.backlog,
            "rejected": self.rejected,
            "dropped": self.dropped,
            "error_count": self.error_count,
            "writer_error": self._writer_error,
        }

    # -- connections ------------------------------------------------------------------------------
    def _open_writer(self, synchronous: str) -> sqlite3.Connection:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._restrict_files()
            conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            conn.execute(f"PRAGMA busy_timeout = {self._busy_timeout_ms}")
            mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if mode.lower() != "wal":
                raise RecordStoreError(f"record file {self.path}: journal_mode is {mode!r}, WAL refused")
            conn.execute(f"PRAGMA synchronous = {synchronous}")
            # Keep the WAL file from staying huge after a burst (it is reset at each checkpoint).
            conn.execute("PRAGMA journal_size_limit = 67108864")
            version = self._check_schema(conn)
            if version < SCHEMA_VERSION:
                self._migrate(conn, version)
            conn.executescript(SCHEMA)
            self._add_to_schema(conn)
            conn.execute(
                "INSERT OR IGNORE INTO meta (key, value)"
                " VALUES ('schema_version', ?), ('created_wall_ns', ?)",
                (str(SCHEMA_VERSION), str(time.time_ns())),
            )
            self._aggregates = AggregateKeeper(SELECT_CYCLES, str(self.path))
            self._aggregates.open(conn)
            # The -wal and -shm files exist now (SQLite gives them the main file's mode).
            self._restrict_files()
            st = os.stat(self.path)
            self._identity = (st.st_dev, st.st_ino)
        except (sqlite3.Error, OSError) as exc:
            raise RecordStoreError(f"record file {self.path}: {exc}") from exc
        return conn

    def _restrict_files(self) -> None:
        """The file and its -wal/-shm readable by nobody beyond `file_mode` (0640: owner and group).

        A new file is created with that mode before SQLite opens it (SQLite gives the -wal and -shm
        files the main file's mode); an existing one that is looser is tightened.
        """
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, self._file_mode)
        except FileExistsError:
            pass
        else:
            os.close(fd)
        for suffix in ("", "-wal", "-shm"):
            p = Path(f"{self.path}{suffix}")
            try:
                mode = os.stat(p).st_mode & 0o7777
            except FileNotFoundError:
                continue
            if mode & ~self._file_mode:
                os.chmod(p, mode & self._file_mode)

    def _migrate(self, conn: sqlite3.Connection, version: int) -> None:
        """An older file brought to SCHEMA_VERSION in one transaction, every row kept: the columns
        added since read NULL (unknown source, no run)."""
        rows = conn.execute("SELECT count(*) FROM cycles").fetchone()[0]
        steps = " ".join(MIGRATIONS[v] for v in range(version + 1, SCHEMA_VERSION + 1))
        conn.executescript(
            f"BEGIN IMMEDIATE; {steps}"
            f" UPDATE meta SET value = '{SCHEMA_VERSION}' WHERE key = 'schema_version'; COMMIT;"
        )
        log.info(
            "record file migrated",
            path=str(self.path),
            schema_from=version,
            schema_to=SCHEMA_VERSION,
            rows=rows,
        )

    def _add_to_schema(self, conn: sqlite3.Connection) -> None:
        """Schema 3's additions (run labels and notes) in one transaction; the version stays 3, so
        readers that predate them still read the file (docs/records.md, "Migration")."""
        conn.execute("BEGIN IMMEDIATE")
        try:
            added = add_to_schema(conn)
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        if added:
            log.info("record file gained columns", path=str(self.path), columns=added)

    def _check_schema(self, conn: sqlite3.Connection) -> int:
        """The file's schema version (SCHEMA_VERSION for a new, empty file); refuses one it cannot read."""
        try:
            has_meta = conn.execute(
                "SELECT 1 FROM sqlite_master WHERE type='table' AND name='meta'"
            ).fetchone()
            if not has_meta:
                if self.readonly:
                    raise RecordStoreError(f"record file {self.path} has no usmswitch schema")
                return SCHEMA_VERSION
            row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        except sqlite3.Error as exc:
            raise RecordStoreError(f"record file {self.path}: {exc}") from exc
        if row is None:
            return SCHEMA_VERSION
        if row[0] not in {str(v) for v in READABLE_VERSIONS}:
            raise RecordStoreError(
                f"record file {self.path} has schema version {row[0]};"
                f" this daemon reads versions {', '.join(map(str, READABLE_VERSIONS))}"
            )
        return int(row[0])

    def _check_file(self) -> None:
        """Raise RecordFileGone unless the path still names the file the writer has open."""
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            raise RecordFileGone(f"record file {self.path} deleted under the writer") from None
        except OSError as exc:
            raise RecordFileGone(f"record file {self.path} cannot be checked: {exc}") from None
        if (st.st_dev, st.st_ino) != self._identity:
            raise RecordFileGone(f"record file {self.path} replaced under the writer (another file is there)")

    # -- the writer thread ----------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._run_writer()
        except BaseException as exc:
            # A bug here must not pass silently: the status shows it and close() reports the backlog.
            self._writer_error = f"record writer thread died: {type(exc).__name__}: {exc}"
            log.exception("record writer thread died", path=str(self.path))
            raise

    def _run_writer(self) -> None:
        drop_realtime()
        conn = self._writer
        assert conn is not None
        pending: deque[Any] = deque()  # records and events taken off the queue, not yet committed
        waiters: list[tuple[int, _Flush]] = []  # flush markers and how many items precede them
        taken = 0  # items ever moved into `pending`
        done = 0  # items ever committed or rejected
        stopping = False
        retry_at = 0
        backoff = self._retry_ns[0]
        next_check = time.monotonic_ns() + FILE_CHECK_NS
        while True:
            # Block for work only when nothing is waiting to be written, and never for longer than
            # the file check's period: a file deleted while idle is noticed before the next stroke.
            item: Any = None
            try:
                if not pending and not stopping:
                    item = self._queue.get(timeout=FILE_CHECK_NS / 1e9)
                elif self._writer_error is not None and not stopping:
                    item = self._queue.get(timeout=max(0, retry_at - time.monotonic_ns()) / 1e9)
            except queue.Empty:
                item = None
            while True:
                if item is _STOP:
                    stopping = True
                elif isinstance(item, _Flush):
                    waiters.append((taken, item))
                elif item is not None:
                    pending.append(item)
                    taken += 1
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
            if len(pending) > self._max_pending:
                excess = len(pending) - self._max_pending
                lost = 0
                for _ in range(excess):
                    if isinstance(pending.popleft(), CycleRecord):
                        lost += 1
                self.dropped += lost
                done += excess
                log.error(
                    "record writer backlog full: oldest records dropped", dropped=lost, path=str(self.path)
                )
            now = time.monotonic_ns()
            if not pending:
                self._retain(conn)
            if not pending and self._writer_error is None and now >= next_check:
                next_check = now + FILE_CHECK_NS
                try:
                    self._check_file()
                except RecordFileGone as exc:
                    self._fail(conn, exc)
                    retry_at = now + backoff
            if pending and (self._writer_error is None or now >= retry_at or stopping):
                while pending:
                    self.gate()
                    batch = self._next_batch(pending)
                    try:
                        self._check_file()
                        counts = self._write(conn, batch)
                        # Committed into the file we opened: is that still the file at the path?
                        # If not, the batch went to an unlinked (or moved) file: keep it.
                        self._check_file()
                    except (sqlite3.Error, RecordFileGone) as exc:
                        pending.extendleft(reversed(batch))
                        self._fail(conn, exc)
                        retry_at = time.monotonic_ns() + backoff
                        backoff = min(2 * backoff, self._retry_ns[1])
                        break
                    self._count(counts)
                    if self._writer_error is not None:  # the strokes are in: said at once
                        log.info("record writer recovered", path=str(self.path), after=self._writer_error)
                        self._writer_error = None
                        backoff = self._retry_ns[0]
                    if self._wait_when_behind:
                        with self._caught_up:
                            self._caught_up.notify_all()
                    rejected = {*counts[4], *(c for c, _ in counts[3])}
                    self._tell_committed(batch, rejected)
                    # The runs' statistics after what waits on the strokes (subscribers, the
                    # shipper, the recovery): their own transaction, its failure only logged.
                    self._fold_aggregates(conn, batch, rejected)
                    self._retain(conn)  # a run that ended in this batch, before the strokes after it
                    next_check = time.monotonic_ns() + FILE_CHECK_NS
                    done += len(batch)
                    batch = []  # the records are on disk: hold none of them while idle
            elif not pending and self._writer_error is not None and now >= retry_at:
                # Failing with nothing to write (the file vanished while idle): recovered only
                # if the path names our file again.
                try:
                    self._check_file()
                except RecordFileGone:
                    retry_at = now + backoff
                    backoff = min(2 * backoff, self._retry_ns[1])
                else:
                    log.info("record writer recovered", path=str(self.path), after=self._writer_error)
                    self._writer_error = None
                    backoff = self._retry_ns[0]
            still = []
            for n, marker in waiters:
                if n <= done:
                    marker.done.set()
                else:
                    still.append((n, marker))
            waiters = still
            if stopping and (not pending or self._writer_error is not None):
                if pending and self._writer_error is not None:
                    # close() asked to stop while writing fails: try until close() gives up on us.
                    time.sleep(max(0, retry_at - time.monotonic_ns()) / 1e9)
                    continue
                self._finish(conn)
                for _, marker in waiters:
                    marker.done.set()
                return

    def _next_batch(self, pending: deque[Any]) -> list[Any]:
        """Up to max_batch items off `pending`; with retention kept, a run's end ends its batch, so
        the run is moved before the strokes after it are written: a backlog (a writer behind, a
        disk back) grows the file by one run past keep_bytes, not by a batch of many runs."""
        retained = self.retention is not None
        batch = []
        while pending and len(batch) < self._max_batch:
            item = pending.popleft()
            batch.append(item)
            if retained and type(item) is RunRecord and item.last_cycle is not None:
                break
        return batch

    def _write(
        self, conn: sqlite3.Connection, batch: list[Any]
    ) -> tuple[int, int, int, list[tuple[int, str]], list[int]]:
        """Commit one batch; (written, rejected, events, unconvertible, rejected cycles) for `_count`."""
        cycles = []
        events = []
        runs = []
        unconvertible: list[tuple[int, str]] = []
        writes = []
        for item in batch:
            if type(item) is tuple:
                events.append(item)
                continue
            if type(item) is _Write:
                writes.append(item)
                continue
            if type(item) is RunRecord:
                runs.append(item.to_row())
                continue
            try:
                cycles.append(item.to_row())
            except (TypeError, ValueError) as exc:
                unconvertible.append((item.cycle, str(exc)))
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.execute("SAVEPOINT batch")
            try:
                conn.executemany(INSERT_CYCLE, cycles)
                rejected: list[int] = []
            except (sqlite3.IntegrityError, OverflowError):
                # One bad row (a duplicate cycle, a CHECK, an int past 64 bits) fails the statement
                # after the rows before it went in: undo them and go row by row, so the good rows
                # land and only the bad one is rejected.
                conn.execute("ROLLBACK TO batch")
                rejected = self._insert_one_by_one(conn, cycles)
            conn.execute("RELEASE batch")
            if events:
                conn.executemany(INSERT_EVENT, events)
            if runs:
                conn.executemany(UPSERT_RUN, runs)
            for w in writes:
                conn.execute("SAVEPOINT write")
                try:
                    w.result, w.error = w.fn(conn), None
                except sqlite3.OperationalError:
                    raise  # the file's trouble (locked, full): the batch is retried
                except Exception as exc:
                    conn.execute("ROLLBACK TO write")
                    w.error = exc
                conn.execute("RELEASE write")
            conn.execute("COMMIT")
        except BaseException:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            raise
        return len(cycles) - len(rejected), len(rejected), len(events), unconvertible, rejected

    def _count(self, counts: tuple[int, int, int, list[tuple[int, str]], list[int]]) -> None:
        """Counted once the batch is in the file at our path: a failed batch is retried whole."""
        written, rejected, events, unconvertible, _ = counts
        for cycle, reason in unconvertible:
            self.last_error = f"cycle {cycle} rejected: {reason}"
            log.error("cycle record rejected: a field is not a plain value", cycle=cycle, reason=reason)
        self.written += written
        self.rejected += rejected + len(unconvertible)
        self.events_written += events

    def _fold_aggregates(self, conn: sqlite3.Connection, batch: list[Any], rejected: set[int]) -> None:
        """The committed strokes into their runs' statistics (saved in a transaction of their own:
        a failure there is logged and the save tried again, the strokes are safe already)."""
        records = [r for r in batch if type(r) is CycleRecord and r.cycle not in rejected]
        ended = {r.run_id for r in batch if type(r) is RunRecord and r.end_reason is not None}
        self.gate()  # Python work: not while the loop is about to start a stroke
        try:
            self._aggregates.fold(conn, records, ended)
        except sqlite3.Error as exc:
            log.warning("run statistics not saved", path=str(self.path), error=str(exc))

    def _retain(self, conn: sqlite3.Connection) -> None:
        """Apply the retention policy when it is due (daemon/retention.py)."""
        retention = self.retention
        if retention is None or self._writer_error is not None or not retention.due(time.monotonic_ns()):
            return
        try:
            retention.apply(conn)
        except sqlite3.Error as exc:  # the strokes stay where they are: tried again later
            log.warning("retention failed", path=str(self.path), error=str(exc))

    def _tell_committed(self, batch: list[Any], rejected: set[int]) -> None:
        """Hand the records and runs now in the file to `on_commit` and `on_run`, in the order they
        were submitted (a subscriber sees only what is kept, and a run's end after its strokes)."""
        records: list[CycleRecord] = []
        for item in batch:
            if type(item) is CycleRecord:
                if item.cycle not in rejected:
                    records.append(item)
            elif type(item) is RunRecord:
                self.runs_written += 1
                if item.last_cycle is not None and self.retention is not None:
                    self.retention.run_ended()
                self._tell(self.on_commit, records)
                records = []
                self._tell(self.on_run, item)
            elif type(item) is _Write:
                if item.error is None:
                    item.done.set_result(item.result)
                else:
                    item.done.set_exception(item.error)
        self._tell(self.on_commit, records)

    def _tell(self, listener: Callable[[Any], None] | None, what: Any) -> None:
        if listener is None or (type(what) is list and not what):
            return
        try:
            listener(what)
        except Exception:  # a listener's bug must not stop the writing
            log.exception("record commit listener failed", path=str(self.path))

    def _insert_one_by_one(self, conn: sqlite3.Connection, rows: list[tuple[Any, ...]]) -> list[int]:
        rejected: list[int] = []
        for row in rows:
            try:
                conn.execute(INSERT_CYCLE, row)
            except (sqlite3.IntegrityError, OverflowError) as exc:
                rejected.append(row[0])
                self.last_error = f"cycle {row[0]} rejected: {exc}"
                log.error("cycle record rejected by the database", cycle=row[0], reason=str(exc))
        return rejected

    def _fail(self, conn: sqlite3.Connection, exc: sqlite3.Error | RecordFileGone) -> None:
        message = str(exc) if isinstance(exc, RecordFileGone) else f"{type(exc).__name__}: {exc}"
        self.error_count += 1
        self.last_error = message
        if conn.in_transaction:
            with contextlib.suppress(sqlite3.Error):
                conn.execute("ROLLBACK")
        if message != self._writer_error:
            log.error(
                "record writer failing, records kept in memory and retried",
                path=str(self.path),
                error=message,
            )
        self._writer_error = message

    def _finish(self, conn: sqlite3.Connection) -> None:
        """Make every commit durable, then close without waiting for anyone.

        The WAL is fsynced (synchronous=NORMAL syncs it only at checkpoints), so what was committed
        survives a power cut after the exit. The checkpoint is PASSIVE: a TRUNCATE one waits on
        the busy handler for every reader (the shipper catching up, a history being read), and
        took 80 ms of a 100 ms SIGTERM-to-exit. Closing the last connection then folds the WAL
        into the file and removes it; with a reader still open it stays, and the next open of
        the file reads it (nothing is lost either way).
        """
        try:
            with open(f"{self.path}-wal", "rb") as wal:
                os.fsync(wal.fileno())
        except FileNotFoundError:
            pass  # nothing was written since the last checkpoint removed it
        except OSError as exc:
            log.warning("record file WAL sync at close failed", path=str(self.path), error=str(exc))
        with contextlib.suppress(sqlite3.Error):
            self._aggregates.flush(conn)
        try:
            conn.execute("PRAGMA wal_checkpoint(PASSIVE)")
        except sqlite3.Error as exc:
            log.warning("record file checkpoint at close failed", path=str(self.path), error=str(exc))
        conn.close()


def open_reader(path: str) -> RecordStore:
    """A read-only store on the records file, for the socket's server process, which imports this
    by name (`RpcServer(records_reader=...)`); a file it cannot open is an OSError saying why."""
    try:
        return RecordStore(path, readonly=True)
    except RecordStoreError as exc:
        raise OSError(str(exc)) from None
