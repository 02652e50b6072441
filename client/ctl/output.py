"""What usmswitchctl prints: human units out, tables, JSON, CSV rows, running figures."""

from __future__ import annotations

import contextlib
import datetime
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import IO, Any

from usmswitch.protocol.record import FIELDS, UNUSABLE, Flag
from usmswitch.protocol.record_csv import (  # noqa: F401 (re-exported: the commands use them from here)
    CSV_HEADER,
    CSV_NAME_COLUMNS,
    csv_row,
    direction_name,
    flag_names,
    write_csv,
)
from usmswitch.protocol.stats import Running
from usmswitch.protocol.units import format_elapsed, format_ns, is_instant_field

from ..types import CycleRecord
from .args import WATCH_HEADER_EVERY


def show_ns(value: float | int | None) -> str:
    """A duration for people; "-" when the daemon has none yet (no strokes, a stall's missing time)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format_ns(round(value))


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


#: What a person reads for each record field (`switch`); a field not named here shows as it is.
FIELD_LABELS: dict[str, str] = {
    "direction": "direction",
    "target_ns": "target",
    "order": "model order",
    "t_hat_ns": "t_hat (predicted)",
    "delay_ns": "delay T_d",
    "t_cmd_ns": "command at",
    "t_start_ns": "start at",
    "t_depart_ns": "depart at",
    "t_arrive_ns": "arrive at",
    "operating_ns": "operating time",
    "total_ns": "total",
    "error_ns": "error",
    "dead_ns": "dead time",
    "lateness_ns": "start lateness",
    "temperature_c": "temperature",
    "frequency_hz": "frequency",
    "wall_ns": "time",
    "run_id": "run",
}


def field_label(name: str) -> str:
    """A record field's name for people ("target_ns" -> "target")."""
    return FIELD_LABELS.get(name, name.removesuffix("_ns"))


def record_rows(rec: CycleRecord) -> list[list[str]]:
    """One stroke as (label, value) rows: durations in units, stamps as raw clock ns."""
    rows: list[list[str]] = []
    for name in FIELDS:
        value = rec.get(name)  # type: ignore[misc]
        if value is None:
            text = "-"
        elif name == "direction":
            text = direction_name(value)
        elif name == "flags":
            text = flag_names(value)
        elif name == "coefficients":
            text = ", ".join(f"{c:.6g}" for c in value) or "-"
        elif name == "wall_ns":
            text = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(value / 1e9))
        elif is_instant_field(name):
            text = f"{value} ns (clock)"  # instants: only differences mean something
        elif name.endswith("_ns"):
            text = show_ns(value)
        elif name == "temperature_c":
            text = f"{value:.2f} °C"
        elif name == "frequency_hz":
            text = show_hz(value)
        elif isinstance(value, float):
            text = f"{value:.6g}"
        else:
            text = str(value)
        rows.append([field_label(name), text])
    return rows


def show_hz(value: float | None) -> str:
    """An excitation frequency for people: "40.0000 kHz"."""
    return "-" if value is None else f"{value / 1000:.4f} kHz"


def status_table(st: dict[str, Any]) -> str:
    """The status reply for people: one row per figure, uptime as a person reads it."""
    answering = {True: " (answering)", False: " (NOT answering)"}.get(st.get("driver_ok"), "")
    rows = [
        ["state", st["state"]],
        ["fault", st["fault"] or "-"],
        ["mode", st["mode"]],
        ["target on", show_ns(st["target_on_ns"])],
        ["target off", show_ns(st["target_off_ns"])],
        ["next cycle", str(st["cycle"])],
        ["driver", st["driver"] + answering],
        ["loop scheduling", st.get("scheduling", "-")],
        ["version", f"{st['version']} (protocol {st['protocol_version']})"],
        ["uptime", format_elapsed(st["uptime_ns"])],
    ]
    return table(rows, right_from=2)


#: The drive reply's fields as a person reads them: label and formatter.
_DRIVE_ROWS: dict[str, tuple[str, Callable[[Any], str]]] = {
    "frequency_hz": ("frequency", show_hz),
    "voltage_vpp": ("voltage", lambda v: f"{v:g} Vpp"),
    "temperature_c": ("temperature", lambda v: f"{v:.2f} °C"),
    "enabled": ("drive", lambda v: "on" if v else "off"),
}


def drive_table(result: dict[str, Any]) -> str:
    """The set_drive reply for people: "frequency 40.0000 kHz", "voltage 500 Vpp", ..."""
    rows = []
    for key, value in result.items():
        label, fmt = _DRIVE_ROWS.get(key, (key, str))
        rows.append([label, "-" if value is None else fmt(value)])
    return table(rows, right_from=2)


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


#: What each model's coefficients are (predictor/: each model's `coefficients`; docs/predictor.md).
COEFFICIENTS_ABOUT = {
    "kalman": "phi, the friction's AR(1) coefficient, and K, the gain, of the filter predicting now"
    " (one of a grid of twelve); a_1 of the paper's AR(1) while the direction is cold",
    "rls": "c and a of x_k - m = c + a (x_(k-1) - m), x the log stroke time less the conditions'"
    " shifts; a_1 of the paper's AR(1) while cold",
    "paper": "a_1 ... a_m of Eq. 2, no intercept",
    "centered": "c, the intercept, then a_1 ... a_m",
}


def coefficient_names(model: str | None, n: int) -> list[str] | None:
    """The names of a model's `n` coefficients in the order it stores them; None when not known."""
    ar = [f"a_{i}" for i in range(1, n + 1)]
    if model in ("kalman", "rls"):  # a single one: the cold start's AR(1)
        return {1: ["a_1"], 2: ["phi", "K"] if model == "kalman" else ["c", "a"]}.get(n)
    if model == "paper":
        return ar
    if model == "centered":
        return ["c", *ar[: n - 1]] if n else []
    return None


def coefficients_text(model: str | None, values: list[float]) -> str:
    """`phi 0.8, K 1` (a model known), else the bare numbers; "(none yet)" before a fit."""
    if not values:
        return "(none yet)"
    names = coefficient_names(model, len(values))
    if names is None:
        return " ".join(f"{c:.6g}" for c in values)
    return ", ".join(f"{name} {c:.6g}" for name, c in zip(names, values, strict=True))


def stats_model(stats: dict[str, Any]) -> str | None:
    """The predictor model of the strokes a stats reply covers: its run's, else the reply's own."""
    run = stats.get("run") or {}
    model = (run.get("settings") or {}).get("model") or stats.get("model")
    return str(model) if model else None


def stats_table(stats: dict[str, Any]) -> str:
    """The stats reply as one aligned table: a row per figure, a column per direction and both."""
    cols = [stats.get("on", {}), stats.get("off", {}), stats.get("all", {})]

    def row(label: str, fn: Callable[[dict[str, Any]], str]) -> list[str]:
        return [label, *(fn(d) if d else "-" for d in cols)]

    def ns(key: str) -> Callable[[dict[str, Any]], str]:
        return lambda d: show_ns(d.get(key)) if d.get("count") or key.startswith("lateness") else "-"

    model = stats_model(stats)
    rows = [
        row("strokes (completed)", lambda d: _count(d, "count")),
        row("strokes (all recorded)", lambda d: _count(d, "strokes")),
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
        row("cut short (estop, fault, stop)", lambda d: _count(d, "cut_short")),
        row("implausible (not strokes)", lambda d: _count(d, "implausible")),
        row("mismatched (device disagreed)", lambda d: _count(d, "mismatched")),
        row("model order", lambda d: _count(d, "order")),
        row(
            "coefficients",
            lambda d: coefficients_text(model, d["coefficients"]) if "coefficients" in d else "-",
        ),
        row("predictor ready", lambda d: ("yes" if d["ready"] else "no (nominal)") if "ready" in d else "-"),
        row("start lateness p50", ns("lateness_p50_ns")),
        row("start lateness p99", ns("lateness_p99_ns")),
        row("start lateness max", ns("lateness_max_ns")),
    ]
    run = stats.get("run")
    if "state" in stats:
        head = (
            f"state {stats['state']}"
            + (f" ({stats['fault']})" if stats.get("fault") else "")
            + f", mode {stats.get('mode', '?')}, next cycle {stats.get('cycle', '?')}, "
            f"T on {show_ns(stats.get('target_on_ns'))} / off {show_ns(stats.get('target_off_ns'))}"
        )
    elif run:  # a past run, read from the records (scope_line names it): its settings, not today's
        settings = run.get("settings", {})
        head = (
            f"mode {settings.get('mode', '?')}, T on {show_ns(settings.get('target_on_ns'))}"
            f" / off {show_ns(settings.get('target_off_ns'))} (the run's settings)"
        )
    else:
        head = "from the records"
    lines = [head, "", table(rows, ["", "on", "off", "all"]), ""]
    if "spurious_edges" in stats:
        lines.append(
            f"spurious edges {stats['spurious_edges']}, overruns {stats.get('overruns', '-')}, "
            f"driver bounces {stats.get('driver_bounces', '-')}"
        )
    about = COEFFICIENTS_ABOUT.get(model or "")
    if about:
        lines.append(f"coefficients ({model}): {about}")
    scheduling = stats.get("scheduling")
    if scheduling and not scheduling.startswith("SCHED_FIFO"):
        both = stats.get("all", {})
        n, late = both.get("strokes") or 0, both.get("late") or 0
        rate = f"{late} of {n} strokes late ({100.0 * late / n:.1f} %)" if n else "no strokes yet"
        lines.append(f"loop {scheduling}: {rate}")
    commissioning = stats.get("all", {}).get("commissioning") or []
    if commissioning:
        lines.append(
            "commissioning strokes (first of a direction, nothing known before; not in the figures above):"
        )
        for c in commissioning:
            lines.append(
                f"  cycle {c['cycle']} {direction_name(c['direction'])}: error {show_ns(c['error_ns'])}"
                f" (t_hat {show_ns(c['t_hat_ns'])}, a guess)"
            )
    return "\n".join(lines)


class RunningStats:
    """Errors and flags of the strokes watch has seen, so the live view needs no extra call per stroke."""

    def __init__(self) -> None:
        self.strokes = 0
        self.late = 0
        self.faulted = 0
        self.errors = Running()  # the daemon's own accumulator

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

    def footer(self) -> str:
        """The live line under the strokes: the running figures so far."""
        mean, std, worst = (show_ns(x) if self.n else "-" for x in (self.mean, self.std, self.max_abs))
        return (
            f"strokes {self.strokes} | error mean {mean} std {std} max |error| {worst}"
            f" | late {self.late} | stall/fault/estop {self.faulted} | Ctrl-C ends"
        )

    def summary(self) -> str:
        """One line for people: what the watched strokes did."""
        if not self.strokes:
            return "watched no strokes"
        timed = "all arrived" if self.n == self.strokes else f"{self.n} arrived"
        return (
            f"watched {self.strokes} strokes ({timed}): error mean {show_ns(self.mean)}, "
            f"std {show_ns(self.std)}, max |error| {show_ns(self.max_abs)}; late {self.late}, "
            f"stall/fault/estop {self.faulted}"
        )


#: The watch view's columns: (header, width, left-aligned). Widths fit any value the column shows
#: ("-999.999 ms", a 9-digit cycle), so one header lines up with every row under it; the flags,
#: the one column of varying width, come last.
WATCH_COLUMNS: tuple[tuple[str, int, bool], ...] = (
    ("cycle", 9, False),
    ("dir", 3, True),
    ("mode", 6, True),
    *((name, 11, False) for name in HISTORY_HEADER[3:-1]),
    ("err std", 11, False),
    ("max |err|", 11, False),
    ("flags", 0, True),
)


def watch_line(cells: Sequence[str]) -> str:
    """One line of the watch view, in WATCH_COLUMNS' fixed widths."""
    out = [
        cell.ljust(width) if left else cell.rjust(width)
        for cell, (_, width, left) in zip(cells, WATCH_COLUMNS, strict=True)
    ]
    return "  ".join(out).rstrip()


class WatchView:
    """`watch`'s output: a line per stroke under a header that lines up with it, a line per state
    change, and on a terminal a live footer with the running figures (rich redraws it in place
    while the stroke lines scroll above it; a pipe gets the lines only)."""

    def __init__(self, out: IO[str] | None = None, *, live: bool | None = None) -> None:
        self.out = out or sys.stdout
        self.running = RunningStats()
        self.lines = 0
        self._live_wanted = _isatty(self.out) if live is None else live
        self._live: Any = None

    def __enter__(self) -> WatchView:
        if self._live_wanted:
            from rich.console import Console  # the live footer only: a pipe never loads rich
            from rich.live import Live
            from rich.text import Text

            console = Console(file=self.out, highlight=False)
            self._live = Live(
                console=console,
                transient=True,
                refresh_per_second=4,
                redirect_stdout=False,
                get_renderable=lambda: Text(self.running.footer(), style="bold"),
            )
            self._live.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None

    def _print(self, line: str) -> None:
        if self._live is not None:
            self._live.console.print(line, markup=False, highlight=False, soft_wrap=True)
        else:
            print(line, file=self.out, flush=True)

    def stroke(self, rec: CycleRecord) -> None:
        """Count a stroke and print its line (the header first, and again every WATCH_HEADER_EVERY)."""
        self.running.add(rec)
        if self.lines % WATCH_HEADER_EVERY == 0:
            self._print(watch_line([name for name, _, _ in WATCH_COLUMNS]))
        row = history_row(rec)
        self._print(
            watch_line([*row[:-1], show_ns(self.running.std), show_ns(self.running.max_abs), row[-1]])
        )
        self.lines += 1

    def state(self, payload: dict[str, Any]) -> None:
        """A state change, as a comment line among the strokes."""
        fault = f" ({payload['fault']})" if payload.get("fault") else ""
        self._print(f"# state {payload.get('state')}{fault}")


class CycleProgress:
    """`cycle --count N --wait` on a terminal: a progress bar of the strokes made (rich); else nothing."""

    def __init__(self, first_cycle: int, count: int, out: IO[str] | None = None) -> None:
        self.first_cycle = first_cycle
        self.count = count
        self.out = out or sys.stdout
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> CycleProgress:
        if self.count and _isatty(self.out):
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self._progress = Progress(
                TextColumn("strokes"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                console=Console(file=self.out),
                transient=True,
            )
            self._progress.start()
            self._task = self._progress.add_task("cycle", total=self.count)
        return self

    def update(self, next_cycle: int) -> None:
        """The daemon's next cycle number, from a status reply."""
        if self._progress is not None:
            self._progress.update(
                self._task, completed=min(self.count, max(0, next_cycle - self.first_cycle))
            )

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._progress is not None:
            self._progress.stop()


class ExportProgress:
    """An export's progress bar on a terminal (rich), by cycle through the span exported: shown
    once the export has taken a second, never on a pipe or a file (`out` None: never)."""

    AFTER_NS = 1_000_000_000

    def __init__(self, span: tuple[int, int] | None, out: IO[str] | None) -> None:
        self.span = span
        self.out = out if out is not None and _isatty(out) else None
        self._t0 = time.monotonic_ns()
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> ExportProgress:
        return self

    def update(self, last_cycle: int, strokes: int) -> None:
        """The last cycle written so far, and how many strokes."""
        if self.out is None or self.span is None:
            return
        first, last = self.span
        if self._progress is None:
            if time.monotonic_ns() - self._t0 < self.AFTER_NS:
                return
            from rich.console import Console  # a terminal's export past a second only
            from rich.progress import (
                BarColumn,
                Progress,
                TaskProgressColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self._progress = Progress(
                TextColumn("export"),
                BarColumn(),
                TaskProgressColumn(),
                TextColumn("{task.fields[strokes]:,} strokes"),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                console=Console(file=self.out),
                transient=True,
            )
            self._progress.start()
            self._task = self._progress.add_task("export", total=last - first + 1, strokes=0)
        self._progress.update(self._task, completed=last_cycle - first + 1, strokes=strokes)

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._progress is not None:
            self._progress.stop()


def _isatty(stream: IO[str]) -> bool:
    with contextlib.suppress(AttributeError, ValueError):
        return stream.isatty()
    return False


# -- runs ------------------------------------------------------------------------------------------
RUN_HEADER = (
    "run",
    "kind",
    "cycles",
    "strokes",
    "started",
    "period",
    "T on",
    "T off",
    "mode",
    "ended",
    "label",
)


def run_strokes(run: dict[str, Any]) -> str:
    """How many strokes a run has ("running" while it runs)."""
    if run["last_cycle"] is None:
        return "running"
    return str(run["last_cycle"] - run["first_cycle"] + 1)


def _wall(ns: int | None) -> str:
    if ns is None:
        return "-"
    return datetime.datetime.fromtimestamp(ns / 1e9).strftime("%Y-%m-%d %H:%M:%S")


def run_row(run: dict[str, Any]) -> list[str]:
    """One run for people: its cycles, when it started, its settings, how it ended."""
    st = run.get("settings", {})
    last = run["last_cycle"]
    cycles = f"{run['first_cycle']}.." + ("" if last is None else str(last))
    return [
        str(run["run_id"]),
        run["kind"],
        cycles,
        run_strokes(run),
        _wall(run["started_wall_ns"]),
        show_ns(st.get("period_ns")),
        show_ns(st.get("target_on_ns")),
        show_ns(st.get("target_off_ns")),
        str(st.get("mode", "-")),
        run["end_reason"] or "running",
        run.get("label") or "-",
    ]


def notes_lines(runs: Sequence[dict[str, Any]]) -> list[str]:
    """Each run's notes under its table, one line a run (its line breaks shown as " / ")."""
    return [f"run {r['run_id']} notes: {' / '.join(r['notes'].splitlines())}" for r in runs if r.get("notes")]


def scope_line(stats: dict[str, Any]) -> str:
    """What a stats reply covers: its run, or its cycles, or every stroke since the daemon started."""
    first, last = stats.get("first_cycle"), stats.get("last_cycle")
    cycles = "no strokes yet" if first is None else f"cycles {first}..{'' if last is None else last}"
    run = stats.get("run")
    if run is None:
        live = "state" in stats  # the daemon's own figures, not a range read from the records
        return f"{cycles} (no run yet: every stroke since the daemon started)" if live else cycles
    state = "running" if run["end_reason"] is None else f"ended: {run['end_reason']}"
    label = f" {run['label']}" if run.get("label") else ""
    return f"run {run['run_id']}{label} ({run['kind']}, {state}), {cycles}"


#: A label's per-run table (`stats --label`): the run and its main figures, both directions together.
PER_RUN_HEADER = ("run", "cycles", "strokes", "error mean", "error std", "max |error| % of T", "|error| p99")


def per_run_rows(per_run: Sequence[dict[str, Any]]) -> list[list[str]]:
    """One row a run of a label's statistics."""
    rows = []
    for part in per_run:
        run, both = part["run"], part.get("all", {})
        counted = bool(both.get("count"))
        rows.append(
            [
                str(run["run_id"]),
                f"{part.get('first_cycle') or '-'}..{part.get('last_cycle') or ''}",
                _count(both, "strokes"),
                show_ns(both.get("error_mean_ns")) if counted else "-",
                show_ns(both.get("error_std_ns")) if counted else "-",
                _pct(both.get("max_abs_error_pct")) if counted else "-",
                show_ns(both.get("abs_error_p99_ns")) if counted else "-",
            ]
        )
    return rows
