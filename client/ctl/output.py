"""What usmswitchctl prints: human units out, tables, JSON, CSV rows, running figures."""

from __future__ import annotations

import csv
import json
import math
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from typing import IO, Any

from usmswitch.daemon.record import FIELDS, UNUSABLE, Flag
from usmswitch.daemon.stats import Running
from usmswitch.daemon.units import format_ns

from ..connection import CycleRecord
from .args import DIRECTION_NAMES


def show_ns(value: float | int | None) -> str:
    """A duration for people; "-" when the daemon has none yet (no strokes, a stall's missing time)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format_ns(round(value))


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


# -- output ----------------------------------------------------------------------------------------
def table(rows: Sequence[Sequence[str]], header: Sequence[str] | None = None, right_from: int = 1) -> str:
    """Aligned columns: the first `right_from` columns left-aligned, the rest right-aligned."""
    all_rows = [list(header)] if header is not None else []
    all_rows += [list(r) for r in rows]
    if not all_rows:
        return ""
    widths = [max(len(r[i]) for r in all_rows) for i in range(len(all_rows[0]))]
    lines = []
    for row in all_rows:
        cells = [
            cell.ljust(w) if i < right_from else cell.rjust(w)
            for i, (cell, w) in enumerate(zip(row, widths, strict=True))
        ]
        lines.append("  ".join(cells).rstrip())
    return "\n".join(lines)


def print_json(value: Any, out: IO[str] | None = None) -> None:
    """The raw result for scripts: one JSON document, keys sorted so diffs between runs stay small."""
    print(json.dumps(value, indent=2, sort_keys=True), file=out or sys.stdout)


def record_rows(rec: CycleRecord) -> list[list[str]]:
    """One stroke as (field, value) rows: durations in units, stamps as raw clock ns."""
    rows: list[list[str]] = []
    for name in FIELDS:
        value = rec.get(name)  # type: ignore[misc]
        if name == "direction":
            text = direction_name(value)
        elif name == "flags":
            text = flag_names(value)
        elif name == "coefficients":
            text = ", ".join(f"{c:.6g}" for c in value) or "-"
        elif name == "wall_ns":
            text = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(value / 1e9))
        elif name.startswith("t_") and name.endswith("_ns") and name != "t_hat_ns":
            text = "-" if value is None else f"{value} ns (clock)"  # instants: differences mean something
        elif name.endswith("_ns"):
            text = show_ns(value)
        elif value is None:
            text = "-"
        elif isinstance(value, float):
            text = f"{value:.6g}"
        else:
            text = str(value)
        rows.append([name, text])
    return rows


HISTORY_HEADER = (
    "cycle",
    "dir",
    "mode",
    "T",
    "t_hat",
    "delay",
    "operating",
    "total",
    "error",
    "lateness",
    "flags",
)


def history_row(rec: CycleRecord) -> list[str]:
    """One stroke as a line of the history and watch tables."""
    return [
        str(rec["cycle"]),
        direction_name(rec["direction"]),
        rec["mode"],
        show_ns(rec["target_ns"]),
        show_ns(rec["t_hat_ns"]),
        show_ns(rec["delay_ns"]),
        show_ns(rec["operating_ns"]),
        show_ns(rec["total_ns"]),
        show_ns(rec["error_ns"]),
        show_ns(rec["lateness_ns"]),
        flag_names(rec["flags"]),
    ]


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f} %"


def _count(d: dict[str, Any], key: str) -> str:
    return str(d[key]) if key in d else "-"


def stats_table(stats: dict[str, Any]) -> str:
    """The stats reply as one aligned table: a row per figure, a column per direction and both."""
    cols = [stats.get("on", {}), stats.get("off", {}), stats.get("all", {})]

    def row(label: str, fn: Callable[[dict[str, Any]], str]) -> list[str]:
        return [label, *(fn(d) if d else "-" for d in cols)]

    def ns(key: str) -> Callable[[dict[str, Any]], str]:
        return lambda d: show_ns(d.get(key)) if d.get("count") or key.startswith("lateness") else "-"

    rows = [
        row("strokes (completed)", lambda d: _count(d, "count")),
        row("strokes (incl. stalls)", lambda d: _count(d, "strokes")),
        row("operating mean", ns("operating_mean_ns")),
        row("operating std", ns("operating_std_ns")),
        row("total mean", ns("total_mean_ns")),
        row("total std", ns("total_std_ns")),
        row("error mean", ns("error_mean_ns")),
        row("error std", ns("error_std_ns")),
        row("max |error|", ns("error_max_abs_ns")),
        row("max |error| % of T", lambda d: _pct(d.get("max_abs_error_pct")) if d.get("count") else "-"),
        row("|error| p50", ns("abs_error_p50_ns")),
        row("|error| p95", ns("abs_error_p95_ns")),
        row("|error| p99", ns("abs_error_p99_ns")),
        row("late", lambda d: _count(d, "late")),
        row("stalls", lambda d: _count(d, "stalls")),
        row("bounces", lambda d: _count(d, "bounces")),
        row("faults", lambda d: _count(d, "faults")),
        row("model order", lambda d: _count(d, "order")),
        row(
            "coefficients",
            lambda d: (
                (" ".join(f"{c:.6g}" for c in d["coefficients"]) or "(none yet)")
                if "coefficients" in d
                else "-"
            ),
        ),
        row("predictor ready", lambda d: ("yes" if d["ready"] else "no (nominal)") if "ready" in d else "-"),
        row("start lateness p50", ns("lateness_p50_ns")),
        row("start lateness p99", ns("lateness_p99_ns")),
        row("start lateness max", ns("lateness_max_ns")),
    ]
    head = (
        f"state {stats.get('state', '?')}"
        + (f" ({stats['fault']})" if stats.get("fault") else "")
        + f", mode {stats.get('mode', '?')}, next cycle {stats.get('cycle', '?')}, "
        f"T on {show_ns(stats.get('target_on_ns'))} / off {show_ns(stats.get('target_off_ns'))}"
    )
    foot = (
        f"spurious edges {stats.get('spurious_edges', '-')}, overruns {stats.get('overruns', '-')}, "
        f"driver bounces {stats.get('driver_bounces', '-')}"
    )
    return "\n".join([head, "", table(rows, ["", "on", "off", "all"]), "", foot])


class RunningStats:
    """Errors and flags of the strokes watch has seen, so the live view needs no extra call per stroke."""

    def __init__(self) -> None:
        self.strokes = 0
        self.late = 0
        self.faulted = 0
        self.errors = Running()  # the daemon's own Welford accumulator

    def add(self, rec: CycleRecord) -> None:
        """Count one stroke (its error, when it has one; its flags always)."""
        self.strokes += 1
        if rec["flags"] & Flag.LATE:
            self.late += 1
        if rec["flags"] & UNUSABLE:
            self.faulted += 1
        if rec["error_ns"] is not None:
            self.errors.add(rec["error_ns"])

    @property
    def n(self) -> int:
        """Strokes with an error (completed)."""
        return self.errors.count

    @property
    def mean(self) -> float:
        return self.errors.mean

    @property
    def std(self) -> float:
        """Sample standard deviation of the errors seen (0 with fewer than two)."""
        return self.errors.std

    @property
    def max_abs(self) -> int:
        return self.errors.max_abs

    def summary(self) -> str:
        """One line for people: what the watched strokes did."""
        return (
            f"watched {self.strokes} strokes, {self.n} with an error: "
            f"mean {show_ns(self.mean)}, std {show_ns(self.std)}, "
            f"max |error| {show_ns(self.max_abs)}, late {self.late}, stall/fault/estop {self.faulted}"
        )


def watch_line(cells: Sequence[str], widths: list[int]) -> str:
    # Widths only grow, so a live view stays aligned without knowing future values.
    while len(widths) < len(cells):
        widths.append(0)
    for i, cell in enumerate(cells):
        widths[i] = max(widths[i], len(cell))
    return "  ".join(
        c.ljust(widths[i]) if i < 3 else c.rjust(widths[i]) for i, c in enumerate(cells)
    ).rstrip()


def csv_row(rec: CycleRecord) -> list[Any]:
    """One record as a CSV row in FIELDS order: coefficients as JSON text, None as an empty cell."""
    out: list[Any] = []
    for name in FIELDS:
        value = rec[name]  # type: ignore[literal-required]
        if name == "coefficients":
            value = json.dumps([float(c) for c in value])
        elif value is None:
            value = ""
        elif isinstance(value, float):
            value = repr(value)  # shortest text that reads back to the same float
        out.append(value)
    return out


def write_csv(records: Iterable[CycleRecord], out: IO[str]) -> int:
    """Write the header (the CycleRecord field names) and the records; returns how many."""
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(FIELDS)
    n = 0
    for rec in records:
        writer.writerow(csv_row(rec))
        n += 1
    return n
