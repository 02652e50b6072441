"""The records file's WAL folded back in and its -wal and -shm files removed when the file is closed.

SQLite removes them at the close of the last connection to the file, if that connection may write:
a read-only one never does, and a read-only open even makes them again. The store's own readers and
a sibling process's (the shipper's, the socket's server process's) may close after the writer, so
whoever closes the file last for good says so here, with a read-write connection opened and closed.
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path
from urllib.parse import quote

import structlog

log = structlog.get_logger("usmswitch.records")


def settle_wal(path: str | os.PathLike[str]) -> bool:
    """Checkpoint the WAL into `path` and let SQLite remove -wal and -shm; True when they are gone.

    Never waits (no busy timeout, a PASSIVE checkpoint: a shutdown is bounded, docs/daemon.md). Left
    in place while another connection (another process's) still has the file open: then its own
    close cannot remove them, and the next writer's open folds them in as SQLite always does."""
    p = Path(path)
    # mode=rw: never a new, empty file where the records file has gone.
    uri = f"file:{quote(str(p.resolve()))}?mode=rw"
    try:
        conn = sqlite3.connect(uri, uri=True, isolation_level=None, timeout=0)
        try:
            # Opens the file (a connection alone does not); the close, if last, folds the rest in.
            conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
        finally:
            conn.close()
    except sqlite3.Error as exc:
        log.warning("record file WAL not settled at close", path=str(p), error=str(exc))
        return False
    return not any(Path(f"{p}{suffix}").exists() for suffix in ("-wal", "-shm"))
