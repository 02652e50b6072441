#!/usr/bin/env python3
"""A lab script: set the target T, run 500 strokes through the daemon, print what they did.

    python examples/run_500_strokes.py --target 12ms
    python examples/run_500_strokes.py --socket /run/usmswitch/usmswitchd.sock --target 24ms --strokes 1000

It talks to a running `usmswitchd` (e.g. `make run`, the simulated rig) with the Python client only:
stop any cycling, set the mode and T, start `--strokes` strokes, follow them on the subscription,
then read the run's records back (`history`, the daemon's SQLite file) and summarise those strokes:
the paper's figure of merit is the standard deviation of error = total - T (95.3 us at T = 12 ms).
Exit status: 0 when every stroke finished, 1 when the daemon refused or the run ended in FAULT.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from typing import Any

from usmswitch.client import Client, CycleRecord, RpcError, client_socket_paths
from usmswitch.daemon.record import UNUSABLE, Flag
from usmswitch.daemon.units import format_ns, parse_duration_ns

# The paper's closed-loop result at T = 12 ms and 24 ms (std of the error), for comparison.
PAPER_STD_NS = {12_000_000: 95_300, 24_000_000: 102_700}


def duration(text: str) -> int:
    """argparse type: "12ms", "10500us", "0.012s" -> integer ns."""
    try:
        return parse_duration_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def default_socket() -> str:
    """The first daemon socket that exists, as usmswitchctl looks for it."""
    paths = client_socket_paths()
    return str(next((p for p in paths if p.exists()), paths[0]))


def summarise(records: list[CycleRecord]) -> dict[str, Any]:
    """Error and operating-time figures of some strokes (those that reached the far sensor)."""
    done = [r for r in records if r["error_ns"] is not None]
    errors = [r["error_ns"] for r in done]
    abs_errors = [abs(e) for e in errors]
    operating = [r["operating_ns"] for r in done if r["operating_ns"] is not None]
    out: dict[str, Any] = {
        "strokes": len(records),
        "completed": len(done),
        "late": sum(1 for r in records if r["flags"] & Flag.LATE),
        "failed": sum(1 for r in records if r["flags"] & UNUSABLE),
        "error_mean_ns": statistics.fmean(errors) if errors else None,
        "error_std_ns": statistics.stdev(errors) if len(errors) > 1 else None,
        "error_max_abs_ns": max(abs_errors) if abs_errors else None,
        "max_abs_error_pct": max(abs(r["error_ns"]) / r["target_ns"] * 100 for r in done) if done else None,
        "operating_mean_ns": statistics.fmean(operating) if operating else None,
        "operating_std_ns": statistics.stdev(operating) if len(operating) > 1 else None,
    }
    ranked = sorted(abs_errors)
    for q in (50, 95, 99):
        out[f"abs_error_p{q}_ns"] = nearest_rank(ranked, q)
    return out


def nearest_rank(ranked: list[int], q: float) -> int | None:
    """The q-th percentile by nearest rank (a value that occurred), as the daemon's stats define it."""
    if not ranked:
        return None
    return ranked[max(1, math.ceil(q * len(ranked) / 100)) - 1]


def show(value: float | None) -> str:
    """A duration in ns for people ("-" when there is none)."""
    return "-" if value is None or not math.isfinite(value) else format_ns(round(value))


def print_report(
    target_ns: int, mode: str, summary: dict[str, dict[str, Any]], stats: dict[str, Any]
) -> None:
    """The run's figures as an aligned table, one column per direction and one for both."""
    cols = ("on", "off", "all")
    rows = [
        ("strokes", lambda s: str(s["strokes"])),
        ("completed", lambda s: str(s["completed"])),
        ("error mean", lambda s: show(s["error_mean_ns"])),
        ("error std", lambda s: show(s["error_std_ns"])),
        ("max |error|", lambda s: show(s["error_max_abs_ns"])),
        (
            "max |error| % of T",
            lambda s: "-" if s["max_abs_error_pct"] is None else f"{s['max_abs_error_pct']:.3f} %",
        ),
        ("|error| p50", lambda s: show(s["abs_error_p50_ns"])),
        ("|error| p95", lambda s: show(s["abs_error_p95_ns"])),
        ("|error| p99", lambda s: show(s["abs_error_p99_ns"])),
        ("operating mean", lambda s: show(s["operating_mean_ns"])),
        ("operating std", lambda s: show(s["operating_std_ns"])),
        ("late", lambda s: str(s["late"])),
        ("stall/fault/estop", lambda s: str(s["failed"])),
    ]
    table = [["", *cols]] + [[label, *(fn(summary[c]) for c in cols)] for label, fn in rows]
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
    print(f"{summary['all']['strokes']} strokes, mode {mode}, T = {format_ns(target_ns)}")
    for r in table:
        print(
            "  ".join([r[0].ljust(widths[0]), *(c.rjust(w) for c, w in zip(r[1:], widths[1:], strict=True))])
        )
    paper = PAPER_STD_NS.get(target_ns)
    if paper is not None and mode == "closed":
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
    """Set up the rig, run the strokes, read them back and report; the exit status of the script."""
    with Client(args.socket) as rig:
        status = wait_idle(rig)
        if status["state"] == "fault":
            print(f"the rig is in FAULT ({status['fault']}): `usmswitchctl reset` first", file=sys.stderr)
            return 1
        rig.set_mode(args.mode)
        rig.set_target(args.target, "both")
        # Subscribe before starting, so not one stroke of the run is missed.
        strokes = rig.subscribe("stroke", "state", timeout_ns=max(10 * args.period, 5_000_000_000))
        started = rig.start_cycling(args.period, args.strokes)
        first = started["first_cycle"]
        last = first + args.strokes - 1
        seen = 0
        for topic, payload in strokes:
            if topic == "state" and payload.get("state") == "fault":
                print(f"FAULT during the run: {payload.get('fault')}", file=sys.stderr)
                break
            if topic == "stroke" and first <= payload["cycle"] <= last:
                seen += 1
                if not args.json and seen % args.progress == 0:
                    print(
                        f"  {seen}/{args.strokes} strokes, last error {show(payload['error_ns'])}", flush=True
                    )
                if payload["cycle"] == last:
                    break
        strokes.close()
        # The records are the truth (a slow reader may have lost notifications): read the run back.
        records = [r for r in rig.history(min(args.strokes, 10_000)) if first <= r["cycle"] <= last]
        stats = rig.stats()
    summary = {
        "on": summarise([r for r in records if r["direction"] == 0]),
        "off": summarise([r for r in records if r["direction"] == 1]),
        "all": summarise(records),
    }
    if args.json:
        print(
            json.dumps(
                {
                    "target_ns": args.target,
                    "mode": args.mode,
                    "first_cycle": first,
                    "last_cycle": last,
                    "summary": summary,
                    "order": {"on": stats["on"]["order"], "off": stats["off"]["order"]},
                    "coefficients": {"on": stats["on"]["coefficients"], "off": stats["off"]["coefficients"]},
                },
                indent=2,
            )
        )
    else:
        print_report(args.target, args.mode, summary, stats)
    complete = len(records) == args.strokes and summary["all"]["failed"] == 0
    return 0 if complete else 1


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
    args.socket = args.socket or default_socket()
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
