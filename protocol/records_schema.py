"""The records file's SQL: the schema (version 3), the statements the store runs, the migrations.

Apart from `records.py` (the store: its writer thread, reads, failures) so that the file's layout,
which docs/records.md shows and other tools query, reads in one place.

Two kinds of change: a new version (`MIGRATIONS`) for what older readers could not read, which
they then refuse by its number; and additions to version 3 (`ADDED_COLUMNS`, `ADDITIONS`: new
columns and tables, nothing renamed or removed), which readers of version 3 read past as they read
past `run_aggregates`, so the version stays 3 and no reader in the field refuses the file.
"""

from __future__ import annotations

from typing import Any, Protocol

from .record import FIELDS, RUN_FIELDS, SOURCE_FIELDS

SCHEMA_VERSION = 3
#: Versions this code reads; a writer migrates an older file to SCHEMA_VERSION at open.
READABLE_VERSIONS = (1, 2, 3)
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS cycles (
    cycle INTEGER PRIMARY KEY CHECK (cycle >= 1),
    direction INTEGER NOT NULL CHECK (direction IN (0, 1)),
    mode TEXT NOT NULL CHECK (mode IN ('closed', 'open')),
    target_ns INTEGER NOT NULL,
    "order" INTEGER NOT NULL,
    coefficients TEXT NOT NULL,
    t_hat_ns INTEGER NOT NULL,
    delay_ns INTEGER NOT NULL CHECK (delay_ns >= 0),
    t_cmd_ns INTEGER NOT NULL,
    t_start_ns INTEGER,
    t_depart_ns INTEGER,
    t_arrive_ns INTEGER,
    operating_ns INTEGER,
    total_ns INTEGER,
    error_ns INTEGER,
    dead_ns INTEGER,
    lateness_ns INTEGER,
    temperature_c REAL,
    frequency_hz REAL,
    flags INTEGER NOT NULL DEFAULT 0,
    wall_ns INTEGER NOT NULL,
    driver TEXT,
    rig TEXT,
    run_id INTEGER
);
CREATE INDEX IF NOT EXISTS cycles_direction ON cycles (direction, cycle);
CREATE INDEX IF NOT EXISTS cycles_source ON cycles (driver, rig, direction, cycle);
CREATE INDEX IF NOT EXISTS cycles_run ON cycles (run_id, cycle);
CREATE TABLE IF NOT EXISTS runs (
    run_id INTEGER PRIMARY KEY CHECK (run_id >= 1),
    kind TEXT NOT NULL,
    first_cycle INTEGER NOT NULL,
    started_wall_ns INTEGER NOT NULL,
    settings TEXT NOT NULL,
    last_cycle INTEGER,
    ended_wall_ns INTEGER,
    end_reason TEXT,
    driver TEXT,
    rig TEXT,
    label TEXT,
    notes TEXT
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY,
    wall_ns INTEGER NOT NULL,
    after_cycle INTEGER,
    kind TEXT NOT NULL,
    data TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS events_kind ON events (kind, id);
"""

COLUMNS = ", ".join(f'"{f}"' for f in FIELDS)
INSERT_CYCLE = f"INSERT INTO cycles ({COLUMNS}) VALUES ({', '.join('?' * len(FIELDS))})"
INSERT_EVENT = "INSERT INTO events (wall_ns, after_cycle, kind, data) VALUES (?, ?, ?, ?)"
SELECT_CYCLES = f"SELECT {COLUMNS} FROM cycles"


def select_without(missing: tuple[str, ...]) -> str:
    """The cycles SELECT for an older file (read-only): the columns it lacks read as NULL."""
    return "SELECT {} FROM cycles".format(
        ", ".join(f'NULL AS "{f}"' if f in missing else f'"{f}"' for f in FIELDS)
    )


# What an older file (opened read-only) lacks, by its schema version.
SELECT_BY_VERSION = {1: select_without((*SOURCE_FIELDS, "run_id")), 2: select_without(("run_id",))}
# A run's label and notes are its opener's at the insert; the loop's row at the run's end does not
# overwrite notes edited meanwhile.
UPSERT_RUN = "INSERT INTO runs ({}) VALUES ({}) ON CONFLICT (run_id) DO UPDATE SET {}".format(
    ", ".join(RUN_FIELDS),
    ", ".join("?" * len(RUN_FIELDS)),
    ", ".join(f"{f} = excluded.{f}" for f in RUN_FIELDS if f not in ("run_id", "label", "notes")),
)
# Migrations, each from the version before. Old rows keep NULL ("unknown" source, no run).
MIGRATIONS = {
    2: "ALTER TABLE cycles ADD COLUMN driver TEXT; ALTER TABLE cycles ADD COLUMN rig TEXT;",
    3: "ALTER TABLE cycles ADD COLUMN run_id INTEGER;",
}

#: Additions to schema 3, per table: columns an older file gains at a writer's open (NULL in its
#: rows). The last columns of their table, so that `INSERT ... SELECT *` between two files agrees.
ADDED_COLUMNS: dict[str, tuple[tuple[str, str], ...]] = {"runs": (("label", "TEXT"), ("notes", "TEXT"))}
#: Additions to schema 3 that need the added columns (run after them), one statement each.
ADDITIONS = (
    "CREATE INDEX IF NOT EXISTS runs_label ON runs (label, run_id)",
    # The queue of runs (daemon/run_queue.py): every entry submitted, kept after it leaves the queue
    # (started: the run it became; cancelled or refused: why), so a restart finds what waits.
    """CREATE TABLE IF NOT EXISTS run_queue (
        entry INTEGER PRIMARY KEY CHECK (entry >= 1),
        submitted_wall_ns INTEGER NOT NULL,
        owner TEXT NOT NULL,
        priority INTEGER NOT NULL,
        params TEXT NOT NULL,
        state TEXT NOT NULL CHECK (state IN ('queued', 'started', 'cancelled', 'refused')),
        run_id INTEGER,
        first_cycle INTEGER,
        reason TEXT,
        changed_wall_ns INTEGER
    )""",
    "CREATE INDEX IF NOT EXISTS run_queue_state ON run_queue (state, entry)",
)


class _Connection(Protocol):
    def execute(self, sql: str, /) -> Any: ...


def add_to_schema(conn: _Connection) -> list[str]:
    """Bring a file of schema 3 (SCHEMA already run on it) to today's additions; idempotent, and
    inside the caller's transaction if it has one. Returns the columns added ("runs.label", ...)."""
    added = []
    for table, columns in ADDED_COLUMNS.items():
        have = {row[1] for row in conn.execute(f"PRAGMA table_info({table})")}
        for name, decl in columns:
            if name not in have:
                conn.execute(f"ALTER TABLE {table} ADD COLUMN {name} {decl}")
                added.append(f"{table}.{name}")
    for statement in ADDITIONS:
        conn.execute(statement)
    return added
