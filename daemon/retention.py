"""Retention: old runs moved from the records file to an archive file, so a months-long rig's file
stays bounded (issue 36; the file grew ~175 bytes a stroke, forever).

The policy (`[records]` keep_strokes, keep_days, keep_bytes; 0: no limit) is applied by the record
writer as soon as a run's end is written (what makes a run movable), busy or not, and otherwise at
most once a minute (keep_days ages runs; a run in progress grows the file): while the file holds
more strokes than keep_strokes, or more used bytes than keep_bytes, or a run that ended more than
keep_days ago, the oldest ended run is moved, whole, with its run row and its statistics, into
`records-archive.sqlite` beside it (the same schema: `usmswitchctl export --from` and
`RecordsFile.dataframe()` read it as they read the records file). Never a run in progress, never a
stroke without a run (a lone `switch`), and, where the records are shipped to PostgreSQL, never a
stroke not yet shipped. Each move is one transaction over both files (ATTACH): a crash leaves the
run in one of them, never both or neither. The pages a move frees are reused by the strokes after
it, so the file settles at about keep_bytes plus the largest run (a run in progress is never moved)
and grows no further. Each move is logged.
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import structlog

from usmswitch.protocol.records_schema import SCHEMA, SCHEMA_VERSION, add_to_schema

from .run_aggregates import TABLE as AGGREGATES_TABLE

log = structlog.get_logger("usmswitch.records")

ARCHIVE_FILE = "records-archive.sqlite"
#: The writer looks at the policy at most this often, but for a run's end (looked at at once).
CHECK_EVERY_NS = 60_000_000_000
_DAY_NS = 86_400_000_000_000


@dataclass(frozen=True)
class RetentionPolicy:
    """What the records file keeps (0: no limit on that count)."""

    keep_strokes: int = 0
    keep_days: int = 0
    keep_bytes: int = 0

    @property
    def active(self) -> bool:
        return bool(self.keep_strokes or self.keep_days or self.keep_bytes)


class Retention:
    """The record writer's retention: which runs go, and moving them (writer thread only)."""

    def __init__(
        self,
        policy: RetentionPolicy,
        path: Path,
        *,
        shipped: Callable[[], int | None] = lambda: None,
        check_every_ns: int = CHECK_EVERY_NS,
    ) -> None:
        """`shipped`: the last cycle the PostgreSQL copy has (None: no copy is kept)."""
        self.policy = policy
        self.archive = path.with_name(ARCHIVE_FILE)
        self._shipped = shipped
        self._every = check_every_ns
        self._next_ns = 0
        self._ended = False  # a run's end written since the last look
        #: Runs moved to the archive by this writer, and their strokes.
        self.runs_archived = 0
        self.strokes_archived = 0

    def run_ended(self) -> None:
        """A run's end is in the file: look at once. In virtual time runs follow each other far
        faster than once a minute, with the writer never idle; waiting for either let the file
        grow by many runs past its bound."""
        self._ended = True

    def due(self, now_ns: int) -> bool:
        return self.policy.active and (self._ended or now_ns >= self._next_ns)

    def apply(self, conn: sqlite3.Connection) -> int:
        """Move the oldest ended runs until the policy holds; returns how many runs moved."""
        self._next_ns = time.monotonic_ns() + self._every
        self._ended = False
        p = self.policy
        runs = conn.execute(
            "SELECT run_id, first_cycle, last_cycle, ended_wall_ns FROM runs"
            " WHERE last_cycle IS NOT NULL ORDER BY run_id"
        ).fetchall()
        if not runs:
            return 0
        strokes = conn.execute("SELECT count(*) FROM cycles").fetchone()[0]
        shipped = self._shipped()
        moved = 0
        for run_id, first, last, ended_ns in runs:
            used = _used_bytes(conn)
            old = p.keep_days and ended_ns is not None and time.time_ns() - ended_ns > p.keep_days * _DAY_NS
            over = (p.keep_strokes and strokes > p.keep_strokes) or (p.keep_bytes and used > p.keep_bytes)
            if not (old or over):
                break
            if shipped is not None and last > shipped:
                log.info("retention waits for shipping", run=run_id, last_cycle=last, shipped_cycle=shipped)
                break
            n = self._move(conn, run_id, first, last)
            strokes -= n
            moved += 1
            self.runs_archived += 1
            self.strokes_archived += n
            why = "older than keep_days" if old and not over else "over keep_strokes or keep_bytes"
            log.info("run archived", run=run_id, strokes=n, archive=str(self.archive), why=why)
        return moved

    def _move(self, conn: sqlite3.Connection, run_id: int, first: int, last: int) -> int:
        _prepare_archive(self.archive)
        conn.execute("ATTACH DATABASE ? AS archive", (str(self.archive),))
        try:
            conn.execute("BEGIN IMMEDIATE")
            try:
                where = "cycle >= ? AND cycle <= ? AND run_id = ?"
                args = (first, last, run_id)
                conn.execute(
                    f"INSERT OR REPLACE INTO archive.cycles SELECT * FROM main.cycles WHERE {where}", args
                )
                conn.execute(
                    "INSERT OR REPLACE INTO archive.runs SELECT * FROM main.runs WHERE run_id = ?", (run_id,)
                )
                conn.execute(
                    "INSERT OR REPLACE INTO archive.run_aggregates"
                    " SELECT * FROM main.run_aggregates WHERE run_id = ?",
                    (run_id,),
                )
                n = conn.execute(f"DELETE FROM main.cycles WHERE {where}", args).rowcount
                conn.execute("DELETE FROM main.run_aggregates WHERE run_id = ?", (run_id,))
                conn.execute("DELETE FROM main.runs WHERE run_id = ?", (run_id,))
                conn.execute("COMMIT")
            except BaseException:
                conn.execute("ROLLBACK")
                raise
        finally:
            conn.execute("DETACH DATABASE archive")
        return n


def _used_bytes(conn: sqlite3.Connection) -> int:
    """The file's size less its free pages (what the strokes after a move will reuse)."""
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    free = conn.execute("PRAGMA freelist_count").fetchone()[0]
    size = conn.execute("PRAGMA page_size").fetchone()[0]
    return (pages - free) * size


def _prepare_archive(path: Path) -> None:
    """The archive file with the records file's schema (a records file of its own, for readers)."""
    conn = sqlite3.connect(path, isolation_level=None)
    try:
        conn.execute("PRAGMA journal_mode = WAL")
        conn.executescript(SCHEMA + AGGREGATES_TABLE)
        add_to_schema(conn)  # an archive made before the additions gains them, as the file did
        conn.execute(
            "INSERT OR IGNORE INTO meta (key, value) VALUES ('schema_version', ?), ('created_wall_ns', ?),"
            " ('archive_of', ?)",
            (str(SCHEMA_VERSION), str(time.time_ns()), path.with_name("records.sqlite").name),
        )
    finally:
        conn.close()
