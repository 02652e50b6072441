"""`open_records(source)`: a rig's records from a records file, a state directory or PostgreSQL."""

from __future__ import annotations

import os

from usmswitch.fleet.pg_schema import is_postgres_url

from .records import RecordsFile, RecordsSource


def open_records(source: str | os.PathLike[str], rig: str | None = None) -> RecordsSource:
    """A reader of the records at `source`: a `postgresql://` URL (one `rig` of the database; may
    be left out when it holds one rig only), else a records file or a state directory (a file holds
    one rig's records: `rig` is not needed)."""
    text = os.fspath(source)
    if is_postgres_url(text):
        from .pgrecords import PostgresRecords  # psycopg, only when a database is asked for

        return PostgresRecords(text, rig)
    return RecordsFile(text)
