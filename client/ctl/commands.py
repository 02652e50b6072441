"""usmswitchctl's commands on a connected rig: each one or two Client calls plus formatting."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from typing import Any

from usmswitch.protocol.record import UNUSABLE
from usmswitch.protocol.sockets import web_token_path

from ..connection import Client
from .args import (
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_REFUSED,
    PROG,
    UsageError,
    positive_duration_arg,
)
from .output import (
    HISTORY_HEADER,
    PER_RUN_HEADER,
    RUN_HEADER,
    CycleProgress,
    WatchView,
    drive_table,
    history_row,
    notes_lines,
    per_run_rows,
    print_json,
    record_rows,
    run_row,
    run_strokes,
    scope_line,
    show_ns,
    stats_table,
    status_table,
    table,
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
        print(status_table(st))
    return EXIT_FAULT if st["state"] == "fault" else EXIT_OK


def cmd_stats(client: Client, args: argparse.Namespace) -> int:
    """A run's statistics (the current or last one by default), a range of cycles', or a label's
    runs' (pooled and per run), as a table."""
    if args.label is not None:
        return print_stats(client.stats(label=args.label), args)
    cycles = None if args.first is None else (args.first, args.last if args.last is not None else 2**62)
    return print_stats(client.stats(args.run, cycles=cycles), args)


def print_stats(stats: dict[str, Any], args: argparse.Namespace) -> int:
    """A stats reply (the daemon's, or one read from the records) as `stats` prints it."""
    if args.json:
        print_json(stats)
        return EXIT_OK
    if "label" in stats:  # a label's runs: pooled, then a row a run
        ids = ", ".join(str(r["run_id"]) for r in stats["runs"]) or "none"
        print(f"label {stats['label']}: runs {ids} pooled, {scope_line({**stats, 'run': None})}")
        print(stats_table(stats))
        if stats["per_run"]:
            print()
            print(table(per_run_rows(stats["per_run"]), PER_RUN_HEADER))
        for line in notes_lines(stats["runs"]):
            print(line)
        return EXIT_OK
    print(scope_line(stats))
    print(stats_table(stats))
    if stats.get("run") and stats["run"].get("notes"):
        print(*notes_lines([stats["run"]]), sep="\n")
    return EXIT_OK


def cmd_runs(client: Client, args: argparse.Namespace) -> int:
    """The last runs (with a label) as a table, oldest first."""
    return print_runs(client.runs(args.n, label=args.label), args)


def print_runs(runs: list[dict[str, Any]], args: argparse.Namespace) -> int:
    """The last runs (the daemon's, or read from the records), oldest first, as `runs` prints them."""
    if args.json:
        print_json(runs)
    elif not runs:
        label = getattr(args, "label", None)
        print(f"no run labelled {label}" if label else "no run recorded yet (`cycle` starts one)")
    else:
        print(table([run_row(r) for r in runs], RUN_HEADER))
        for line in notes_lines(runs):
            print(line)
        # Older runs exist: say that this is the tail, and how to see more.
        if runs[0]["run_id"] > 1 and not getattr(args, "label", None):
            print(
                f"(the last {len(runs)} runs; runs 1..{runs[0]['run_id'] - 1} are older: `runs -n N` shows"
                " more)"
            )
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
        result = client.set_target(target_ns, args.direction, allow_late=args.allow_late)
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
    """Start a run of on/off strokes (or queue it); with --wait, follow it to its end and report how
    it ended."""
    if args.queue:
        return _queue_run(client, args)
    if not args.wait:
        result = client.start_cycling(
            args.period,
            args.count,
            target=args.target,
            allow_late=args.allow_late,
            take_over=args.take_over,
            label=args.label,
            notes=args.notes,
        )
        _print_cycling(result, args)
        return EXIT_OK
    # Subscribed before the start: the end of a short run cannot slip past. From the start on, a
    # Ctrl-C (even one that lands while the first line prints) leaves the daemon cycling, and says so.
    run = client.run(
        args.count,
        args.period,
        args.target,
        allow_late=args.allow_late,
        take_over=args.take_over,
        label=args.label,
        notes=args.notes,
    )
    try:
        _print_cycling(run.started, args)
        with CycleProgress(run.started["first_cycle"], args.count if not args.json else 0) as progress:
            for rec in run:
                progress.update(rec["cycle"] + 1)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; the daemon keeps cycling (`{PROG} stop` stops it)", file=sys.stderr)
        return EXIT_INTERRUPTED
    info = run.info
    assert info is not None
    if not args.json:
        print(f"run {info['run_id']} ended: {info['end_reason']}, {run_strokes(info)} strokes")
    return EXIT_FAULT if info["end_reason"].startswith("fault") else EXIT_OK


def _queue_run(client: Client, args: argparse.Namespace) -> int:
    """`cycle --queue`: the run into the queue; with --wait, followed to its start and its end."""
    options = {
        "target": args.target,
        "allow_late": args.allow_late,
        "label": args.label,
        "notes": args.notes,
        "priority": args.priority,
        "take_over": args.take_over,
    }
    if not args.wait:
        entry = client.submit_entry(args.period, args.count, **options)
        if args.json:
            print_json(entry)
        else:
            print(f"queued as entry {entry['entry']}, {_place(entry)}")
        return EXIT_OK
    run = client.submit(args.count, args.period, **options)
    if not args.json:
        print(f"queued as entry {run.entry['entry']}, {_place(run.entry)}", flush=True)
    try:
        for _ in run:
            pass
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; entry {run.entry['entry']} stays queued or running", file=sys.stderr)
        return EXIT_INTERRUPTED
    info = run.info
    assert info is not None
    if args.json:
        print_json(info)
    else:
        print(f"run {info['run_id']} ended: {info['end_reason']}, {run_strokes(info)} strokes")
    return EXIT_FAULT if info["end_reason"].startswith("fault") else EXIT_OK


def _place(entry: dict[str, Any]) -> str:
    if entry.get("position") is None:
        return str(entry["state"])
    return f"position {entry['position']}" + (" (the queue is paused)" if entry.get("paused") else "")


def cmd_queue(client: Client, args: argparse.Namespace) -> int:
    """The queue of runs: listed, an entry cancelled or reordered, paused or resumed."""
    if args.action == "priority":
        entry = client.queue_priority(args.entry, args.priority, operator=args.operator)
        if args.json:
            print_json(entry)
        else:
            print(f"entry {entry['entry']}: priority {entry['priority']}, position {entry['position']}")
        return EXIT_OK
    if args.action == "cancel":
        entry = client.queue_cancel(args.entry, operator=args.operator)
        if args.json:
            print_json(entry)
        else:
            print(f"entry {entry['entry']} {entry['reason']}")
        return EXIT_OK
    if args.action == "pause":
        queue = client.queue_pause(operator=args.operator)
    elif args.action == "resume":
        queue = client.queue_resume(operator=args.operator)
    else:
        queue = client.status()["queue"]
    if args.json:
        print_json(queue)
        return EXIT_OK
    current = queue["current"]
    print("paused" if queue["paused"] else "going on", end="")
    print(f"; running: entry {current['entry']}, run {current['run_id']}" if current else "; none running")
    rows = [
        [
            str(e["position"]),
            str(e["entry"]),
            e["owner"],
            e["label"] or "-",
            str(e["priority"]),
            show_ns(e["period_ns"]),
            str(e["count"] or "until stopped"),
        ]
        for e in queue["queued"]
    ]
    if rows:
        print(table(rows, ("#", "entry", "owner", "label", "priority", "period", "strokes"), right_from=4))
    else:
        print("nothing queued (`cycle --queue` queues a run)")
    return EXIT_OK


def _print_cycling(result: dict[str, Any], args: argparse.Namespace) -> None:
    if args.json:
        print_json(result)
        return
    count = f"{args.count} strokes" if args.count else "until stopped"
    print(
        f"run {result['run_id']}: every {show_ns(result['period_ns'])}, {count}, "
        f"T on {show_ns(result['target_on_ns'])} / off {show_ns(result['target_off_ns'])}, "
        f"from cycle {result['first_cycle']}",
        flush=True,
    )
    for warning in result.get("warnings", []):
        print(f"{PROG}: warning: {warning}", file=sys.stderr)


def cmd_notes(client: Client, args: argparse.Namespace) -> int:
    """A run's notes and label: shown, or edited (its owner, or --operator)."""
    if args.text is None and args.label is None:
        run = client.stats(args.run)["run"]
    else:
        run = client.annotate_run(args.run, args.text, label=args.label, operator=args.operator)
    if args.json:
        print_json(run)
    else:
        print(f"run {run['run_id']} label: {run.get('label') or '-'}")
        print(f"notes: {run.get('notes') or '-'}")
    return EXIT_OK


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
    records = client.history(args.n, args.run)
    if args.json:
        print_json(records)
    elif not records:
        print("no strokes recorded yet" if args.run is None else f"run {args.run} has no strokes")
    else:
        print(table([history_row(r) for r in records], HISTORY_HEADER))
    return EXIT_OK


def cmd_watch(client: Client, args: argparse.Namespace) -> int:
    """Print every stroke as it finishes, with running error figures; Ctrl-C or --count ends it."""
    if args.count == 0:
        return EXIT_OK
    sub = client.subscribe("stroke", "state")
    seen = 0
    view = WatchView(live=False if args.json else None)
    try:
        if not args.json:
            print(f"watching {client.address} (Ctrl-C to stop)", flush=True)
            state = client.status().get("state")
            if state != "cycling":
                # A view of nothing would show zeros and leave the reader to wonder.
                print(
                    f"the rig is {state}: strokes show here once a run starts (usmswitchctl cycle)",
                    flush=True,
                )
        with view:
            for note in sub:
                if args.json:
                    print(
                        json.dumps({"topic": note.topic, "payload": note.payload}, sort_keys=True), flush=True
                    )
                elif note.topic == "state":
                    view.state(note.payload)
                else:
                    view.stroke(note.payload)
                seen += note.topic == "stroke"
                if args.count is not None and seen >= args.count:
                    break
    except KeyboardInterrupt:
        pass  # the user ended the view: a clean exit with the summary, no traceback
    if not args.json:
        print(view.running.summary() + (f"; {sub.dropped} dropped by the daemon" if sub.dropped else ""))
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
    return print_estop(client.estop(), args)


def print_estop(result: dict[str, Any], args: argparse.Namespace) -> int:
    """Say what an estop did (main() sends it by every path, with no Client made beforehand)."""
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
        print(drive_table(result))
    return EXIT_OK


def cmd_web_url(client: Client, args: argparse.Namespace) -> int:
    """The browser panel's URL with its token (as Jupyter prints one): read from the token file beside
    the socket, which only the socket's group may read, so whoever may use the socket may act."""
    url = client.status().get("web_url")
    if not url:
        print(
            f"{PROG}: the daemon serves no panel: start it with --web [HOST:]PORT or set [web] listen",
            file=sys.stderr,
        )
        return EXIT_REFUSED
    if client.family != "unix":
        raise UsageError("web-url reads the token beside the daemon's Unix socket; use --socket, not TCP")
    token_file = web_token_path(client.address)
    try:
        token = token_file.read_text().strip()
    except PermissionError:
        raise UsageError(
            f"cannot read the panel's token {token_file}: it is for the socket's group (mode 0640);"
            " join that group, or open the URL read-only: " + url
        ) from None
    except FileNotFoundError:
        raise UsageError(f"no panel token at {token_file}: is the daemon serving the panel?") from None
    full = f"{url}?token={token}"
    if args.json:
        print_json({"url": full, "token_file": str(token_file)})
    else:
        print(full)
    return EXIT_OK


COMMANDS: dict[str, Callable[[Client, argparse.Namespace], int]] = {
    "ping": cmd_ping,
    "status": cmd_status,
    "stats": cmd_stats,
    "runs": cmd_runs,
    "target": cmd_target,
    "switch": cmd_switch,
    "cycle": cmd_cycle,
    "notes": cmd_notes,
    "queue": cmd_queue,
    "stop": cmd_stop,
    "mode": cmd_mode,
    "history": cmd_history,
    "watch": cmd_watch,
    "reset": cmd_reset,
    "estop": cmd_estop,
    "drive": cmd_drive,
    "web-url": cmd_web_url,
}
