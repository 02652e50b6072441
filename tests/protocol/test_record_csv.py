"""The CSV that SQLite builds (record_csv.csv_text_chunks, issue 36) is the csv module's, byte for
byte, whatever a cell holds: text that needs quoting, floats that need 17 digits or an exponent,
NULLs, unknown flag bits, a value of the wrong type in a column."""

from __future__ import annotations

import csv
import io
import math
import random
import sqlite3

import pytest

from usmswitch.protocol.record import FIELDS
from usmswitch.protocol.record_csv import (
    BadCell,
    csv_header_line,
    csv_rows_of_table,
    csv_text_chunks,
)
from usmswitch.protocol.records_schema import COLUMNS, INSERT_CYCLE, SCHEMA


def _by_csv_module(rows: list[tuple]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(csv_rows_of_table(rows))
    return buf.getvalue()


def _by_sqlite(conn: sqlite3.Connection, **kw: object) -> str:
    return "".join(text for _n, _last, text in csv_text_chunks(conn, **kw))  # type: ignore[arg-type]


ODD_TEXT = ["", "plain", "a,b", 'say "hi"', "two\nlines", "cr\rhere", "tab\there", " lead", "é ü", ",", '"']
ODD_FLOATS = [
    0.0, -0.0, 1.0, 0.1, 25.006783643336602, 40000.0, 1e-4, 9.99e-5, 1e-5, 1e15, 1e16, 123456789012345.6,
    5e-324, 1.7976931348623157e308, -2.5, math.inf, -math.inf, math.nan, 1 / 3, 2 / 3 * 1e-7,
]  # fmt: skip


def _odd_rows(n: int, seed: int = 1) -> list[tuple]:
    rng = random.Random(seed)
    rows = []
    for cycle in range(1, n + 1):
        r = {f: rng.randrange(-(2**62), 2**62) for f in FIELDS}
        r.update(cycle=cycle, direction=cycle % 2, mode=rng.choice(("closed", "open")), order=1)
        r["delay_ns"] = abs(r["delay_ns"])
        r["coefficients"] = rng.choice(("[]", "[0.5]", "[0.9, -0.1]", "[1e-05, 2.5e+16]"))
        r["flags"] = rng.choice((0, 0, 1, 3, 64, 1 << 20, 5 | (1 << 30)))
        for f in ("temperature_c", "frequency_hz"):
            r[f] = rng.choice((None, rng.random() * 100, rng.choice(ODD_FLOATS), rng.uniform(-1e20, 1e20)))
        for f in ("t_start_ns", "error_ns", "lateness_ns"):
            if rng.random() < 0.2:
                r[f] = None
        r["driver"] = rng.choice((None, *ODD_TEXT))
        r["rig"] = rng.choice((None, *ODD_TEXT))
        r["run_id"] = 1 + cycle // 100
        rows.append(tuple(r[f] for f in FIELDS))
    return rows


def test_sqlites_csv_is_the_csv_modules_byte_for_byte() -> None:
    conn = sqlite3.connect(":memory:")
    conn.executescript(SCHEMA)
    rows = _odd_rows(3000)
    conn.executemany(INSERT_CYCLE, rows)
    # A cell of the wrong type: SQLite keeps a float or text where an integer belongs (no STRICT).
    conn.execute("UPDATE cycles SET delay_ns = 1.5, wall_ns = 'x,y' WHERE cycle = 7")
    conn.execute("UPDATE cycles SET temperature_c = 'warm' WHERE cycle = 8")
    # Text holding the character that marks a float's place in SQLite's line: that chunk is made
    # the slow way (every float called back), the same bytes.
    conn.execute("UPDATE cycles SET rig = 'a' || char(31) || 'b', temperature_c = 2.5 WHERE cycle = 9")
    stored = conn.execute(f"SELECT {COLUMNS} FROM cycles ORDER BY cycle").fetchall()
    want = _by_csv_module(stored)
    assert _by_sqlite(conn, chunk=1000) == want
    assert _by_sqlite(conn, chunk=7) == want  # chunk edges change nothing
    # A range, and one run's strokes.
    part = [r for r in stored if 100 <= r[0] <= 250]
    assert _by_sqlite(conn, first=100, last=250) == _by_csv_module(part)
    run = [r for r in stored if r[FIELDS.index("run_id")] == 5]
    assert _by_sqlite(conn, run_id=5, chunk=33) == _by_csv_module(run)
    assert _by_sqlite(conn, run_id=999) == ""
    header = io.StringIO()
    from usmswitch.protocol.record_csv import CSV_HEADER

    csv.writer(header, lineterminator="\n").writerow(CSV_HEADER)
    assert csv_header_line() == header.getvalue()


def test_floats_read_back_as_the_csv_modules_repr() -> None:
    # The REAL columns are the cells SQLite's own printf would round (15 digits): a million random
    # doubles of every magnitude come out as Python's repr.
    conn = sqlite3.connect(":memory:")
    conn.executescript(SCHEMA)
    rng = random.Random(7)
    base = _odd_rows(1)[0]
    t = FIELDS.index("temperature_c")
    rows = []
    for cycle in range(1, 20_001):
        value = rng.choice((rng.random() * 10 ** rng.randrange(-30, 30), rng.gauss(25, 3)))
        row = list(base)
        row[0], row[t] = cycle, value
        # A column of few distinct values (formatted once a value), and one with a zero among them.
        row[t + 1] = rng.choice((40000.0, 39500.5, -0.0 if cycle > 10_000 else 41000.0))
        rows.append(tuple(row))
    conn.executemany(INSERT_CYCLE, rows)
    stored = conn.execute(f"SELECT {COLUMNS} FROM cycles ORDER BY cycle").fetchall()  # -0.0 reads 0.0
    assert _by_sqlite(conn) == _by_csv_module(stored)


def test_a_chunk_with_a_bad_cell_is_refused_before_it_is_given() -> None:
    conn = sqlite3.connect(":memory:")
    conn.executescript(SCHEMA)
    conn.executemany(INSERT_CYCLE, _odd_rows(50))
    conn.execute("UPDATE cycles SET coefficients = 'not json' WHERE cycle = 23")
    got = []
    with pytest.raises(BadCell, match="cycle 23"):
        for n, last, _text in csv_text_chunks(conn, chunk=10):
            got.append((n, last))
    assert got == [(10, 10), (10, 20)]


def test_a_file_from_before_runs_and_sources_reads_them_as_empty() -> None:
    conn = sqlite3.connect(":memory:")
    old = SCHEMA.replace("    driver TEXT,\n    rig TEXT,\n    run_id INTEGER\n", "    wall_x INTEGER\n")
    old = old.replace("    wall_ns INTEGER NOT NULL,\n    wall_x INTEGER", "    wall_ns INTEGER NOT NULL")
    keep = [line for line in old.splitlines() if not line.startswith("CREATE INDEX IF NOT EXISTS cycles_")]
    old = "\n".join(keep)
    assert "run_id" not in old.split("CREATE TABLE IF NOT EXISTS runs")[0]
    old += "\nCREATE INDEX cycles_direction ON cycles (direction, cycle);"
    conn.executescript(old)
    n_old = len(FIELDS) - 3
    rows = [r[:n_old] for r in _odd_rows(40)]
    conn.executemany(f"INSERT INTO cycles VALUES ({', '.join('?' * n_old)})", rows)
    stored = conn.execute("SELECT * FROM cycles ORDER BY cycle").fetchall()  # a NaN is kept as NULL
    assert _by_sqlite(conn) == _by_csv_module([(*r, None, None, None) for r in stored])
    assert _by_sqlite(conn, run_id=1) == ""
