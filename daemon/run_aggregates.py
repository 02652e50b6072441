"""Each run's statistics kept in the records file as its strokes are written (`run_aggregates`).

The record writer folds every committed stroke into its run's `RunAggregate` (protocol/aggregate.py)
and saves it every 10 s and when the run ends, in a transaction of its own: a saved
aggregate may lag its strokes by the last seconds, never lead them. A reader takes the saved one and
folds in the strokes after its `last_cycle` (an indexed range read of at most 10 s of strokes),
so `stats --run N` costs the same at 10^7 strokes as at 10. A file written before the table existed
gets every run's aggregate built once, when a writer opens it, with a progress line. The full scan
(`stats.stats_of_records`) stays: what the tests hold these against.

The table is added with CREATE TABLE IF NOT EXISTS: readers that do not know it still read the file.
"""

from __future__ import annotations

import sqlite3
import time
from typing import Any

import msgpack
import structlog

from usmswitch.protocol.aggregate import ExactRunning, RunAggregate, Sketch
from usmswitch.protocol.record import CycleRecord, RunRecord
from usmswitch.protocol.stats import model_of

log = structlog.get_logger("usmswitch.records")

TABLE = """
CREATE TABLE IF NOT EXISTS run_aggregates (
    run_id INTEGER PRIMARY KEY,
    last_cycle INTEGER,
    records INTEGER NOT NULL,
    data BLOB NOT NULL,
    summary BLOB
);
"""
#: A run's aggregate is saved at most this often while it runs (and at its end). The save encodes its
#: sketches in Python on the record writer's thread, holding the GIL the loop may need: rarely.
SAVE_EVERY_NS = 10_000_000_000
_PROGRESS_EVERY_NS = 2_000_000_000
_CHUNK = 5000


def _fold_after(conn: sqlite3.Connection, select: str, agg: RunAggregate, run_id: int) -> None:
    """Fold in the run's strokes after the aggregate's last cycle, in chunks."""
    after = agg.last_cycle or 0
    while True:
        rows = conn.execute(
            f"{select} WHERE run_id = ? AND cycle > ? ORDER BY cycle LIMIT ?", (run_id, after, _CHUNK)
        ).fetchall()
        if not rows:
            return
        for r in rows:
            agg.add(CycleRecord.from_row(r))
        after = agg.last_cycle or after


def load(conn: sqlite3.Connection, select: str, run_id: int) -> RunAggregate | None:
    """The run's aggregate, up to its last stroke in the file; None if none was ever saved."""
    try:
        row = conn.execute("SELECT data FROM run_aggregates WHERE run_id = ?", (run_id,)).fetchone()
    except sqlite3.OperationalError:  # a file from before the table: no aggregates yet
        return None
    if row is None:
        return None
    agg = RunAggregate(bytes(row[0]))
    _fold_after(conn, select, agg, run_id)
    return agg


def _ended_already(conn: sqlite3.Connection, run_ids: set[int]) -> set[int]:
    """Of `run_ids`, the runs whose row says they have ended: a stroke cut short by an estop is
    submitted after its run's end (its record comes once the stroke is over), and its run's
    aggregate was held for good (~1 MB a run: 380 MB after 400 estops)."""
    marks = ",".join("?" * len(run_ids))
    sql = f"SELECT run_id FROM runs WHERE end_reason IS NOT NULL AND run_id IN ({marks})"
    return {row[0] for row in conn.execute(sql, sorted(run_ids))}


def _summary(agg: RunAggregate) -> dict[str, Any]:
    """What a reply shows of an aggregate: its figures, without the sketches."""
    return {
        "first_cycle": agg.first_cycle,
        "last_cycle": agg.last_cycle,
        "all": agg.both.snapshot(),
        "on": agg.per[0].snapshot(),
        "off": agg.per[1].snapshot(),
    }


def run_stats(conn: sqlite3.Connection, select: str, run: RunRecord) -> dict[str, Any] | None:
    """A run's statistics in the shape of `stats.stats_of_records`, from its aggregate (None: the run
    has none yet, the caller scans its strokes). A run with no stroke after its last save (every
    ended run) is answered from the saved figures alone, without decoding its sketches."""
    try:
        row = conn.execute(
            "SELECT last_cycle, summary FROM run_aggregates WHERE run_id = ?", (run.run_id,)
        ).fetchone()
    except sqlite3.OperationalError:  # a file from before the table
        return None
    if row is None:
        return None
    after = conn.execute(
        "SELECT 1 FROM cycles WHERE run_id = ? AND cycle > ? LIMIT 1", (run.run_id, row[0] or 0)
    ).fetchone()
    if after is None and row[1] is not None:
        figures = msgpack.unpackb(bytes(row[1]), raw=False)
    else:
        agg = load(conn, select, run.run_id)
        if agg is None:
            return None
        figures = _summary(agg)
    out: dict[str, Any] = {"run": run.to_dict(), **figures}
    last = figures["last_cycle"]
    for d, name in ((0, "on"), (1, "off")):
        snap = figures[name]
        row = None
        if last is not None:
            # The direction's last stroke: the model it used (a short backward range read).
            row = conn.execute(
                f"{select} WHERE run_id = ? AND direction = ? AND cycle <= ? ORDER BY cycle DESC LIMIT 1",
                (run.run_id, d, last),
            ).fetchone()
        out[name] = {**snap, **model_of(None if row is None else CycleRecord.from_row(row))}
    return out


def merge_into(into: RunAggregate, other: RunAggregate) -> None:
    """`other`'s strokes pooled into `into`, as if folded one by one, without reading them: exact
    sums and counts added, sketches merged (the same buckets: the same stated error), maxima kept,
    commissioning strokes listed. Over the figures' attributes by kind (an int is a count, a float
    a maximum), so a counter added to `DirectionStats` pools without a change here."""
    for mine, theirs in zip((*into.per, into.both), (*other.per, other.both), strict=True):
        for name, value in vars(theirs).items():
            have = getattr(mine, name)
            if isinstance(have, ExactRunning):
                have.count, have.s, have.ss = have.count + value.count, have.s + value.s, have.ss + value.ss
                have.max_abs = max(have.max_abs, value.max_abs)
            elif isinstance(have, Sketch):
                have.hist.add(value.hist)
            elif isinstance(have, list):
                have.extend(value)
            elif isinstance(have, int) and not isinstance(have, bool):
                setattr(mine, name, have + value)
            elif isinstance(have, float):
                setattr(mine, name, max(have, value))
    firsts = [c for c in (into.first_cycle, other.first_cycle) if c is not None]
    lasts = [c for c in (into.last_cycle, other.last_cycle) if c is not None]
    into.first_cycle = min(firsts, default=None)
    into.last_cycle = max(lasts, default=None)
    into.records += other.records


def label_stats(conn: sqlite3.Connection, select: str, label: str, runs: list[RunRecord]) -> dict[str, Any]:
    """The statistics of every run with one label: pooled (`on`, `off`, `all` over all their
    strokes, from their kept aggregates merged) and per run (`per_run`, each as `stats --run`)."""
    pooled = RunAggregate()
    per_run = []
    for run in runs:
        agg = load(conn, select, run.run_id)
        if agg is None:  # none kept yet (a file being migrated): its strokes folded now
            agg = RunAggregate()
            _fold_after(conn, select, agg, run.run_id)
        merge_into(pooled, agg)
        per_run.append(run_stats(conn, select, run) or {"run": run.to_dict(), **_summary(agg)})
    return {
        "label": label,
        "run": None,
        "runs": [r.to_dict() for r in runs],
        **_summary(pooled),
        "per_run": per_run,
    }


class AggregateKeeper:
    """The record writer's running aggregates, one per run it wrote strokes of."""

    def __init__(self, select: str, path: str) -> None:
        self._select = select
        self._path = path
        self._aggs: dict[int, RunAggregate] = {}
        self._dirty: set[int] = set()
        self._saved_ns: dict[int, int] = {}
        #: Saving failed (the file's trouble is the writer's to report): tried again at the next save.
        self.last_error: str | None = None

    def open(self, conn: sqlite3.Connection) -> None:
        """Create the table; build the aggregate of every run that has none (once, with progress)."""
        conn.executescript(TABLE)
        missing = [
            r[0]
            for r in conn.execute(
                "SELECT run_id FROM runs WHERE run_id NOT IN (SELECT run_id FROM run_aggregates)"
                " ORDER BY run_id"
            )
        ]
        if not missing:
            return
        t0 = said = time.monotonic_ns()
        strokes = 0
        for i, run_id in enumerate(missing, 1):
            agg = RunAggregate()
            _fold_after(conn, self._select, agg, run_id)
            self._write(conn, run_id, agg, summary=True)
            strokes += agg.records
            now = time.monotonic_ns()
            if now - said >= _PROGRESS_EVERY_NS or i == len(missing):
                said = now
                log.info(
                    "building run statistics",
                    path=self._path,
                    runs=f"{i}/{len(missing)}",
                    strokes=strokes,
                    seconds=round((now - t0) / 1e9, 1),
                )

    def fold(self, conn: sqlite3.Connection, records: list[CycleRecord], ended: set[int]) -> None:
        """Committed strokes folded in; saved every SAVE_EVERY_NS per run, and at a run's end."""
        for rec in records:
            run_id = rec.run_id
            if run_id is None:
                continue
            agg = self._aggs.get(run_id)
            if agg is None:
                agg = load(conn, self._select, run_id)
                if agg is None:
                    agg = RunAggregate()
                    _fold_after(conn, self._select, agg, run_id)  # strokes before this process's
                    self._aggs[run_id] = agg
                    self._dirty.add(run_id)
                    continue  # this record is in the file: folded just now
                self._aggs[run_id] = agg
                if agg.last_cycle is not None and rec.cycle <= agg.last_cycle:
                    continue
            if agg.last_cycle is not None and rec.cycle <= agg.last_cycle:
                continue  # already folded (read from the file)
            agg.add(rec)
            self._dirty.add(run_id)
        touched = {rec.run_id for rec in records if rec.run_id is not None} - ended
        self.save(conn, force=ended | _ended_already(conn, touched) if touched else ended)

    def save(self, conn: sqlite3.Connection, force: set[int] | None = None) -> None:
        now = time.monotonic_ns()
        ending = {r for r in force or () if r in self._aggs}  # saved with their figures, dirty or not
        try:
            for run_id in sorted(self._dirty | ending):
                if run_id in ending or now - self._saved_ns.get(run_id, 0) >= SAVE_EVERY_NS:
                    self._write(conn, run_id, self._aggs[run_id], summary=run_id in ending)
                    self._dirty.discard(run_id)
                    self._saved_ns[run_id] = now
            self.last_error = None
        except sqlite3.Error as exc:
            self.last_error = str(exc)
        finally:
            # An ended run takes no more strokes: hold nothing for it, saved or not (one whose
            # save failed is built again from its strokes: by a reader, and at the next start).
            for run_id in force or ():
                self._aggs.pop(run_id, None)
                self._saved_ns.pop(run_id, None)
                self._dirty.discard(run_id)

    def flush(self, conn: sqlite3.Connection) -> None:
        """Save every aggregate not yet saved (the writer is closing)."""
        self.save(conn, force=set(self._dirty))

    @staticmethod
    def _write(conn: sqlite3.Connection, run_id: int, agg: RunAggregate, *, summary: bool) -> None:
        """The aggregate's row; with its figures (`summary`) once the run has ended: the quantiles
        are a walk of the sketches in Python, done once, not at every save of a running run."""
        figures = msgpack.packb(_summary(agg)) if summary else None
        conn.execute(
            "INSERT OR REPLACE INTO run_aggregates (run_id, last_cycle, records, data, summary)"
            " VALUES (?, ?, ?, ?, ?)",
            (run_id, agg.last_cycle, agg.records, agg.to_bytes(), figures),
        )
