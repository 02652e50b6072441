"""The records file's reads (`RecordQueries`, the read side of `records.RecordStore`): any thread,
each thread on its own read-only connection, never waiting on the writer. Schema: docs/records.md.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterator
from typing import Any
from urllib.parse import quote

from usmswitch.protocol.record import UNUSABLE, CycleRecord, RunRecord
from usmswitch.protocol.record_csv import BadCell, csv_text_chunks

from .run_aggregates import label_stats, run_stats


class RecordStoreError(Exception):
    """The record file cannot be opened or used; the message names the path and the reason."""


class RecordQueries:
    """Reads of a records file. The store sets `path`, `schema_version`, `_select` (the cycles
    SELECT for its schema), `_busy_timeout_ms` and the per-thread readers (`_local`, `_readers`,
    `_readers_lock`)."""

    path: Any
    schema_version: int
    _select: str
    _busy_timeout_ms: int
    _local: threading.local
    _readers: list[sqlite3.Connection]
    _readers_lock: threading.Lock

    def last_cycle(self) -> int:
        """The highest cycle number in the file (0 when empty): the next stroke is this + 1."""
        row = self._reader().execute("SELECT max(cycle) FROM cycles").fetchone()
        return row[0] or 0

    def count(self) -> int:
        """How many strokes the file holds."""
        return self._reader().execute("SELECT count(*) FROM cycles").fetchone()[0]

    def last_strokes(
        self,
        direction: int,
        n: int,
        exclude_flags: int = UNUSABLE,
        *,
        driver: str | None = None,
        rig: str | None = None,
    ) -> list[int]:
        """The last `n` operating times (ns) of one direction, oldest first: a predictor's warm start.

        With `driver` and/or `rig`, only strokes that driver made on that rig: a real rig never
        warm-starts from simulated strokes or another rig's (rows of unknown source never match).
        """
        if direction not in (0, 1):
            raise ValueError(f"direction must be 0 (on) or 1 (off), got {direction!r}")
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        where = "direction = ? AND operating_ns IS NOT NULL AND (flags & ?) = 0"
        args: list[Any] = [direction, int(exclude_flags)]
        for column, value in (("driver", driver), ("rig", rig)):
            if value is not None:
                if self.schema_version < 2:
                    return []  # a schema 1 file does not know where its strokes came from
                where += f" AND {column} = ?"
                args.append(value)
        rows = (
            self._reader()
            .execute(f"SELECT operating_ns FROM cycles WHERE {where} ORDER BY cycle DESC LIMIT ?", (*args, n))
            .fetchall()
        )
        return [r[0] for r in reversed(rows)]

    def history(self, n: int, direction: int | None = None, run_id: int | None = None) -> list[CycleRecord]:
        """The last `n` records (of one direction, or both; of one run, or any), oldest first."""
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        where, args = self._where(direction=direction, run_id=run_id)
        sql = f"{self._select}{where} ORDER BY cycle DESC LIMIT ?"
        rows = self._reader().execute(sql, (*args, n)).fetchall()
        return [CycleRecord.from_row(r) for r in reversed(rows)]

    def _where(self, **equal: int | None) -> tuple[str, list[Any]]:
        """A WHERE clause for the columns given a value (None: any); run_id on an old file: none."""
        terms, args = [], []
        for column, value in equal.items():
            if value is not None:
                if column == "run_id" and self.schema_version < 3:
                    terms.append("0")  # a file from before runs has no run's strokes
                    continue
                terms.append(f"{column} = ?")
                args.append(value)
        return (" WHERE " + " AND ".join(terms) if terms else ""), args

    def iter_records(
        self, first: int = 1, last: int | None = None, chunk: int = 1000, run_id: int | None = None
    ) -> Iterator[CycleRecord]:
        """Every record from cycle `first` to `last` (of one run, or any) in order, read in chunks.

        Each chunk is its own short read, so a long export never pins the WAL.
        """
        after = first - 1
        stop = last if last is not None else (1 << 63) - 1
        where, args = self._where(run_id=run_id)
        where = f"{where} AND" if where else " WHERE"
        while True:
            rows = (
                self._reader()
                .execute(
                    f"{self._select}{where} cycle > ? AND cycle <= ? ORDER BY cycle LIMIT ?",
                    (*args, after, stop, chunk),
                )
                .fetchall()
            )
            if not rows:
                return
            for r in rows:
                yield CycleRecord.from_row(r)
            after = rows[-1]["cycle"]

    def csv_chunks(
        self,
        first: int = 1,
        last: int | None = None,
        run_id: int | None = None,
        chunk: int = 10_000,
        label: str | None = None,
    ) -> Iterator[tuple[int, int, str]]:
        """The records (of a run, of the runs with a label) as CSV text (record_csv's lines), `chunk`
        strokes a read, each chunk's text built by SQLite in one short statement: (strokes, last
        cycle, text). What the exports stream (issue 36: within 2x `sqlite3 -csv`); ValueError where
        a cell is not what it should be."""
        try:
            yield from csv_text_chunks(self._reader(), first, last, run_id, chunk, label=label)
        except BadCell as exc:
            raise ValueError(f"record file {self.path}: {exc}") from None

    def runs(self, n: int = 20, label: str | None = None) -> list[RunRecord]:
        """The last `n` runs (with that label), oldest first (none in a file from before runs)."""
        if self.schema_version < 3:
            return []
        where, args = ("", ()) if label is None else (" WHERE label = ?", (label,))
        try:
            rows = (
                self._reader()
                .execute(f"SELECT * FROM runs{where} ORDER BY run_id DESC LIMIT ?", (*args, n))
                .fetchall()
            )
        except sqlite3.OperationalError:  # read-only, a file from before labels: no run has one
            return []
        return [RunRecord.from_row(r) for r in reversed(rows)]

    def label_stats(self, label: str, n: int = 1000) -> dict[str, Any]:
        """The statistics of the last `n` runs with `label`, pooled and per run (`run_aggregates`)."""
        return label_stats(self._reader(), self._select, label, self.runs(n, label))

    def run(self, run_id: int) -> RunRecord | None:
        """One run by its id, or None."""
        if self.schema_version < 3:
            return None
        row = self._reader().execute("SELECT * FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        return None if row is None else RunRecord.from_row(row)

    def last_run_id(self) -> int:
        """The highest run id in the file (0 when none): the next run is this + 1."""
        if self.schema_version < 3:
            return 0
        return self._reader().execute("SELECT max(run_id) FROM runs").fetchone()[0] or 0

    def events(self, kind: str | None = None, n: int = 100) -> list[dict[str, Any]]:
        """The last `n` events (of one kind, or all), oldest first, with their fields merged in."""
        if kind is None:
            sql, args = "SELECT * FROM events ORDER BY id DESC LIMIT ?", (n,)
        else:
            sql, args = "SELECT * FROM events WHERE kind = ? ORDER BY id DESC LIMIT ?", (kind, n)
        out = []
        for r in reversed(self._reader().execute(sql, args).fetchall()):
            ev = {"id": r["id"], "wall_ns": r["wall_ns"], "after_cycle": r["after_cycle"], "kind": r["kind"]}
            ev.update(json.loads(r["data"]))
            out.append(ev)
        return out

    def run_stats(self, run_id: int) -> dict[str, Any] | None:
        """A run's statistics from its aggregate kept as its strokes were written (None: no such
        run, or one with none yet: scan its strokes, `stats.stats_of_records`)."""
        run = self.run(run_id)
        if run is None:
            return None
        return run_stats(self._reader(), self._select, run)

    # -- connections ------------------------------------------------------------------------------
    def _reader(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            uri = f"file:{quote(str(self.path.resolve()))}?mode=ro"
            try:
                conn = sqlite3.connect(uri, uri=True, check_same_thread=False)
                conn.execute(f"PRAGMA busy_timeout = {self._busy_timeout_ms}")
            except sqlite3.Error as exc:
                raise RecordStoreError(f"record file {self.path}: {exc}") from exc
            conn.row_factory = sqlite3.Row
            self._local.conn = conn
            with self._readers_lock:
                self._readers.append(conn)
        return conn

    def release(self) -> None:
        """Close the read connections (the next read opens its own again): a process that reads
        between requests (the socket's records readers) then holds no file open while idle, and
        the writer's last close removes -wal and -shm (daemon/wal.py)."""
        self._close_readers()

    def _close_readers(self) -> None:
        with self._readers_lock:
            readers, self._readers = self._readers, []
        for conn in readers:
            conn.close()
        self._local = threading.local()
