"""The CSV form of cycle records: one format for `usmswitchctl export` and the panel's run export.

Columns: every record field (FIELDS) in order, then the direction and flags as names beside their
numbers for a person reading the sheet; `CycleRecord.from_row` reads it back and ignores those two.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import IO, Any

from .record import FIELDS, Flag

#: The words for a record's direction (0 = on, A to B; 1 = off).
DIRECTION_NAMES = ("on", "off")
#: Columns a CSV export adds after the record's fields: the direction and flags as names beside
#: their numbers (`on`/`off`, `LATE|CLAMPED`), for a person reading the sheet; readers that rebuild
#: records (`CycleRecord.from_row`) ignore them.
CSV_NAME_COLUMNS: tuple[str, ...] = ("direction_name", "flag_names")
CSV_HEADER: tuple[str, ...] = (*FIELDS, *CSV_NAME_COLUMNS)


def flag_names(flags: int) -> str:
    """Record flag bits as names ("LATE|WARMUP"), "-" for a clean stroke."""
    names = [f.name for f in Flag if f.name is not None and flags & f]
    unknown = flags & ~sum(Flag)
    if unknown:
        names.append(hex(unknown))
    return "|".join(names) or "-"


def direction_name(direction: int) -> str:
    """A record's direction (0, 1) as the word the commands take."""
    return DIRECTION_NAMES[direction] if direction in (0, 1) else str(direction)


def csv_row(rec: Mapping[str, Any]) -> list[Any]:
    """One record (its dict) as a CSV row in CSV_HEADER order: coefficients as JSON text, None as an
    empty cell, floats as the shortest text that reads back to the same float."""
    out: list[Any] = []
    for name in FIELDS:
        value = rec[name]
        if name == "coefficients":
            value = json.dumps([float(c) for c in value])
        elif value is None:
            value = ""
        elif isinstance(value, float):
            value = repr(value)
        out.append(value)
    flags = flag_names(rec["flags"])
    out += [direction_name(rec["direction"]), "" if flags == "-" else flags]
    return out


def csv_rows_of_table(rows: Iterable[Sequence[Any]]) -> Iterator[tuple[Any, ...]]:
    """Rows of the records file's `cycles` table as read (FIELDS order, the coefficients as their
    stored JSON text) as CSV rows in CSV_HEADER order, the same cells `csv_row` makes of a record,
    at the speed of the csv module: what exports stream (issue 36: 43-67 us a stroke through
    records and dicts, against ~1 us for sqlite3 -csv). The csv writer writes None as an empty cell
    and a float as its repr, as csv_row does."""
    names: dict[int, str] = {}
    d = FIELDS.index("direction")
    f = FIELDS.index("flags")
    for row in rows:
        flags = row[f]
        name = names.get(flags)
        if name is None:
            name = flag_names(flags)
            name = names.setdefault(flags, "" if name == "-" else name)
        yield (*row, direction_name(row[d]), name)


def write_csv(records: Iterable[Mapping[str, Any]], out: IO[str]) -> int:
    """Write the header (CSV_HEADER) and the records; returns how many."""
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    n = 0
    for rec in records:
        writer.writerow(csv_row(rec))
        n += 1
    return n
