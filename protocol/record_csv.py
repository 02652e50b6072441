"""The CSV form of cycle records: one format for `usmswitchctl export` and the panel's run export.

Columns: every record field (FIELDS) in order, then the direction and flags as names beside their
numbers for a person reading the sheet; `CycleRecord.from_row` reads it back and ignores those two.
"""

from __future__ import annotations

import csv
import functools
import io
import json
import sqlite3
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


# -- the same CSV made by SQLite: a chunk of rows as one string (issue 36) --------------------------
#
# The csv module writes ~1 us of Python a cell; `sqlite3 -csv` none. Here SQLite builds each line's
# text (printf over the columns) and a chunk's lines into one string (group_concat), so Python
# touches one string per chunk. The cells are the csv module's, byte for byte: integers and text as
# they are, text quoted (quotes doubled) when it holds a character that makes this Python's csv
# writer quote, None empty; what SQLite cannot say the same way (a float's repr, the flag names, a
# cell of an unexpected type) is handed to a Python function by the same rules.


def _quoting_chars() -> tuple[str, ...]:
    """The characters that make this Python's csv writer (lineterminator "\n") quote a cell."""
    out = []
    for ch in (",", '"', "\n", "\r", "\t", " ", ";", "'"):
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow([f"a{ch}b", 0])
        if buf.getvalue().startswith('"'):
            out.append(ch)
    return tuple(out)


_QUOTING = _quoting_chars()


def csv_cell(value: Any) -> str:
    """One cell as the csv module writes it (None empty, a float its repr, text quoted when needed)."""
    if type(value) is float:
        return repr(value)
    if value is None:
        return ""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow([value, 0])
    return buf.getvalue()[: -len(",0\n")]


@functools.lru_cache(maxsize=4096)
def _flags_cell(flags: Any) -> str:
    name = flag_names(flags)
    return "" if name == "-" else csv_cell(name)


def _direction_cell(direction: Any) -> str:
    return csv_cell(direction_name(direction))


#: The Python functions the CSV SQL calls, by name: (number of arguments, function).
CSV_SQL_FUNCTIONS: dict[str, tuple[int, Any]] = {
    "usm_csv_cell": (1, csv_cell),
    "usm_csv_flags": (1, _flags_cell),
    "usm_csv_direction": (1, _direction_cell),
}


def register_csv_functions(conn: sqlite3.Connection) -> None:
    """Give a connection the functions `csv_line_sql` calls."""
    for name, (nargs, fn) in CSV_SQL_FUNCTIONS.items():
        conn.create_function(name, nargs, fn, deterministic=True)


def _cell_sql(name: str, decltype: str | None) -> str:
    x = f'"{name}"'
    if decltype is None:  # a column an older file lacks: None, an empty cell
        return "''"
    kind = decltype.upper()
    if "INT" in kind:
        return f"CASE typeof({x}) WHEN 'integer' THEN {x} WHEN 'null' THEN '' ELSE usm_csv_cell({x}) END"
    if "CHAR" in kind or "TEXT" in kind or "CLOB" in kind:
        special = " OR ".join(f"instr({x}, char({ord(c)}))" for c in _QUOTING)
        quoted = f"'\"' || replace({x}, '\"', '\"\"') || '\"'"
        return (
            f"CASE WHEN typeof({x}) <> 'text' THEN usm_csv_cell({x})"
            f" WHEN {special} THEN {quoted} ELSE {x} END"
        )
    return f"CASE WHEN {x} IS NULL THEN '' ELSE usm_csv_cell({x}) END"  # REAL: repr, in Python


#: Where a REAL cell goes in a line SQLite builds with `slots`: Python fills it with the value's repr.
SLOT = "\x1f"


def _is_real(decltype: str | None) -> bool:
    """A column whose cells `csv_line_sql(slots=True)` leaves to Python (neither INT nor TEXT)."""
    kind = (decltype or "INT").upper()
    return not ("INT" in kind or "CHAR" in kind or "TEXT" in kind or "CLOB" in kind)


def csv_line_sql(columns: Mapping[str, str | None], *, slots: bool = False) -> str:
    """The SQL expression of one cycles row's CSV line (CSV_HEADER order, no line end): `columns`
    maps each column the table has to its declared type; a FIELDS name missing reads empty.
    `slots`: each REAL cell is SLOT, for `csv_text_chunks` to fill with the values read apart (a
    float's repr is Python's: a call back per cell cost ~2.5 us, a third of an export)."""
    cells = [
        f"'{SLOT}'" if slots and f in columns and _is_real(columns[f]) else _cell_sql(f, columns.get(f))
        for f in FIELDS
    ]  # a typeless column: "", not None
    cells.append("CASE direction WHEN 0 THEN 'on' WHEN 1 THEN 'off' ELSE usm_csv_direction(direction) END")
    cells.append("CASE flags WHEN 0 THEN '' ELSE usm_csv_flags(flags) END")
    return "printf('" + ",".join(["%s"] * len(cells)) + "', " + ", ".join(cells) + ")"


def csv_header_line(runs: Iterable[Mapping[str, Any]] = ()) -> str:
    """The CSV's first line, as the csv module writes CSV_HEADER, after a comment line for each of
    `runs` (the runs the export covers) with a label or notes (`csv_run_lines`)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(CSV_HEADER)
    return csv_run_lines(runs) + buf.getvalue()


#: What starts a comment line of a CSV export (a run's label and notes), before the header.
CSV_COMMENT = "#"


def csv_run_lines(runs: Iterable[Mapping[str, Any]]) -> str:
    """One line for each run with a label or notes: `# run 3: {"label": "sweep-12", "notes": "..."}`,
    a JSON object on one line (newlines in the notes escaped). An export of runs with neither has
    none: the same bytes as before labels. Readers skip them (`pandas.read_csv(f, comment="#")`;
    no cell of a stroke starts with `#`)."""
    lines = []
    for run in runs:
        said = {k: run.get(k) for k in ("label", "notes") if run.get(k)}
        if said:
            lines.append(f"{CSV_COMMENT} run {run['run_id']}: {json.dumps(said, ensure_ascii=False)}\n")
    return "".join(lines)


class BadCell(ValueError):
    """A stroke's cell would not read back as a record (its coefficients are not JSON)."""

    def __init__(self, cycle: int) -> None:
        super().__init__(f"cycle {cycle}: its coefficients are not JSON")
        self.cycle = cycle


def _csv_column(values: Sequence[Any]) -> list[str]:
    """One REAL column's cells as the csv module writes them: a float's repr, None empty, anything
    else `csv_cell`. A column of few distinct floats (the drive's frequency) is formatted once a
    value; 0.0 and -0.0 are equal keys with different reprs, so a column holding zero is not."""
    if set(map(type, values)) == {float}:
        distinct = set(values)
        if 4 * len(distinct) <= len(values) and 0.0 not in distinct:
            return list(map({v: repr(v) for v in distinct}.__getitem__, values))
        return list(map(repr, values))
    return [repr(v) if type(v) is float else csv_cell(v) for v in values]


def csv_text_chunks(
    conn: sqlite3.Connection,
    first: int = 1,
    last: int | None = None,
    run_id: int | None = None,
    chunk: int = 10_000,
    *,
    label: str | None = None,
) -> Iterator[tuple[int, int, str]]:
    """The CSV lines (each ending "\n") of the records file's strokes from cycle `first` to `last`
    (of one run; of the runs with `label`), `chunk` strokes a read, each read its own short
    transaction: (strokes, the last cycle, text) per chunk. SQLite builds the lines (printf of the
    cells, group_concat of the lines) with a SLOT for each REAL cell; the REAL columns are read in
    the same transaction and their reprs put in the slots by one join. BadCell where a stroke's
    coefficients are not JSON (as a record's read refuses them), before that chunk's text is given."""
    register_csv_functions(conn)
    cur = conn.cursor()
    cur.row_factory = None  # plain tuples, whatever the connection's rows are
    columns = {r[1]: r[2] for r in cur.execute("PRAGMA table_info(cycles)")}
    where = " AND run_id = ?" if run_id is not None else ""
    if run_id is not None and "run_id" not in columns:
        return  # a file from before runs has no run's strokes
    if label is not None:
        if "label" not in {r[1] for r in cur.execute("PRAGMA table_info(runs)")}:
            return  # a file from before labels (or runs) has no labelled run's strokes
        where += " AND run_id IN (SELECT run_id FROM runs WHERE label = ?)"
    reals = [f for f in FIELDS if f in columns and _is_real(columns[f])]

    def lines_sql(slots: bool) -> str:
        return (
            "SELECT count(*), max(cycle), group_concat(line, char(10)),"
            " min(CASE WHEN ok THEN NULL ELSE cycle END)"
            f" FROM (SELECT cycle, {csv_line_sql(columns, slots=slots)} AS line,"
            f" json_valid(coefficients) AS ok FROM cycles WHERE cycle > ? AND cycle <= ?{where}"
            " ORDER BY cycle LIMIT ?)"
        )

    sql = lines_sql(bool(reals))
    values_sql = (
        f"SELECT {', '.join(f'{chr(34)}{f}{chr(34)}' for f in reals)} FROM cycles"
        f" WHERE cycle > ? AND cycle <= ?{where} ORDER BY cycle"
    )
    after = first - 1
    stop = last if last is not None else (1 << 63) - 1
    args = (*(() if run_id is None else (run_id,)), *(() if label is None else (label,)))
    while True:
        own = not conn.in_transaction  # the lines and the values from one snapshot of the file
        if own:
            cur.execute("BEGIN")
        try:
            n, top, text, bad = cur.execute(sql, (after, stop, *args, chunk)).fetchone()
            if n and bad is None and reals:
                parts = text.split(SLOT)
                rows = cur.execute(values_sql, (after, top, *args)).fetchall()
                cells: list[str] = [""] * (len(rows) * len(reals))
                for i, column in enumerate(zip(*rows, strict=True)):
                    cells[i :: len(reals)] = _csv_column(column)
                if len(parts) == len(cells) + 1:
                    joined: list[str] = [""] * (2 * len(cells) + 1)
                    joined[0::2] = parts
                    joined[1::2] = cells
                    text = "".join(joined)
                else:  # a text cell holds SLOT itself: this chunk the slow way, each float called back
                    text = cur.execute(lines_sql(False), (after, top, *args, chunk)).fetchone()[2]
        finally:
            if own:
                cur.execute("COMMIT")
        if not n:
            return
        if bad is not None:
            raise BadCell(bad)
        yield n, top, text + "\n"
        after = top
