"""usmswitchctl: the daemon's command line, a thin shell over `usmswitch.daemon.client.Client`.

Every command is one or two Client calls plus formatting: human units in ("12ms", "40kHz") and out,
`--json` for the raw result. Exit codes (docs/usmswitchctl.md) are part of the interface:

    0  ok
    1  the daemon refused the call (its error code and message are printed)
    2  usage error: bad command, flag or unit; an export file that cannot be written
    3  cannot reach the daemon: no socket, connection refused or lost, no answer in --timeout
    4  the rig is in FAULT: `status` found FAULT latched, a command was refused with the FAULT
       code, or the stroke `switch` made ended in a stall, driver fault or emergency stop
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import math
import os
import re
import signal
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import IO, Any, NoReturn

from .client import Client, ConnectionClosed, CycleRecord, ErrorCode, RpcError, parse_address
from .record import FIELDS, UNUSABLE, Flag
from .stats import Running
from .units import format_ns, parse_duration_ns
from .wire import estop_socket_path

EXIT_OK = 0
EXIT_REFUSED = 1
EXIT_USAGE = 2
EXIT_CONNECT = 3
EXIT_FAULT = 4
#: What a shell reports for a process ended by Ctrl-C; used when a command other than watch is cut.
EXIT_INTERRUPTED = 130

PROG = "usmswitchctl"
DIRECTION_NAMES = ("on", "off")
#: history's upper bound on the socket (usmswitch.daemon.wire.MAX_HISTORY); export over the socket uses it.
MAX_HISTORY = 10_000
#: Stroke lines between repeated column headers in `watch`.
WATCH_HEADER_EVERY = 40
#: How often `cycle --wait` checks the state when no notification comes.
WAIT_POLL_NS = 500_000_000


class UsageError(Exception):
    """A bad argument that argparse cannot catch (a unit, a combination); exits 2."""


# -- units -----------------------------------------------------------------------------------------
def duration_arg(text: str) -> int:
    """argparse type: a human duration ("12ms", "10500us", "0.012s") as integer ns."""
    try:
        return parse_duration_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def positive_duration_arg(text: str) -> int:
    """argparse type: a human duration that must be longer than 0 (a target, a period)."""
    ns = duration_arg(text)
    if ns <= 0:
        raise argparse.ArgumentTypeError(f"duration {text!r}: must be longer than 0")
    return ns


_QUANTITY = re.compile(
    r"^\s*(?P<number>[+-]?(?:\d[\d_]*(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?)\s*(?P<unit>\S*)\s*$"
)
# Matched without case ("40khz" and "40KHz" are not ambiguous); the help shows the usual spelling.
_FREQUENCY_UNITS = {"Hz": Decimal(1), "kHz": Decimal(1_000), "MHz": Decimal(1_000_000)}
_VOLTAGE_UNITS = {"V": Decimal(1), "Vpp": Decimal(1), "kV": Decimal(1_000)}


def _quantity(text: str, what: str, units: dict[str, Decimal], example: str) -> float:
    m = _QUANTITY.match(text)
    if m is None:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: not a number with a unit, e.g. {example!r}")
    unit = m["unit"]
    if not unit:
        # As with durations: "40" could mean 40 Hz or 40 kHz, and the wrong guess drives the motor.
        raise argparse.ArgumentTypeError(
            f"{what} {text!r}: needs a unit ({', '.join(units)}), e.g. {example!r}"
        )
    scale = next((v for k, v in units.items() if k.lower() == unit.lower()), None)
    if scale is None:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: unknown unit {unit!r} (use {', '.join(units)})")
    try:
        value = Decimal(m["number"].replace("_", "")) * scale
    except InvalidOperation:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: not a number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: negative")
    return float(value)


def frequency_arg(text: str) -> float:
    """argparse type: an excitation frequency ("40kHz", "39600Hz") in hertz."""
    return _quantity(text, "frequency", _FREQUENCY_UNITS, "40kHz")


def voltage_arg(text: str) -> float:
    """argparse type: an excitation voltage ("500V", "500Vpp") in volts peak-to-peak."""
    return _quantity(text, "voltage", _VOLTAGE_UNITS, "500V")


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


# -- commands --------------------------------------------------------------------------------------
def cmd_ping(client: Client, args: argparse.Namespace) -> int:
    """Check the daemon answers."""
    result = client.ping()
    if args.json:
        print_json(result)
    else:
        print(result)
    return EXIT_OK


def cmd_status(client: Client, args: argparse.Namespace) -> int:
    """State, mode, fault, versions, targets; exits 4 when FAULT is latched so scripts can test it."""
    st = client.status()
    if args.json:
        print_json(st)
    else:
        rows = [
            ["state", st["state"]],
            ["fault", st["fault"] or "-"],
            ["mode", st["mode"]],
            ["target on", show_ns(st["target_on_ns"])],
            ["target off", show_ns(st["target_off_ns"])],
            ["next cycle", str(st["cycle"])],
            [
                "driver",
                st["driver"] + {True: " (answering)", False: " (NOT answering)"}.get(st.get("driver_ok"), ""),
            ],
            ["version", f"{st['version']} (protocol {st['protocol_version']})"],
            ["uptime", show_ns(st["uptime_ns"])],
        ]
        print(table(rows, right_from=2))
    return EXIT_FAULT if st["state"] == "fault" else EXIT_OK


def cmd_stats(client: Client, args: argparse.Namespace) -> int:
    """The daemon's running statistics as one aligned table."""
    stats = client.stats()
    if args.json:
        print_json(stats)
    else:
        print(stats_table(stats))
    return EXIT_OK


def _targets_text(t: dict[str, Any]) -> str:
    return table(
        [
            ["on", show_ns(t["target_on_ns"])],
            ["off", show_ns(t["target_off_ns"])],
            ["from cycle", str(t["from_cycle"])],
        ]
    )


def cmd_target(client: Client, args: argparse.Namespace) -> int:
    """Read T, or set it for one direction or both (from the next armed stroke)."""
    if args.action in (None, "get"):
        if args.value is not None:
            raise UsageError(f"target get takes no value, got {args.value!r}")
        result = client.get_target()
    else:
        if args.value is None:
            raise UsageError("target set needs a duration, e.g. `target set 12ms`")
        try:
            target_ns = positive_duration_arg(args.value)
        except argparse.ArgumentTypeError as exc:
            raise UsageError(f"target: {exc}") from None
        result = client.set_target(target_ns, args.direction)
        for warning in result.get("warnings", []):
            print(f"warning: {warning}", file=sys.stderr)
    if args.json:
        print_json(result)
    else:
        print(_targets_text(result))
    return EXIT_OK


def cmd_switch(client: Client, args: argparse.Namespace) -> int:
    """One stroke; prints its record. Exits 4 when the stroke ended in a stall, fault or estop."""
    rec = client.switch(args.direction)
    if args.json:
        print_json(rec)
    else:
        print(table(record_rows(rec), right_from=2))
    return EXIT_FAULT if rec["flags"] & UNUSABLE else EXIT_OK


def cmd_cycle(client: Client, args: argparse.Namespace) -> int:
    """Start periodic on/off strokes; with --wait, block until they are done and report how it ended."""
    if args.wait:
        client.subscribe("state")  # before starting, so the end of a short run cannot slip past
    result = client.start_cycling(args.period, args.count)
    if args.json:
        print_json(result)
    else:
        count = f"{args.count} strokes" if args.count else "until stopped"
        print(
            f"cycling every {show_ns(result['period_ns'])}, {count}, from cycle {result['first_cycle']}",
            flush=True,
        )
    if not args.wait:
        return EXIT_OK
    try:
        while True:
            # A state notification says when cycling ends; status confirms it (and covers a change
            # the daemon coalesced between two of its slack checks).
            with contextlib.suppress(TimeoutError):
                client.next_notification(WAIT_POLL_NS)
            st = client.status()
            if st["state"] != "cycling":
                break
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; the daemon keeps cycling (`{PROG} stop` stops it)", file=sys.stderr)
        return EXIT_INTERRUPTED
    if not args.json:
        print(
            f"finished: {st['state']}"
            + (f" ({st['fault']})" if st["fault"] else "")
            + f", next cycle {st['cycle']}"
        )
    return EXIT_FAULT if st["state"] == "fault" else EXIT_OK


def cmd_stop(client: Client, args: argparse.Namespace) -> int:
    """Stop cycling after the stroke in progress."""
    result = client.stop_cycling()
    if args.json:
        print_json(result)
    else:
        what = "stopping after the stroke in progress" if result["was_cycling"] else "was not cycling"
        print(f"{what}; next cycle {result['cycle']}")
    return EXIT_OK


def cmd_mode(client: Client, args: argparse.Namespace) -> int:
    """Closed loop (T_d = T - t_hat) or open loop with a fixed delay, from the next armed stroke."""
    if args.delay is not None and args.mode != "open":
        raise UsageError("mode: --delay is the open loop's fixed delay; it needs `mode open`")
    result = client.set_mode(args.mode, args.delay)
    if args.json:
        print_json(result)
    else:
        delay = result.get("open_delay_ns")
        extra = (
            f", open-loop delay {show_ns(delay)}"
            if result.get("mode") == "open" and delay is not None
            else ""
        )
        print(f"mode {result['mode']}{extra}, from cycle {result['from_cycle']}")
    return EXIT_OK


def cmd_history(client: Client, args: argparse.Namespace) -> int:
    """The last n stroke records as a table, oldest first."""
    records = client.history(args.n)
    if args.json:
        print_json(records)
    elif not records:
        print("no strokes recorded yet")
    else:
        print(table([history_row(r) for r in records], HISTORY_HEADER))
    return EXIT_OK


def cmd_watch(client: Client, args: argparse.Namespace) -> int:
    """Print every stroke as it finishes, with running error figures; Ctrl-C or --count ends it."""
    running = RunningStats()
    if args.count == 0:
        return EXIT_OK
    sub = client.subscribe("stroke", "state")
    seen = 0
    widths = [len(h) for h in HISTORY_HEADER]
    try:
        if not args.json:
            print(f"watching {client.address} (Ctrl-C to stop)", flush=True)
        for note in sub:
            if args.json:
                print(json.dumps({"topic": note.topic, "payload": note.payload}, sort_keys=True), flush=True)
            if note.topic == "state":
                if not args.json:
                    p = note.payload
                    print(
                        f"# state {p.get('state')}" + (f" ({p['fault']})" if p.get("fault") else ""),
                        flush=True,
                    )
                continue
            rec = note.payload
            running.add(rec)
            seen += 1
            if not args.json:
                if (seen - 1) % WATCH_HEADER_EVERY == 0:
                    print(_watch_line([*HISTORY_HEADER, "err std", "max |err|"], widths), flush=True)
                cells = [*history_row(rec), show_ns(running.std), show_ns(running.max_abs)]
                print(_watch_line(cells, widths), flush=True)
            if args.count is not None and seen >= args.count:
                break
    except KeyboardInterrupt:
        pass  # the user ended the view: a clean exit with the summary, no traceback
    if not args.json:
        print(running.summary() + (f"; {sub.dropped} dropped by the daemon" if sub.dropped else ""))
    return EXIT_OK


def _watch_line(cells: Sequence[str], widths: list[int]) -> str:
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


def _records_from_file(state_dir: Path, first: int, last: int | None) -> Iterator[CycleRecord]:
    # Read-only straight from the daemon's SQLite file: every stroke, without the socket's limit.
    from .records import RecordStore, RecordStoreError

    path = state_dir / "records.sqlite" if state_dir.is_dir() else state_dir
    try:
        store = RecordStore(path, readonly=True)
    except RecordStoreError as exc:
        raise UsageError(f"export: {exc}") from None
    try:
        for rec in store.iter_records(first, last):
            yield rec.to_dict()  # type: ignore[misc]
    finally:
        store.close()


def cmd_export(args: argparse.Namespace, connect: Callable[[], Client]) -> int:
    """Write cycle records as CSV: all of them from the SQLite file, or the last n over the socket."""
    if args.csv is None:
        raise UsageError("export needs --csv FILE (or --csv - for standard output)")
    if args.state_dir is not None:
        records: Iterable[CycleRecord] = _records_from_file(Path(args.state_dir), args.first, args.last)
    else:
        if args.first != 1 or args.last is not None:
            raise UsageError("export: --first/--last read the SQLite file; give --state-dir too")
        with connect() as client:
            records = client.history(args.n)
    try:
        if args.csv == "-":
            n = write_csv(records, sys.stdout)
            sys.stdout.flush()
        else:
            tmp = Path(f"{args.csv}.partial")
            with open(tmp, "w", newline="", encoding="utf-8") as fh:
                n = write_csv(records, fh)
            os.replace(tmp, args.csv)  # a reader never sees half a file
    except OSError as exc:
        raise UsageError(f"export: cannot write {args.csv}: {exc.strerror or exc}") from None
    if args.csv != "-":
        message = {"records": n, "file": str(args.csv)}
        if args.json:
            print_json(message)
        else:
            print(f"{n} records written to {args.csv}")
    return EXIT_OK


def cmd_plot(args: argparse.Namespace, connect: Callable[[], Client]) -> int:
    """Draw a run (operating time and t_hat, error against T, its histogram) to an image file."""
    from .plots import plot_run
    from .record import CycleRecord as Record

    if args.state_dir is not None:
        rows: Iterable[CycleRecord] = _records_from_file(Path(args.state_dir), args.first, args.last)
    else:
        with connect() as client:
            rows = client.history(args.n)
    try:
        out = plot_run((Record.from_row(r) for r in rows), args.out, title=args.title or "")
    except ValueError as exc:
        raise UsageError(f"plot: {exc}") from None
    except OSError as exc:
        raise UsageError(f"plot: cannot write {args.out}: {exc.strerror or exc}") from None
    if args.json:
        print_json({"file": str(out)})
    else:
        print(f"plot written to {out}")
    return EXIT_OK


def cmd_reset(client: Client, args: argparse.Namespace) -> int:
    """Clear a latched FAULT so strokes may run again (refused, exit 1, when none is latched)."""
    result = client.reset_fault()
    if args.json:
        print_json(result)
    else:
        print(f"fault cleared ({result['fault']})")
    return EXIT_OK


def cmd_estop(client: Client, args: argparse.Namespace) -> int:
    """Emergency stop: drive off now and latch FAULT (a successful estop exits 0)."""
    result = client.estop()
    if args.json:
        print_json(result)
    else:
        print(f"emergency stop: state {result.get('state')}, fault {result.get('fault')!r}")
    return EXIT_OK


def cmd_drive(client: Client, args: argparse.Namespace) -> int:
    """Set the drive's excitation (only the flags given); with none, read it."""
    result = client.set_drive(frequency_hz=args.frequency, voltage_vpp=args.voltage, enabled=args.enabled)
    if args.json:
        print_json(result)
    else:
        rows = []
        for key, value in result.items():
            if key == "frequency_hz" and value is not None:
                text = f"{value / 1000:.4f} kHz"
            elif key == "voltage_vpp" and value is not None:
                text = f"{value:g} Vpp"
            elif key == "temperature_c" and value is not None:
                text = f"{value:.2f} C"
            else:
                text = "-" if value is None else str(value)
            rows.append([key, text])
        print(table(rows, right_from=2))
    return EXIT_OK


COMMANDS: dict[str, Callable[[Client, argparse.Namespace], int]] = {
    "ping": cmd_ping,
    "status": cmd_status,
    "stats": cmd_stats,
    "target": cmd_target,
    "switch": cmd_switch,
    "cycle": cmd_cycle,
    "stop": cmd_stop,
    "mode": cmd_mode,
    "history": cmd_history,
    "watch": cmd_watch,
    "reset": cmd_reset,
    "estop": cmd_estop,
    "drive": cmd_drive,
}


# -- arguments ---------------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse that exits with EXIT_USAGE (as it does) but names the program consistently."""

    def error(self, message: str) -> NoReturn:
        self.print_usage(sys.stderr)
        self.exit(EXIT_USAGE, f"{PROG}: error: {message}\n")


def _connection_flags(p: argparse.ArgumentParser, suppress: bool) -> None:
    # Declared on the main parser and on every command, so `usmswitchctl stats --json` works too;
    # on the commands the default is SUPPRESS so they never overwrite a flag given before the command.
    d = (lambda v: argparse.SUPPRESS) if suppress else (lambda v: v)
    p.add_argument(
        "--socket",
        default=d(None),
        help="the daemon's Unix socket (default: first that exists "
        "of $USMSWITCH_SOCKET, $XDG_RUNTIME_DIR/usmswitch/usmswitchd.sock, /run/usmswitch/...)",
    )
    p.add_argument(
        "--tcp", default=d(None), metavar="HOST:PORT", help="connect over TCP instead (needs a token)"
    )
    p.add_argument("--token", default=d(None), help="TCP token (default: $USMSWITCH_TOKEN)")
    p.add_argument(
        "--timeout",
        type=positive_duration_arg,
        default=d(None),
        help="give up on an answer after this long (default 10s; switch waits its stroke)",
    )
    p.add_argument("--json", action="store_true", default=d(False), help="print the raw result as JSON")


def build_parser() -> argparse.ArgumentParser:
    """Every command and flag; `usmswitchctl COMMAND --help` shows one command's."""
    p = _Parser(
        prog=PROG,
        description="Drive the usmswitchd daemon: status, statistics, targets, strokes, cycling, records.",
        epilog="Exit codes: 0 ok, 1 refused by the daemon, 2 usage, 3 cannot connect, 4 rig in FAULT.",
    )
    _connection_flags(p, suppress=False)
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    def command(name: str, help_text: str) -> argparse.ArgumentParser:
        c = sub.add_parser(name, help=help_text, description=help_text)
        _connection_flags(c, suppress=True)
        return c

    command("ping", "check that the daemon answers")
    command("status", "state, mode, fault, targets, versions (exit 4 when FAULT is latched)")
    command("stats", "running statistics per direction and combined, as a table")
    c = command("target", "get or set the target total time T")
    c.add_argument("action", nargs="?", choices=("get", "set"), help="get (default) or set")
    c.add_argument("value", nargs="?", help="the new T for `set`, e.g. 12ms, 10500us, 0.012s")
    c.add_argument("--direction", choices=("on", "off", "both"), default="both", help="default both")
    c = command("switch", "make one stroke and print its record")
    c.add_argument("direction", nargs="?", choices=("on", "off", "next"), default="next")
    c = command("cycle", "start alternating on/off strokes")
    c.add_argument(
        "--period", type=positive_duration_arg, default=50_000_000, help="command to command, default 50ms"
    )
    c.add_argument("--count", type=int, default=0, help="strokes to make, 0 (default) until `stop`")
    c.add_argument("--wait", action="store_true", help="return when cycling ends (exit 4 if in FAULT)")
    command("stop", "stop cycling after the stroke in progress")
    c = command("mode", "closed loop (T_d = T - t_hat) or open loop (fixed delay)")
    c.add_argument("mode", choices=("open", "closed"))
    c.add_argument("--delay", type=duration_arg, help="the open loop's fixed delay, e.g. 1ms")
    c = command("history", "the last strokes as a table")
    c.add_argument("-n", type=int, default=20, help="how many (1..10000, default 20)")
    c = command("watch", "print every stroke as it finishes, with running error figures")
    c.add_argument("--count", type=int, help="stop after this many strokes (default: until Ctrl-C)")
    c = command("export", "write cycle records as CSV")
    c.add_argument("--csv", metavar="FILE", help="output file, or - for standard output")
    c.add_argument(
        "--state-dir",
        help="read every record from this state directory's records.sqlite "
        "(or this .sqlite file), read-only, instead of the socket",
    )
    c.add_argument(
        "-n", type=int, default=MAX_HISTORY, help=f"over the socket: the last n (max {MAX_HISTORY})"
    )
    c.add_argument("--first", type=int, default=1, help="with --state-dir: first cycle (default 1)")
    c.add_argument("--last", type=int, help="with --state-dir: last cycle (default: the newest)")
    c = command("plot", "draw a run to an image (PNG, SVG or PDF by the file's suffix)")
    c.add_argument("--out", required=True, metavar="FILE", help="e.g. run.png")
    c.add_argument("--state-dir", help="read the records from this state directory, read-only")
    c.add_argument(
        "-n", type=int, default=MAX_HISTORY, help=f"over the socket: the last n (max {MAX_HISTORY})"
    )
    c.add_argument("--first", type=int, default=1, help="with --state-dir: first cycle (default 1)")
    c.add_argument("--last", type=int, help="with --state-dir: last cycle (default: the newest)")
    c.add_argument("--title", help="the plot's title")
    command("reset", "clear a latched FAULT")
    command("estop", "emergency stop: drive off, latch FAULT")
    c = command("drive", "set the drive board's excitation; no flags: read it")
    c.add_argument("--frequency", type=frequency_arg, help="excitation frequency, e.g. 40kHz")
    c.add_argument("--voltage", type=voltage_arg, help="excitation voltage, e.g. 500V")
    en = c.add_mutually_exclusive_group()
    en.add_argument("--enable", dest="enabled", action="store_true", default=None, help="drive on")
    en.add_argument("--disable", dest="enabled", action="store_false", help="drive off")
    return p


def _check_args(args: argparse.Namespace) -> None:
    if args.command == "history" and not 1 <= args.n <= MAX_HISTORY:
        raise UsageError(f"history: -n must be in 1..{MAX_HISTORY}, got {args.n}")
    if args.command == "export" and not 1 <= args.n <= MAX_HISTORY:
        raise UsageError(f"export: -n must be in 1..{MAX_HISTORY}, got {args.n}")
    if args.command == "export" and args.first < 1:
        raise UsageError(f"export: --first must be >= 1, got {args.first}")
    if args.command == "cycle" and args.count < 0:
        raise UsageError(f"cycle: --count must be >= 0, got {args.count}")
    if args.command == "watch" and args.count is not None and args.count < 0:
        raise UsageError(f"watch: --count must be >= 0, got {args.count}")
    if args.tcp is not None and args.socket is not None:
        raise UsageError("give --socket or --tcp, not both")


def resolve_address(args: argparse.Namespace) -> str:
    """The address the Client takes: tcp://host:port, the --socket path, or the first socket that exists."""
    if args.tcp is not None:
        return f"tcp://{args.tcp}"  # Client checks host and port and names a bad one
    if args.socket is not None:
        return args.socket
    from .config import client_socket_paths  # the daemon's defaults; imported only when needed

    candidates = client_socket_paths()
    for path in candidates:
        if path.exists():
            return str(path)
    raise ConnectionError(
        f"no daemon socket found (looked at {', '.join(map(str, candidates))}); give --socket"
    )


def _fail(args: argparse.Namespace, code: int, message: str, rpc_code: int | None = None) -> int:
    if getattr(args, "json", False):
        err: dict[str, Any] = {"exit": code, "message": message}
        if rpc_code is not None:
            err["code"] = rpc_code
            err["name"] = _code_name(rpc_code)
        print(json.dumps({"error": err}, sort_keys=True), file=sys.stderr)
    else:
        print(f"{PROG}: {message}", file=sys.stderr)
    return code


def _code_name(code: int) -> str:
    try:
        return ErrorCode(code).name
    except ValueError:
        return "UNKNOWN"


def estop_address(address: str) -> str:
    """The estop socket beside a Unix socket when it is there (its own slots: a flood on the main
    socket cannot lock an estop out), else the address itself."""
    family, path, _ = parse_address(address)
    if family == "unix" and estop_socket_path(path).exists():
        return str(estop_socket_path(path))
    return address


def main(argv: list[str] | None = None) -> int:
    """Entry point of `usmswitchctl`."""
    parser = build_parser()
    args = parser.parse_args(argv)
    # A closed pipe (`usmswitchctl watch | head`) ends us quietly, as for other command-line tools.
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    address = "the daemon"
    try:
        _check_args(args)
        timeout_ns = args.timeout if args.timeout is not None else 10_000_000_000

        def connect() -> Client:
            nonlocal address
            address = resolve_address(args)  # only when needed: export from the file has no socket
            if args.command == "estop":
                address = estop_address(address)
            try:
                return Client(address, timeout_ns=timeout_ns, token=args.token)
            except ValueError as exc:  # a malformed address, a TCP connection without a token
                raise UsageError(str(exc)) from None

        if args.command == "export":
            return cmd_export(args, connect)
        if args.command == "plot":
            return cmd_plot(args, connect)
        with connect() as client:
            return COMMANDS[args.command](client, args)
    except UsageError as exc:
        return _fail(args, EXIT_USAGE, str(exc))
    except RpcError as exc:
        exit_code = EXIT_FAULT if exc.code == ErrorCode.FAULT else EXIT_REFUSED
        return _fail(args, exit_code, f"refused: [{exc.code} {_code_name(exc.code)}] {exc.message}", exc.code)
    except TimeoutError as exc:
        return _fail(args, EXIT_CONNECT, f"no answer from the daemon: {exc}")
    except ConnectionClosed as exc:
        return _fail(args, EXIT_CONNECT, f"lost the daemon: {exc}", exc.code)
    except OSError as exc:  # no socket file, refused, permission denied, unreachable host
        return _fail(args, EXIT_CONNECT, f"cannot connect to {address}: {exc.strerror or exc}")
    except KeyboardInterrupt:
        return _fail(args, EXIT_INTERRUPTED, "interrupted")


if __name__ == "__main__":
    sys.exit(main())
