"""The PostgreSQL copy of the records: its tables, the SQL that fills and reads them, URL redaction.

Pure (no psycopg here): the daemon's shipper (`shipper.py`) writes these tables and the client's
reader (`usmswitch.client.pgrecords`) reads them, with the same names. Many rigs share one database:
every row carries its `rig`, and the primary key is `(rig, cycle)`. Schema: docs/fleet.md.
"""

from __future__ import annotations

from typing import Any
from urllib.parse import SplitResult, urlsplit, urlunsplit

from usmswitch.protocol.record import FIELDS, LATER_RUN_FIELDS, RUN_FIELDS

#: The version of these tables; the shipper creates them at start and refuses a newer database.
PG_SCHEMA_VERSION = 1
META_TABLE = "usmswitch_meta"
CYCLES_TABLE = "usmswitch_cycles"
RUNS_TABLE = "usmswitch_runs"
URL_SCHEMES = ("postgresql", "postgres")
#: Held (pg_advisory_xact_lock) while the schema is created or checked: daemons starting together
#: would otherwise race in CREATE TABLE IF NOT EXISTS (a unique violation in pg_type).
SCHEMA_LOCK_KEY = 0x75736D73  # "usms"

#: Each record field's column type; `rig` is part of the key, so never NULL here.
CYCLE_COLUMN_TYPES: dict[str, str] = {
    "cycle": "bigint NOT NULL CHECK (cycle >= 1)",
    "direction": "smallint NOT NULL CHECK (direction IN (0, 1))",
    "mode": "text NOT NULL",
    "target_ns": "bigint NOT NULL",
    "order": "smallint NOT NULL",
    "coefficients": "double precision[] NOT NULL",
    "t_hat_ns": "bigint NOT NULL",
    "delay_ns": "bigint NOT NULL",
    "t_cmd_ns": "bigint NOT NULL",
    "t_start_ns": "bigint",
    "t_depart_ns": "bigint",
    "t_arrive_ns": "bigint",
    "operating_ns": "bigint",
    "total_ns": "bigint",
    "error_ns": "bigint",
    "dead_ns": "bigint",
    "lateness_ns": "bigint",
    "temperature_c": "double precision",
    "frequency_hz": "double precision",
    "flags": "integer NOT NULL",
    "wall_ns": "bigint NOT NULL",
    "driver": "text",
    "rig": "text NOT NULL",
    "run_id": "integer",
}
RUN_COLUMN_TYPES: dict[str, str] = {
    "run_id": "integer NOT NULL",
    "kind": "text NOT NULL",
    "first_cycle": "bigint NOT NULL",
    "started_wall_ns": "bigint NOT NULL",
    "settings": "jsonb NOT NULL",
    "last_cycle": "bigint",
    "ended_wall_ns": "bigint",
    "end_reason": "text",
    "driver": "text",
    "rig": "text NOT NULL",
    "label": "text",
    "notes": "text",
}
if tuple(CYCLE_COLUMN_TYPES) != FIELDS or tuple(RUN_COLUMN_TYPES) != RUN_FIELDS:
    raise ImportError("pg_schema: the column lists must follow record.FIELDS and RUN_FIELDS")


def _columns(names: tuple[str, ...]) -> str:
    return ", ".join(f'"{f}"' for f in names)


CYCLE_COLUMNS = _columns(FIELDS)
RUN_COLUMNS = _columns(RUN_FIELDS)

SCHEMA = [
    f"CREATE TABLE IF NOT EXISTS {META_TABLE} (key text PRIMARY KEY, value text NOT NULL)",
    "CREATE TABLE IF NOT EXISTS {} ({}, PRIMARY KEY (rig, cycle))".format(
        CYCLES_TABLE, ", ".join(f'"{f}" {t}' for f, t in CYCLE_COLUMN_TYPES.items())
    ),
    f"CREATE INDEX IF NOT EXISTS {CYCLES_TABLE}_run ON {CYCLES_TABLE} (rig, run_id, cycle)",
    f"CREATE INDEX IF NOT EXISTS {CYCLES_TABLE}_wall ON {CYCLES_TABLE} (wall_ns)",
    "CREATE TABLE IF NOT EXISTS {} ({}, PRIMARY KEY (rig, run_id))".format(
        RUNS_TABLE, ", ".join(f'"{f}" {t}' for f, t in RUN_COLUMN_TYPES.items())
    ),
]
#: Migrations to PG_SCHEMA_VERSION, each from the version before (none yet).
MIGRATIONS: dict[int, list[str]] = {}
#: Additions to the schema of this version, made at a start that finds them missing: new columns an
#: older daemon neither writes nor minds, so the version stays and daemons not yet upgraded still
#: ship. Checked first (ALTER TABLE takes the table's exclusive lock even when there is nothing to do).
MISSING_ADDITIONS = (
    "SELECT count(*) FROM information_schema.columns WHERE table_schema = current_schema()"
    f" AND table_name = '{RUNS_TABLE}' AND column_name IN ({', '.join(repr(f) for f in LATER_RUN_FIELDS)})"
)
ADDITIONS = [
    f'ALTER TABLE {RUNS_TABLE} ADD COLUMN IF NOT EXISTS "{name}" {RUN_COLUMN_TYPES[name]}'
    for name in LATER_RUN_FIELDS
] + [f"CREATE INDEX IF NOT EXISTS {RUNS_TABLE}_label ON {RUNS_TABLE} (label, rig, run_id)"]
SELECT_VERSION = f"SELECT value FROM {META_TABLE} WHERE key = 'schema_version'"
SET_VERSION = (
    f"INSERT INTO {META_TABLE} (key, value) VALUES ('schema_version', %s)"
    " ON CONFLICT (key) DO UPDATE SET value = excluded.value"
)
#: The strokes of a batch go to a temporary table by COPY, then into the shared one: rows the
#: database already holds are skipped (idempotent), and the count says how many were new.
STAGE_TABLE = "usmswitch_stage"
CREATE_STAGE = (
    f"CREATE TEMPORARY TABLE IF NOT EXISTS {STAGE_TABLE} (LIKE {CYCLES_TABLE}) ON COMMIT DELETE ROWS"
)
COPY_STAGE = f"COPY {STAGE_TABLE} ({CYCLE_COLUMNS}) FROM STDIN"
INSERT_FROM_STAGE = (
    f"INSERT INTO {CYCLES_TABLE} ({CYCLE_COLUMNS}) SELECT {CYCLE_COLUMNS} FROM {STAGE_TABLE}"
    " ON CONFLICT (rig, cycle) DO NOTHING"
)
UPSERT_RUN = "INSERT INTO {} ({}) VALUES ({}) ON CONFLICT (rig, run_id) DO UPDATE SET {}".format(
    RUNS_TABLE,
    RUN_COLUMNS,
    ", ".join("%s::jsonb" if f == "settings" else "%s" for f in RUN_FIELDS),
    ", ".join(f'"{f}" = excluded."{f}"' for f in RUN_FIELDS if f not in ("rig", "run_id")),
)
#: Where shipping resumes: the highest cycle of a rig the database holds, and that row's stamps
#: (a database that holds another file's strokes under this rig's name is refused, not merged).
LAST_SHIPPED = (
    f"SELECT cycle, t_cmd_ns, wall_ns FROM {CYCLES_TABLE} WHERE rig = %s ORDER BY cycle DESC LIMIT 1"
)
#: The first run of a rig that may still change (open when last shipped), else the one after the last.
RUNS_FROM = (
    f"SELECT coalesce(min(run_id) FILTER (WHERE end_reason IS NULL), max(run_id) + 1, 1)"
    f" FROM {RUNS_TABLE} WHERE rig = %s"
)


_COEFFICIENTS = FIELDS.index("coefficients")
_RIG = FIELDS.index("rig")
_RUN_RIG = RUN_FIELDS.index("rig")


def pg_cycle(row: tuple[Any, ...], rig: str) -> tuple[Any, ...]:
    """A records-file row (FIELDS order, as `CycleRecord.to_row()`) as a COPY row of
    usmswitch_cycles: the JSON array of coefficients as an array literal, and the rig the shipping
    daemon's (the key of all its file's strokes there, a row an earlier name stamped included)."""
    coefficients = "{" + row[_COEFFICIENTS][1:-1] + "}"
    return (*row[:_COEFFICIENTS], coefficients, *row[_COEFFICIENTS + 1 : _RIG], rig, *row[_RIG + 1 :])


def pg_run(row: tuple[Any, ...], rig: str) -> tuple[Any, ...]:
    """A records-file runs row (RUN_FIELDS order, settings as JSON text) as UPSERT_RUN's parameters."""
    return (*row[:_RUN_RIG], rig, *row[_RUN_RIG + 1 :])


def is_postgres_url(text: str) -> bool:
    """Whether `text` names a PostgreSQL database (postgresql://...) rather than a file."""
    return urlsplit(text).scheme in URL_SCHEMES


def check_url(url: str) -> str:
    """`url` if it is a postgresql:// URL with a host or socket; ValueError saying what is wrong."""
    parts = urlsplit(url)
    if parts.scheme not in URL_SCHEMES:
        raise ValueError(
            f"{redact_url(url)!r} is not a PostgreSQL URL: write postgresql://USER@HOST:PORT/DATABASE"
        )
    try:
        parts.port  # noqa: B018  (raises on a port that is not a number)
    except ValueError as exc:
        raise ValueError(f"{redact_url(url)!r}: {exc}") from None
    if not parts.path.strip("/") and "dbname=" not in parts.query:
        raise ValueError(f"{redact_url(url)!r} names no database: postgresql://USER@HOST:PORT/DATABASE")
    return url


def redact_url(url: str) -> str:
    """The URL with its password (if any) replaced by ***, for logs, status and errors."""
    try:
        parts = urlsplit(url)
    except ValueError:
        return "<unparsable URL>"
    netloc = parts.netloc
    if "@" in netloc:
        userinfo, _, hostport = netloc.rpartition("@")
        user, sep, _ = userinfo.partition(":")
        netloc = f"{user}:***@{hostport}" if sep else netloc
    query = "&".join(
        "password=***" if p.lower().startswith("password=") else p for p in parts.query.split("&") if p
    )
    return urlunsplit(SplitResult(parts.scheme, netloc, parts.path, query, parts.fragment))
