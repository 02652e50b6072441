"""Read a rig's records file for analysis, read-only, on a lab machine: no daemon needed.

    from usmswitch.client import RecordsFile

    with RecordsFile("~/.local/state/usmswitch/sim/records.sqlite") as f:
        for rec in f.records(first=1000):        # CycleRecord dicts, in cycle order
            ...
        errors = f.column("error_ns")             # a numpy array (NaN where a stroke has none)
        df = f.dataframe()                        # pandas, when installed (`pip install usmswitch[analysis]`)

The file is opened read-only (SQLite `mode=ro`): a running daemon keeps writing beside the reader
(WAL), and each chunk is its own short read, so a long analysis never pins the daemon's log.
Schema: docs/records.md (versions 1 to 3; columns an older file lacks read as None: `driver` and
`rig` before 2, `run_id` before 3, and such a file has no runs).

`RecordsSource` is what every reader offers; `PostgresRecords` (client/pgrecords.py) reads one
rig's records from the PostgreSQL copy the daemons ship, and `open_records(source)` opens either.
"""

from __future__ import annotations

import collections
import csv
import io
import json
import os
import sqlite3
import threading
from abc import ABC, abstractmethod
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any
from urllib.parse import quote

from usmswitch.protocol.export_plan import ExportPlan
from usmswitch.protocol.record import FIELDS, LATER_FIELDS, CycleRecord, Flag, RunRecord
from usmswitch.protocol.record_csv import BadCell, csv_rows_of_table, csv_text_chunks

RECORDS_FILE = "records.sqlite"
KNOWN_SCHEMAS = ("1", "2", "3")


class RecordsFileError(Exception):
    """The records cannot be read: a file missing or of an unknown schema, a database unreachable."""


class RecordsSource(ABC):
    """Records for analysis, wherever they are kept: the calls every reader has."""

    #: What the records are (a path, a redacted URL and rig), for messages.
    name = ""

    def records(
        self,
        first: int = 1,
        last: int | None = None,
        chunk: int = 1000,
        run: int | None = None,
        *,
        label: str | None = None,
    ) -> Iterator[dict[str, Any]]:
        """Every record from cycle `first` to `last` (inclusive; of one run; of every run with
        `label`) in cycle order, as dicts.

        Read `chunk` rows at a time, each its own short read (a daemon writing beside a long
        analysis is never held up by it)."""
        if label is not None:
            for labelled in self.runs(label):
                yield from self.records(first, last, chunk, labelled["run_id"])
            return
        after = first - 1
        stop = last if last is not None else (1 << 63) - 1
        if run is not None:
            self.run(run)  # a run the records lack is an error, not an empty result
        while True:
            rows = self._chunk(after, stop, run, chunk)
            if not rows:
                return
            for r in rows:
                yield CycleRecord.from_row(r).to_dict()
            after = rows[-1]["cycle"]

    def table_rows(
        self,
        first: int = 1,
        last: int | None = None,
        chunk: int = 20_000,
        run: int | None = None,
        *,
        label: str | None = None,
    ) -> Iterator[tuple[Any, ...]]:
        """The same records as `records`, as the file's rows (FIELDS order, coefficients as JSON
        text): for exports, which write them as they are (`record_csv.csv_rows_of_table`)."""
        for rec in self.records(first, last, chunk, run, label=label):
            yield tuple(
                json.dumps([float(c) for c in rec[f]]) if f == "coefficients" else rec[f] for f in FIELDS
            )

    def csv_chunks(
        self,
        first: int = 1,
        last: int | None = None,
        run: int | None = None,
        chunk: int = 10_000,
        *,
        label: str | None = None,
    ) -> Iterator[tuple[int, int, str]]:
        """The same records as CSV text (record_csv's lines, each ending in a newline, no header),
        `chunk` strokes at a time: (strokes, the chunk's last cycle, text). What exports write."""
        c = FIELDS.index("cycle")
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        batch: list[tuple[Any, ...]] = []
        for row in self.table_rows(first, last, run=run, label=label):
            batch.append(row)
            if len(batch) == chunk:
                writer.writerows(csv_rows_of_table(batch))
                yield len(batch), batch[-1][c], buf.getvalue()
                buf.seek(0)
                buf.truncate()
                batch.clear()
        if batch:
            writer.writerows(csv_rows_of_table(batch))
            yield len(batch), batch[-1][c], buf.getvalue()

    def cycle_span(
        self, first: int = 1, last: int | None = None, run: int | None = None
    ) -> tuple[int, int] | None:
        """The first and last cycle there are in that range (of one run), for a progress bar; None
        when there is none or this source cannot say cheaply."""
        return None

    @abstractmethod
    def _chunk(self, after: int, last: int, run: int | None, n: int) -> list[Any]:
        """Up to `n` rows (mappings of FIELDS) with after < cycle <= last (of one run), by cycle."""

    @abstractmethod
    def runs(self, label: str | None = None) -> list[dict[str, Any]]:
        """Every run (with that label), oldest first."""

    @abstractmethod
    def _column_values(self, field: str, first: int, last: int) -> list[Any]:
        """One field's values over cycles first..last, in cycle order."""

    @abstractmethod
    def close(self) -> None:
        """Release the file or the connection."""

    def __enter__(self) -> RecordsSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> Iterator[dict[str, Any]]:
        return self.records()

    def run(self, run_id: int) -> dict[str, Any]:
        """One run's record; RecordsFileError naming the runs there are when there is no such run."""
        runs = self.runs()
        for run in runs:
            if run["run_id"] == run_id:
                return run
        ids = [r["run_id"] for r in runs]
        have = f"runs {ids[0]}..{ids[-1]}" if ids else "no runs"
        raise RecordsFileError(f"no run {run_id} in {self.name} ({have})")

    def column(self, field: str, first: int = 1, last: int | None = None) -> Any:
        """One field over cycles `first`..`last` as a numpy array (float64 with NaN where it is
        missing, for the timing fields; int64 for the ones always present)."""
        import numpy as np

        if field not in FIELDS or field in ("coefficients", "mode", *LATER_FIELDS):
            raise ValueError(f"column takes a numeric record field, got {field!r}")
        values = self._column_values(field, first, last if last is not None else (1 << 63) - 1)
        if any(v is None or isinstance(v, float) for v in values):
            return np.array([np.nan if v is None else v for v in values], dtype=np.float64)
        return np.array(values, dtype=np.int64)

    def dataframe(
        self,
        first: int = 1,
        last: int | None = None,
        *,
        run: int | None = None,
        index_col: str | None = None,
        label: str | None = None,
    ) -> Any:
        """The records as a pandas DataFrame, as `pandas.read_sql` gives a table: one column per
        field, a default RangeIndex unless `index_col` names one (`index_col="cycle"`), `run` for
        one run's strokes, `label` for those of every run with that label (`run_id` tells them
        apart). Needs pandas (the `analysis` extra).

        Two fields would hide DataFrame attributes (`df.flags`, `df.mode()`): they are the columns
        `flag_bits` and `loop_mode`, and each flag is also a boolean column (`late`, `stall`, ...).
        """
        try:
            import pandas as pd
        except ImportError:
            raise ImportError(
                "RecordsFile.dataframe needs pandas: pip install 'usmswitch[analysis]'"
            ) from None
        rows = list(self.records(first, last, run=run, label=label))
        frame = pd.DataFrame.from_records(rows, columns=list(FIELDS))
        frame = frame.rename(columns=DATAFRAME_RENAMES)
        bits = frame["flag_bits"].astype("int64")
        for flag in Flag:
            frame[str(flag.name).lower()] = (bits & int(flag)) != 0
        return frame if index_col is None else frame.set_index(index_col)


#: Record fields renamed in a DataFrame, where their own names are DataFrame attributes.
DATAFRAME_RENAMES = {"flags": "flag_bits", "mode": "loop_mode"}


#: Threads an export from the file builds its chunks on (each with its own read connection).
EXPORT_THREADS = 2


class RecordsFile(RecordsSource):
    """A records file (or a state directory holding one), opened read-only."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        p = Path(path).expanduser()
        self.path = p / RECORDS_FILE if p.is_dir() else p
        self.name = str(self.path)
        if not self.path.is_file():
            raise RecordsFileError(f"no records file at {self.path}")
        self._uri = uri = f"file:{quote(str(self.path.resolve()))}?mode=ro"
        try:
            self._db = sqlite3.connect(uri, uri=True)
            self._db.row_factory = sqlite3.Row
            row = self._db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        except sqlite3.Error as exc:
            raise RecordsFileError(f"{self.path} is not a usmswitch records file: {exc}") from None
        self.schema_version = row[0] if row else None
        if self.schema_version not in KNOWN_SCHEMAS:
            raise RecordsFileError(
                f"{self.path} has schema version {self.schema_version}; this client reads {KNOWN_SCHEMAS}"
            )
        have = {r[1] for r in self._db.execute("PRAGMA table_info(cycles)")}
        self._columns = ", ".join(f'"{f}"' if f in have else f'NULL AS "{f}"' for f in FIELDS)
        self._has_runs = "run_id" in have

    def close(self) -> None:
        """Close the file."""
        self._db.close()

    def __len__(self) -> int:
        return int(self._db.execute("SELECT count(*) FROM cycles").fetchone()[0])

    @property
    def last_cycle(self) -> int:
        """The highest cycle number in the file (0 when empty)."""
        return int(self._db.execute("SELECT coalesce(max(cycle), 0) FROM cycles").fetchone()[0])

    def runs(self, label: str | None = None) -> list[dict[str, Any]]:
        """Every run in the file (with that label), oldest first (none in a file from before runs;
        none with a label in one from before labels)."""
        if not self._has_runs:
            return []
        if label is None:
            rows = self._db.execute("SELECT * FROM runs ORDER BY run_id").fetchall()
        elif "label" not in {r[1] for r in self._db.execute("PRAGMA table_info(runs)")}:
            return []
        else:
            rows = self._db.execute("SELECT * FROM runs WHERE label = ? ORDER BY run_id", (label,)).fetchall()
        return [RunRecord.from_row(r).to_dict() for r in rows]

    def table_rows(
        self,
        first: int = 1,
        last: int | None = None,
        chunk: int = 20_000,
        run: int | None = None,
        *,
        label: str | None = None,
    ) -> Iterator[tuple[Any, ...]]:
        """The file's rows as they are, in chunks of plain tuples (no record, no dict made)."""
        if label is not None:
            for labelled in self.runs(label):
                yield from self.table_rows(first, last, chunk, labelled["run_id"])
            return
        after = first - 1
        stop = last if last is not None else (1 << 63) - 1
        if run is not None:
            self.run(run)
        c = FIELDS.index("cycle")
        while True:
            rows = self._chunk(after, stop, run, chunk, plain=True)
            if not rows:
                return
            # A cell that would not read back as a record is an error, as it is through records():
            # checked by SQLite over the chunk's range, not by Python a row.
            bad = self._db.execute(
                "SELECT cycle FROM cycles WHERE cycle > ? AND cycle <= ? AND NOT json_valid(coefficients)"
                " LIMIT 1",
                (after, rows[-1][c]),
            ).fetchone()
            if bad is not None:
                raise RecordsFileError(f"{self.path}: cycle {bad[0]}: its coefficients are not JSON")
            yield from rows
            after = rows[-1][c]

    def csv_chunks(
        self,
        first: int = 1,
        last: int | None = None,
        run: int | None = None,
        chunk: int = 10_000,
        *,
        label: str | None = None,
    ) -> Iterator[tuple[int, int, str]]:
        """The records (of a run, of the runs with a label) as CSV text, each chunk's built by SQLite
        in one statement (issue 36: within 2x `sqlite3 -csv` of the same rows), the same bytes as
        the csv module writes of them. The chunks ahead are built on two threads, each on a
        connection of its own, as the socket's export asks two reader processes
        (protocol/export_plan.py): SQLite builds one chunk while Python finishes another (one at a
        time, 2.64x `sqlite3 -csv` at 10^7 strokes)."""
        if run is not None:
            self.run(run)
        plan = ExportPlan(first, last, max_strokes=chunk)
        connections: list[sqlite3.Connection] = []
        local = threading.local()

        def build(a: int, b: int | None, most: int) -> tuple[int, int | None, str]:
            conn = getattr(local, "conn", None)
            if conn is None:
                # Used by its thread alone; closed below once the threads have ended.
                conn = local.conn = sqlite3.connect(self._uri, uri=True, check_same_thread=False)
                connections.append(conn)
            return next(csv_text_chunks(conn, a, b, run, most, label=label), (0, None, ""))

        try:
            with ThreadPoolExecutor(EXPORT_THREADS, thread_name_prefix="export") as pool:
                pending: collections.deque[Future[tuple[int, int | None, str]]] = collections.deque()
                try:
                    while True:
                        pending.extend(pool.submit(build, *req) for req in plan.requests())
                        if not pending:
                            return
                        n, top, text = pending.popleft().result()
                        if plan.answered(n, top) and n:
                            assert top is not None
                            yield n, top, text
                finally:
                    for future in pending:  # a reader that stopped early: nothing more is built
                        future.cancel()
        except BadCell as exc:
            raise RecordsFileError(f"{self.path}: {exc}") from None
        finally:
            for conn in connections:
                conn.close()

    def cycle_span(
        self, first: int = 1, last: int | None = None, run: int | None = None
    ) -> tuple[int, int] | None:
        """The first and last cycle there are in that range (of one run): two index lookups."""
        if run is not None and not self._has_runs:
            return None
        where, args = ("", ()) if run is None else (" AND run_id = ?", (run,))
        stop = last if last is not None else (1 << 63) - 1
        ends = []
        for order in ("", " DESC"):  # each one index lookup (min and max in one SELECT would scan)
            sql = f"SELECT cycle FROM cycles WHERE cycle >= ? AND cycle <= ?{where}"
            sql += f" ORDER BY cycle{order} LIMIT 1"
            row = self._db.execute(sql, (first, stop, *args)).fetchone()
            if row is None:
                return None
            ends.append(int(row[0]))
        return ends[0], ends[1]

    def _chunk(self, after: int, last: int, run: int | None, n: int, plain: bool = False) -> list[Any]:
        where, args = ("", ()) if run is None else (" AND run_id = ?", (run,))
        sql = (
            f"SELECT {self._columns} FROM cycles WHERE cycle > ? AND cycle <= ?{where} ORDER BY cycle LIMIT ?"
        )
        cur = self._db.cursor()
        if plain:
            cur.row_factory = None  # plain tuples: what an export writes as they are
        return cur.execute(sql, (after, last, *args, n)).fetchall()

    def _column_values(self, field: str, first: int, last: int) -> list[Any]:
        if f'"{field}"' not in self._columns:
            raise ValueError(f"{self.path} has no column {field!r} (schema {self.schema_version})")
        sql = f'SELECT "{field}" FROM cycles WHERE cycle >= ? AND cycle <= ? ORDER BY cycle'
        return [r[0] for r in self._db.execute(sql, (first, last))]
