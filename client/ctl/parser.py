"""usmswitchctl's argument parser."""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from typing import Any, NoReturn

from usmswitch.protocol.record import check_label
from usmswitch.protocol.version import version_text
from usmswitch.protocol.wire import MAX_HISTORY, PROTOCOL_VERSION

from .args import (
    EXIT_USAGE,
    PROG,
    UsageError,
    duration_arg,
    frequency_arg,
    positive_duration_arg,
    voltage_arg,
)


# -- arguments ---------------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse that exits with EXIT_USAGE (as it does) but names the program consistently, and
    answers in JSON when the command line asked for JSON (scripts parse every error the same way)."""

    #: Whether the command line being parsed has --json (set by the top parser, read by any).
    json_errors = False

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        if self.prog == PROG:  # the top parser sees the whole command line first
            words = list(sys.argv[1:] if args is None else args)
            _Parser.json_errors = (
                "--json" in words[: words.index("--")] if "--" in words else "--json" in words
            )
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> NoReturn:
        message += _did_you_mean(message)
        if _Parser.json_errors:
            err = {"exit": EXIT_USAGE, "message": message, "usage": self.format_usage().strip()}
            self.exit(EXIT_USAGE, json.dumps({"error": err}, sort_keys=True) + "\n")
        self.print_usage(sys.stderr)
        self.exit(EXIT_USAGE, f"{PROG}: error: {message}\n")


_INVALID_CHOICE = re.compile(r"invalid choice: '([^']*)' \(choose from (.*)\)$")


def _did_you_mean(message: str) -> str:
    """For a mistyped command or choice (`satus`), the nearest valid ones ("" when none is near)."""
    m = _INVALID_CHOICE.search(message)
    if m is None:
        return ""
    choices = re.findall(r"'([^']*)'", m.group(2))
    near = difflib.get_close_matches(m.group(1), choices, n=2, cutoff=0.6)
    return f"; did you mean {' or '.join(repr(c) for c in near)}?" if near else ""


#: The heading of the connection flags in every command's --help, after the command's own options.
CONNECTION_GROUP = "connection and output (also taken before the command)"


def _connection_flags(p: Any, suppress: bool) -> None:
    # Declared on the main parser and on every command, so `usmswitchctl stats --json` works too;
    # on the commands the default is SUPPRESS so they never overwrite a flag given before the command.
    # `p` is a parser or an argument group of one (argparse's _ActionsContainer).
    d = (lambda v: argparse.SUPPRESS) if suppress else (lambda v: v)
    p.add_argument(
        "--socket",
        default=d(None),
        help="the daemon's Unix socket (default: first that exists "
        "of $USMSWITCH_SOCKET, $XDG_RUNTIME_DIR/usmswitch/usmswitchd.sock, /run/usmswitch/...)",
    )
    p.add_argument(
        "--rig",
        default=d(None),
        help="the service instance usmswitchd@RIG: its socket /run/usmswitch/RIG/usmswitchd.sock "
        "(default: $USMSWITCH_RIG)",
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


def _from_flag(c: argparse.ArgumentParser) -> None:
    c.add_argument(
        "--from",
        dest="source",
        metavar="SOURCE",
        help="read the records from SOURCE instead of the socket: a state directory, a .sqlite file, "
        "or the PostgreSQL copy, postgresql://USER@HOST/DB (with --rig NAME when it holds several rigs)",
    )


def _records_flags(c: argparse.ArgumentParser) -> None:
    """--state-dir and --from for a command that reads the records: no daemon needed."""
    c.add_argument(
        "--state-dir", help="read this state directory's records.sqlite (or this .sqlite file), read-only"
    )
    _from_flag(c)


def build_parser() -> argparse.ArgumentParser:
    """Every command and flag; `usmswitchctl COMMAND --help` shows one command's."""
    p = _Parser(
        prog=PROG,
        description="Drive the usmswitchd daemon: status, statistics, targets, strokes, cycling, records.",
        epilog="Exit codes: 0 ok, 1 refused by the daemon, 2 usage, 3 cannot connect, 4 rig in FAULT.",
    )
    p.add_argument("--version", action="version", version=version_text(PROG, PROTOCOL_VERSION))
    _connection_flags(p.add_argument_group(CONNECTION_GROUP.split(" (")[0]), suppress=False)
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    commands: list[argparse.ArgumentParser] = []

    def command(name: str, help_text: str) -> argparse.ArgumentParser:
        c = sub.add_parser(name, help=help_text, description=help_text)
        commands.append(c)
        return c

    command("ping", "check that the daemon answers")
    command("status", "state, mode, fault, targets, versions (exit 4 when FAULT is latched)")
    command("web-url", "the browser panel's URL with its token (docs/panel.md)")
    c = command("stats", "statistics of a run (default: the current or last) per direction, as a table")
    c.add_argument("--run", type=int, help="this run's (see `runs`)")
    c.add_argument("--first", type=int, help="statistics of cycles --first..--last instead of a run")
    c.add_argument("--last", type=int, help="with --first: the last cycle (default: the newest)")
    c.add_argument("--label", help="every run with this label: pooled, and each run's")
    _records_flags(c)
    c = command("runs", "the last runs: id, strokes, settings, how each ended, label and notes")
    c.add_argument("-n", type=int, default=20, help="how many (1..1000, default 20)")
    c.add_argument("--label", help="only the runs with this label")
    _records_flags(c)
    c = command("target", "get or set the target total time T")
    c.add_argument("action", nargs="?", choices=("get", "set"), help="get (default) or set")
    c.add_argument("value", nargs="?", help="the new T for `set`, e.g. 12ms, 10500us, 0.012s")
    c.add_argument("unit", nargs="?", help=argparse.SUPPRESS)  # `target set 12 ms`: the unit apart
    c.add_argument("--direction", choices=("on", "off", "both"), default="both", help="default both")
    c.add_argument(
        "--allow-late", action="store_true", help="take a T below what the rig reaches (late strokes)"
    )
    c = command("switch", "make one stroke and print its record")
    c.add_argument("direction", nargs="?", choices=("on", "off", "next"), default="next")
    c = command("cycle", "start alternating on/off strokes")
    c.add_argument(
        "--period", type=positive_duration_arg, default=50_000_000, help="command to command, default 50ms"
    )
    c.add_argument("--count", type=int, default=0, help="strokes to make, 0 (default) until `stop`")
    c.add_argument("--target", type=positive_duration_arg, help="T for this run (default: the current T)")
    c.add_argument(
        "--allow-late", action="store_true", help="take a target below what the rig reaches (late strokes)"
    )
    c.add_argument("--wait", action="store_true", help="return when the run ends (exit 4 if in FAULT)")
    c.add_argument(
        "--take-over",
        action="store_true",
        help="end a run another client started first (the daemon's start-up run gives way anyway)",
    )
    c.add_argument("--label", help="what the run is for, a short word (e.g. sweep-12ms): `runs --label`")
    c.add_argument("--notes", help="free text about the run (`notes RUN TEXT` edits it later)")
    c.add_argument(
        "--queue", action="store_true", help="into the daemon's queue: starts when the runs before it end"
    )
    c.add_argument(
        "--priority", type=int, default=0, help="with --queue: higher first (-1000..1000, default 0)"
    )
    c = command(
        "queue", "the queue of runs: what waits, in order; cancel or reorder an entry, pause or resume it"
    )
    c.add_argument(
        "action", nargs="?", choices=("list", "cancel", "priority", "pause", "resume"), default="list"
    )
    c.add_argument("entry", nargs="?", type=int, help="the entry to cancel or reorder (see `queue`)")
    c.add_argument("priority", nargs="?", type=int, help="with priority: its new one (-1000..1000)")
    c.add_argument(
        "--operator",
        action="store_true",
        help="cancel or reorder another's entry, pause or resume (an operator's to do)",
    )
    c = command("notes", "show or edit a run's notes and label, during or after it")
    c.add_argument("run", type=int, help="the run (see `runs`)")
    c.add_argument("text", nargs="?", help='its notes ("" clears them); none: show them')
    c.add_argument("--label", help='its label ("" clears it)')
    c.add_argument(
        "--operator", action="store_true", help="edit another person's run (refused without, by mistake)"
    )
    command("stop", "stop cycling after the stroke in progress")
    c = command("mode", "closed loop (T_d = T - t_hat) or open loop (fixed delay)")
    c.add_argument("mode", choices=("open", "closed"))
    c.add_argument("--delay", type=duration_arg, help="the open loop's fixed delay, e.g. 1ms")
    c = command("history", "the last strokes as a table")
    c.add_argument("-n", type=int, default=20, help="how many (1..10000, default 20)")
    c.add_argument("--run", type=int, help="of this run only")
    c = command("watch", "print every stroke as it finishes, with running error figures")
    c.add_argument("--count", type=int, help="stop after this many strokes (default: until Ctrl-C)")
    c = command("export", "write cycle records as CSV")
    c.add_argument("--csv", metavar="FILE", help="output file, or - for standard output")
    c.add_argument(
        "--state-dir",
        help="read every record from this state directory's records.sqlite "
        "(or this .sqlite file), read-only, instead of the socket",
    )
    _from_flag(c)
    c.add_argument(
        "-n",
        type=int,
        help=f"over the socket: the last n only (max {MAX_HISTORY}; default: every stroke, streamed)",
    )
    c.add_argument("--first", type=int, default=1, help="first cycle (default 1)")
    c.add_argument("--last", type=int, help="last cycle (default: the newest)")
    c.add_argument("--run", type=int, help="this run's strokes only")
    c.add_argument("--label", help="the strokes of every run with this label")
    c = command("plot", "draw a run to an image (PNG, SVG or PDF by the file's suffix)")
    c.add_argument("--out", required=True, metavar="FILE", help="e.g. run.png")
    c.add_argument("--state-dir", help="read the records from this state directory, read-only")
    _from_flag(c)
    c.add_argument(
        "-n", type=int, default=MAX_HISTORY, help=f"over the socket: the last n (max {MAX_HISTORY})"
    )
    c.add_argument("--first", type=int, default=1, help="with --state-dir/--from: first cycle (default 1)")
    c.add_argument("--last", type=int, help="with --state-dir/--from: last cycle (default: the newest)")
    c.add_argument("--run", type=int, help="this run's strokes only (default: the newest run)")
    c.add_argument("--all", action="store_true", help="every stroke, across runs (the run starts marked)")
    c.add_argument("--title", help="the plot's title")
    command("reset", "clear a latched FAULT")
    command("estop", "emergency stop: drive off, latch FAULT")
    c = command("drive", "set the drive board's excitation; no flags: read it")
    c.add_argument("--frequency", type=frequency_arg, help="excitation frequency, e.g. 40kHz")
    c.add_argument("--voltage", type=voltage_arg, help="excitation voltage, e.g. 500V")
    en = c.add_mutually_exclusive_group()
    en.add_argument("--enable", dest="enabled", action="store_true", default=None, help="drive on")
    en.add_argument("--disable", dest="enabled", action="store_false", help="drive off")
    # Last, in a group of their own: a command's --help and usage show its own options first, and
    # the connection flags once, under one heading, after them.
    for c in commands:
        _connection_flags(c.add_argument_group(CONNECTION_GROUP), suppress=True)
    return p


_NUMBER = re.compile(r"[+-]?(\d[\d_]*(\.\d*)?|\.\d+)([eE][+-]?\d+)?")


def check_args(args: argparse.Namespace) -> None:
    """Checks argparse cannot make; `target set 12 ms` is taken as `12ms`."""
    if args.command == "target" and args.unit is not None:
        if args.value is not None and _NUMBER.fullmatch(args.value):
            args.value = f"{args.value}{args.unit}"
        else:
            raise UsageError(
                f"target takes one duration, got {args.value!r} {args.unit!r}: e.g. `target set 12ms`"
            )
    if args.command == "target" and args.action == "set" and args.value is not None:
        try:  # before connecting: a bad unit is a usage error wherever the daemon is
            positive_duration_arg(args.value)
        except argparse.ArgumentTypeError as exc:
            raise UsageError(f"target: {exc}") from None
    if args.command == "history" and not 1 <= args.n <= MAX_HISTORY:
        raise UsageError(f"history: -n must be in 1..{MAX_HISTORY}, got {args.n}")
    if args.command == "export" and args.n is not None and not 1 <= args.n <= MAX_HISTORY:
        raise UsageError(f"export: -n must be in 1..{MAX_HISTORY}, got {args.n}")
    if args.command == "export" and args.first < 1:
        raise UsageError(f"export: --first must be >= 1, got {args.first}")
    if getattr(args, "run", None) is not None and args.run < 1:
        raise UsageError(f"{args.command}: --run must be a run id >= 1, got {args.run}")
    if args.command == "stats" and args.last is not None and args.first is None:
        raise UsageError("stats: --last needs --first")
    if args.command == "stats" and args.first is not None and args.run is not None:
        raise UsageError("stats: give --run or --first/--last, not both")
    if (
        args.command in ("stats", "export")
        and args.label is not None
        and (args.run is not None or args.first not in (None, 1) or args.last is not None)
    ):
        raise UsageError(f"{args.command}: give --label or --run/--first/--last, not both")
    if getattr(args, "label", None):
        try:  # before connecting, as the daemon would refuse it
            check_label(args.label)
        except ValueError as exc:
            raise UsageError(f"{args.command}: {exc}") from None
    if args.command == "runs" and not 1 <= args.n <= 1000:
        raise UsageError(f"runs: -n must be in 1..1000, got {args.n}")
    if args.command == "queue":
        wants = {"cancel": 1, "priority": 2}.get(args.action, 0)
        given = (args.entry is not None) + (args.priority is not None)
        if given != wants:
            raise UsageError(
                "queue: `queue cancel ENTRY` takes an entry, `queue priority ENTRY N` an entry and its"
                " priority; list, pause and resume none"
            )
    if args.command == "cycle" and args.priority and not args.queue:
        raise UsageError("cycle: --priority orders the queue: give it with --queue")
    if args.command == "cycle" and args.count < 0:
        raise UsageError(f"cycle: --count must be >= 0, got {args.count}")
    if args.command == "watch" and args.count is not None and args.count < 0:
        raise UsageError(f"watch: --count must be >= 0, got {args.count}")
    if getattr(args, "source", None) is not None and getattr(args, "state_dir", None) is not None:
        raise UsageError(f"{args.command}: give --from or --state-dir, not both")
    if getattr(args, "source", None) is not None:
        return  # --rig names the rig in the records, not a socket
    given = [f"--{name}" for name in ("socket", "rig", "tcp") if getattr(args, name) is not None]
    if len(given) > 1:
        raise UsageError(f"give one of --socket, --rig and --tcp, not {' and '.join(given)}")
