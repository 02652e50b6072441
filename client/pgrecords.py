"""Read one rig's records from the PostgreSQL copy the daemons ship (`[records] postgres_url`).

    from usmswitch.client import open_records

    with open_records("postgresql://lab@db.lab/usmswitch", rig="rigA") as rig:
        for rec in rig.records(run=3):         # the same dicts, in cycle order, as from the file
            ...
        errors = rig.column("error_ns")

The same calls as `RecordsFile` (client/records.py): records, runs, run, column, dataframe, len,
last_cycle. The database may hold many rigs: name one, or leave `rig` out when it holds one only.
Needs psycopg 3 (`pip install 'usmswitch[postgres]'`). Tables: docs/fleet.md.
"""

from __future__ import annotations

from typing import Any

from usmswitch.fleet.pg_schema import (
    CYCLE_COLUMNS,
    CYCLES_TABLE,
    META_TABLE,
    PG_SCHEMA_VERSION,
    RUNS_TABLE,
    SELECT_VERSION,
    redact_url,
)
from usmswitch.protocol.record import RunRecord

from .records import RecordsFileError, RecordsSource


class PostgresRecords(RecordsSource):
    """One rig's records in a PostgreSQL database, read-only."""

    def __init__(self, url: str, rig: str | None = None, *, connect_timeout_s: int = 10) -> None:
        try:
            import psycopg
            from psycopg.rows import dict_row
        except ImportError:
            raise RecordsFileError(
                "reading records from PostgreSQL needs psycopg 3: pip install 'usmswitch[postgres]'"
            ) from None
        self.url = redact_url(url)
        try:
            self._db = psycopg.connect(
                url, connect_timeout=connect_timeout_s, autocommit=True, row_factory=dict_row
            )
        except psycopg.Error as exc:
            raise RecordsFileError(f"{self.url}: {' '.join(str(exc).split())}") from None
        self._error = psycopg.Error
        try:
            self.schema_version = self._schema_version()
            self.rig = self._pick_rig(rig)
        except BaseException:
            self._db.close()
            raise
        self.name = f"{self.url} (rig {self.rig})"

    def _query(self, sql: str, args: tuple[Any, ...] = ()) -> list[dict[str, Any]]:
        try:
            return self._db.execute(sql, args).fetchall()
        except self._error as exc:
            raise RecordsFileError(f"{self.url}: {' '.join(str(exc).split())}") from None

    def _schema_version(self) -> int:
        if self._query("SELECT to_regclass(%s) AS t", (META_TABLE,))[0]["t"] is None:
            raise RecordsFileError(f"{self.url} holds no usmswitch records (no table {META_TABLE})")
        rows = self._query(SELECT_VERSION)
        version = int(rows[0]["value"]) if rows else 0
        if not 1 <= version <= PG_SCHEMA_VERSION:
            raise RecordsFileError(
                f"{self.url} has usmswitch schema {version}; this client reads 1..{PG_SCHEMA_VERSION}"
            )
        return version

    def rigs(self) -> list[str]:
        """The rigs the database holds strokes of."""
        return [r["rig"] for r in self._query(f"SELECT DISTINCT rig FROM {CYCLES_TABLE} ORDER BY rig")]

    def _pick_rig(self, rig: str | None) -> str:
        rigs = self.rigs()
        if rig is not None:
            if rig not in rigs:
                have = ", ".join(rigs) if rigs else "none yet"
                raise RecordsFileError(f"{self.url} has no strokes of rig {rig!r} (rigs: {have})")
            return rig
        if len(rigs) != 1:
            have = ", ".join(rigs) if rigs else "none yet"
            raise RecordsFileError(f"{self.url} holds the strokes of several rigs: name one ({have})")
        return rigs[0]

    def close(self) -> None:
        """Close the connection."""
        self._db.close()

    def __len__(self) -> int:
        sql = f"SELECT count(*) AS n FROM {CYCLES_TABLE} WHERE rig = %s"
        return int(self._query(sql, (self.rig,))[0]["n"])

    @property
    def last_cycle(self) -> int:
        """The rig's highest cycle number in the database (0 when none)."""
        sql = f"SELECT coalesce(max(cycle), 0) AS c FROM {CYCLES_TABLE} WHERE rig = %s"
        return int(self._query(sql, (self.rig,))[0]["c"])

    def runs(self, label: str | None = None) -> list[dict[str, Any]]:
        """The rig's runs (with that label), oldest first."""
        # Every column there is: a database only older daemons shipped to has no label or notes.
        where, args = ("", ()) if label is None else (" AND label = %s", (label,))
        if label is not None and "label" not in self._run_columns():
            return []
        sql = f"SELECT * FROM {RUNS_TABLE} WHERE rig = %s{where} ORDER BY run_id"
        rows = self._query(sql, (self.rig, *args))
        return [RunRecord.from_row(r).to_dict() for r in rows]

    def _run_columns(self) -> set[str]:
        sql = "SELECT column_name AS c FROM information_schema.columns WHERE table_name = %s"
        return {r["c"] for r in self._query(sql, (RUNS_TABLE,))}

    def _chunk(self, after: int, last: int, run: int | None, n: int) -> list[Any]:
        where, args = ("", ()) if run is None else (" AND run_id = %s", (run,))
        return self._query(
            f"SELECT {CYCLE_COLUMNS} FROM {CYCLES_TABLE} WHERE rig = %s AND cycle > %s AND cycle <= %s"
            f"{where} ORDER BY cycle LIMIT %s",
            (self.rig, after, last, *args, n),
        )

    def _column_values(self, field: str, first: int, last: int) -> list[Any]:
        sql = (
            f'SELECT "{field}" AS v FROM {CYCLES_TABLE} WHERE rig = %s AND cycle >= %s AND cycle <= %s'
            " ORDER BY cycle"
        )
        return [r["v"] for r in self._query(sql, (self.rig, first, last))]
