#!/usr/bin/env python3
"""A lab script: set the target T, run 500 strokes through the daemon, print what they did.

    python examples/run_500_strokes.py --target 12ms
    python examples/run_500_strokes.py --socket /run/usmswitch/usmswitchd.sock --target 24ms --strokes 1000

It talks to a running `usmswitchd` (e.g. `make run`, the simulated rig) with the Python client only:
stop any cycling, set the mode and T, start `--strokes` strokes, follow them on the subscription,
start `--strokes` strokes as a run, follow them as they come, then print the daemon's statistics of
exactly that run: the paper's figure of merit is the std of error = total - T (95.3 us at T = 12 ms).
Exit status: 0 when every stroke finished, 1 when the daemon refused or the run ended in FAULT.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any

from usmswitch.client import Client, RpcError, Stats, find_socket
from usmswitch.protocol.units import format_ns, parse_duration_ns

# The paper's closed-loop result at T = 12 ms and 24 ms (std of the error), for comparison.
PAPER_STD_NS = {12_000_000: 95_300, 24_000_000: 102_700}


def duration(text: str) -> int:
    """argparse type: "12ms", "10500us", "0.012s" -> integer ns."""
    try:
        return parse_duration_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def show(value: float | None) -> str:
    """A duration in ns for people ("-" when there is none)."""
    return "-" if value is None or not math.isfinite(value) else format_ns(round(value))


def print_report(stats: Stats) -> None:
    """The run's figures (the daemon's own, for exactly this run) as an aligned table."""
    cols = ("on", "off", "all")
    rows = [
        ("strokes", lambda s: str(s["strokes"])),
        ("completed", lambda s: str(s["count"])),
        ("error mean", lambda s: show(s["error_mean_ns"])),
        ("error std", lambda s: show(s["error_std_ns"])),
        ("max |error|", lambda s: show(s["error_max_abs_ns"])),
        ("max |error| % of T", lambda s: f"{s['max_abs_error_pct']:.3f} %"),
        ("|error| p50", lambda s: show(s["abs_error_p50_ns"])),
        ("|error| p95", lambda s: show(s["abs_error_p95_ns"])),
        ("|error| p99", lambda s: show(s["abs_error_p99_ns"])),
        ("operating mean", lambda s: show(s["operating_mean_ns"])),
        ("operating std", lambda s: show(s["operating_std_ns"])),
        ("late", lambda s: str(s["late"])),
        ("stalls / faults", lambda s: f"{s['stalls']} / {s['faults']}"),
    ]
    table = [["", *cols]] + [[label, *(fn(stats[c]) for c in cols)] for label, fn in rows]
    table.append(["model order", str(stats["on"]["order"]), str(stats["off"]["order"]), "-"])
    table.append(
        [
            "coefficients",
            " ".join(f"{c:.5g}" for c in stats["on"]["coefficients"]) or "-",
            " ".join(f"{c:.5g}" for c in stats["off"]["coefficients"]) or "-",
            "-",
        ]
    )
    widths = [max(len(r[i]) for r in table) for i in range(4)]
    run = stats["run"]
    settings = run["settings"]
    target_ns = settings["target_on_ns"]
    print(
        f"run {run['run_id']}: {stats['all']['strokes']} strokes, mode {settings['mode']}, "
        f"T = {format_ns(target_ns)}, {run['end_reason']}"
    )
    for r in table:
        print(
            "  ".join([r[0].ljust(widths[0]), *(c.rjust(w) for c, w in zip(r[1:], widths[1:], strict=True))])
        )
    paper = PAPER_STD_NS.get(target_ns)
    if paper is not None and settings["mode"] == "closed":
        print(f"paper, closed loop at T = {format_ns(target_ns)}: error std {format_ns(paper)}")


def wait_idle(rig: Client, timeout_s: float = 10.0) -> dict[str, Any]:
    """Stop cycling if the daemon is cycling (it cycles on start on the sim) and wait until it has."""
    status = rig.status()
    if status["state"] == "cycling":
        rig.stop_cycling()
        end = time.monotonic() + timeout_s
        while status["state"] == "cycling" and time.monotonic() < end:
            time.sleep(0.02)
            status = rig.status()
    return status


def run(args: argparse.Namespace) -> int:
    """Set up the rig, run the strokes and report; the exit status of the script."""
    with Client(args.socket) as rig:
        status = wait_idle(rig)
        if status["state"] == "fault":
            print(f"the rig is in FAULT ({status['fault']}): `usmswitchctl reset` first", file=sys.stderr)
            return 1
        rig.set_mode(args.mode)
        # A run: subscribed before it starts, so iterating it sees every stroke, and it ends itself.
        # Leaving the `with` by an exception (Ctrl-C included) stops the rig: no run outlives the script.
        with rig.run(count=args.strokes, period=args.period, target=args.target) as strokes:
            for seen, rec in enumerate(strokes, 1):
                if not args.json and seen % args.progress == 0:
                    print(f"  {seen}/{args.strokes} strokes, last error {show(rec['error_ns'])}", flush=True)
        stats = strokes.stats()  # the daemon's statistics of exactly this run
    if args.json:
        print(json.dumps(stats, indent=2))
    else:
        print_report(stats)
    complete = stats["all"]["strokes"] == args.strokes and not (
        stats["all"]["stalls"] or stats["all"]["faults"]
    )
    return 0 if complete and strokes.info["end_reason"] == "done" else 1


def main(argv: list[str] | None = None) -> int:
    """Parse the flags and run; a refused call or a lost daemon is one line on stderr, not a traceback."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--socket", default=None, help="the daemon's socket (default: as usmswitchctl finds it)")
    p.add_argument("--target", type=duration, default=12_000_000, help="T, e.g. 12ms (default) or 24ms")
    p.add_argument("--strokes", type=int, default=500, help="how many strokes (default 500)")
    p.add_argument("--period", type=duration, default=30_000_000, help="command to command (default 30ms)")
    p.add_argument(
        "--mode", choices=("closed", "open"), default="closed", help="default closed (the AR loop)"
    )
    p.add_argument("--progress", type=int, default=100, help="print a line every this many strokes")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    args = p.parse_args(argv)
    if args.strokes < 1:
        p.error(f"--strokes must be at least 1, got {args.strokes}")
    if args.progress < 1:
        p.error(f"--progress must be at least 1, got {args.progress}")
    if args.period <= args.target:
        p.error(f"--period {format_ns(args.period)} must be longer than --target {format_ns(args.target)}")
    try:
        args.socket = args.socket or str(find_socket())
    except FileNotFoundError as exc:
        print(exc, file=sys.stderr)
        return 1
    try:
        return run(args)
    except RpcError as exc:
        print(f"the daemon refused: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"cannot talk to the daemon at {args.socket}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
