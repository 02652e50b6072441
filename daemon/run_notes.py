"""A run's label and notes edited after its open (`annotate_run`): who may, and the write.

A run's notes are a lab notebook's line: what it was for, what was seen. Its owner edits them (the
same `user@host` as the owner its `start_cycling` named, whatever the process), an operator any
run's (`operator=True`). The socket's access is its file's group and TCP's token: every client
there is trusted alike, so this is a guard against editing another's run by mistake, as
`take_over` is for ending one, not a check of who the caller is.

The edit is written by the record writer in order with the strokes (`RecordStore.write`), with an
event `notes` (what was set, by whom), which the PostgreSQL shipper follows to send the run again.
"""

from __future__ import annotations

import sqlite3
from typing import Any

from usmswitch.protocol.record import RunRecord


def owner_person(owner: str) -> str:
    """Who an owner text names, without the process: `alice@lab` of `alice@lab pid 7 (x.py)`."""
    return owner.split(" pid ", 1)[0].strip()


def may_edit(run: RunRecord, owner: str, operator: bool) -> str | None:
    """None when `owner` may edit `run`'s label and notes, else why not (for the STATE error)."""
    if operator:
        return None
    by = str(run.settings.get("owner") or "")
    if by and owner_person(by) == owner_person(owner):
        return None
    whose = f"{owner_person(by)}'s" if by else "no one's (its owner was not recorded)"
    return (
        f"run {run.run_id} is {whose}: its owner edits its label and notes, or an operator"
        " (operator=True, `usmswitchctl notes RUN TEXT --operator`)"
    )


def edit(run_id: int, label: str | None, notes: str | None) -> Any:
    """The write for `RecordStore.write`: the run's label and/or notes set (None: unchanged; "":
    cleared), then its row as it now is (None: no such run in the file)."""

    def apply(conn: sqlite3.Connection) -> RunRecord | None:
        for column, value in (("label", label), ("notes", notes)):
            if value is not None:
                conn.execute(f"UPDATE runs SET {column} = ? WHERE run_id = ?", (value or None, run_id))
        cur = conn.cursor()
        cur.row_factory = sqlite3.Row
        row = cur.execute("SELECT * FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        return None if row is None else RunRecord.from_row(row)

    return apply
