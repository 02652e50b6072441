"""usmswitch-experiment: the paper's experiments, one command each, and a report beside the paper.

    usmswitch-experiment all                        # every experiment on the simulated rig, then the report
    usmswitch-experiment closed-loop --seed 7
    usmswitch-experiment reliability --socket /run/usmswitch/usmswitchd.sock   # a real rig
    usmswitch-experiment all --socket /run/usmswitch/usmswitchd.sock --queue   # its turn on a shared rig
    usmswitch-experiment closed-loop --from-records /var/lib/usmswitch/records.sqlite --run 12

Each run writes to --out (default runs/<name>-<time>): records.sqlite, figures/*.png and .svg,
summary.json and report.md. docs/experiments.md explains each experiment.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import secrets
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from usmswitch.client import RecordsFileError, open_records
from usmswitch.client.plots import wall_text
from usmswitch.protocol.rpc_params import MAX_PRIORITY
from usmswitch.protocol.version import PACKAGE_VERSION

from . import (
    aic,
    closed_loop,
    drive_sensitivity,
    identify,
    open_loop,
    reliability,
    report,
    speed,
    temperature,
)
from .context import Context, NeedsSimulatedRig, NeedsStrokes, no_progress
from .data import Strokes
from .queued_rig import QueuedLiveRig
from .rig import LiveRig, Progress, SimulatedRig

PROG = "usmswitch-experiment"
#: Subcommand -> (summary key, module's run); in the order `all` runs them.
EXPERIMENTS: dict[str, tuple[str, Callable[[Context], dict[str, Any]]]] = {
    "open-loop": ("open_loop", open_loop.run),
    "speed": ("speed", speed.run),
    "identify": ("identify", identify.run),
    "temperature": ("temperature", temperature.run),
    "aic": ("aic", aic.run),
    "closed-loop": ("closed_loop", closed_loop.run),
    "reliability": ("reliability", reliability.run),
    "drive-sensitivity": ("drive_sensitivity", drive_sensitivity.run),
}
#: What a records file can answer (the others need a rig to act on).
FROM_RECORDS = ("open-loop", "aic", "closed-loop", "reliability")
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def _about(name: str) -> str:
    """An experiment's own help: its module's docstring (what figure of the paper, how)."""
    if name == "all":
        return "every experiment in turn on one rig, then report.md beside the paper's numbers"
    fn = EXPERIMENTS[name][1]
    doc = sys.modules[fn.__module__].__doc__ or name
    return doc.strip()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--version", action="version", version=f"{PROG} {PACKAGE_VERSION}")
    common = argparse.ArgumentParser(add_help=False)
    _options(common)
    sub = p.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    for name in [*EXPERIMENTS, "all"]:
        about = _about(name)
        sub.add_parser(
            name,
            parents=[common],
            help=" ".join(about.split("\n\n")[0].split()),
            description=about,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
    return p


def _options(p: argparse.ArgumentParser) -> None:
    """The options every experiment takes."""
    p.add_argument("--seed", type=int, help="the simulated rig's seed (default: a new one, recorded)")
    p.add_argument("--out", type=Path, help="the output folder (default runs/<experiment>-<time>)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--socket", help="run on a live daemon (a real rig) through this socket")
    src.add_argument(
        "--from-records",
        metavar="DB",
        help="analyse a records file (or state directory), or a rig's records in PostgreSQL "
        "(postgresql://USER@HOST/DB, with --rig)",
    )
    p.add_argument("--run", type=int, help="with --from-records: the run to analyse (default: the last)")
    p.add_argument(
        "--take-over",
        action="store_true",
        help="with --socket: end a run a client started (it is started again when the experiment ends)",
    )
    p.add_argument(
        "--queue",
        action="store_true",
        help="with --socket: wait for the rig in the daemon's queue (never ending another's run), then"
        " hold it for the experiment's runs",
    )
    p.add_argument(
        "--priority", type=int, help="with --queue: the turn's place in the queue (-1000..1000, higher first)"
    )
    p.add_argument("--rig", help="with --from-records postgresql://...: the rig (when it holds several)")
    p.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="stroke counts as a fraction of the paper's (default 1; tests use less)",
    )


@contextmanager
def rich_progress(label: str, total: int) -> Iterator[Progress]:
    """A progress bar on a terminal (rich draws and redraws it); nothing on a pipe."""
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn
    from rich.progress import Progress as Bar

    with Bar(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=total)
        pending = [0]

        def advance(n: int) -> None:
            pending[0] += n
            if pending[0] >= 200 or pending[0] + bar.tasks[0].completed >= total:  # redraws cost
                bar.advance(task, pending[0])
                pending[0] = 0

        yield advance


def recorded_run(
    source: str, run_id: int | None, rig: str | None = None, closed_loop: bool = False
) -> tuple[Strokes, str]:
    """A run's strokes from a records file, a state directory or the PostgreSQL copy (`rig` of it):
    run `run_id`, else the last one (`closed_loop`: the last closed-loop one). Says which on stderr."""
    with open_records(source, rig) as f:
        runs = f.runs()
        run = None
        if run_id is not None:
            run = next((r for r in runs if r["run_id"] == run_id), None)
        elif runs:
            fitting = [r for r in runs if not closed_loop or r["settings"].get("mode") == "closed"]
            if not fitting:
                raise RecordsFileError(
                    f"{f.name}: no closed-loop run (runs: {len(runs)}); name one with --run"
                )
            run = fitting[-1]
            run_id = run["run_id"]
        records = list(f.records(run=run_id)) if run_id is not None else list(f.records())
        name = f.name
    if run is not None:
        s = run["settings"]
        print(
            f"{PROG}: run {run_id} of {name}: {s.get('mode', '?')} loop, model {s.get('model', '?')}"
            f" order {s.get('order', '?')}, {len(records)} strokes"
            + ("" if closed_loop or run is runs[-1] else " (not the last run)"),
            file=sys.stderr,
        )
    if not records:
        raise RecordsFileError(f"{name}: no strokes" + (f" in run {run_id}" if run_id else ""))
    where = f"{name}" + (f", run {run_id}" if run_id is not None else ", every stroke")
    strokes = Strokes.from_records(records, run_id=run_id)
    return dataclasses.replace(strokes, run=run), where


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    names = list(EXPERIMENTS) if args.experiment == "all" else [args.experiment]
    for flag in ("run", "rig"):
        if getattr(args, flag) is not None and args.from_records is None:
            print(f"{PROG}: --{flag} goes with --from-records", file=sys.stderr)
            return EXIT_USAGE
    usage = None
    if args.queue and args.socket is None:
        usage = "--queue goes with --socket (the daemon's queue)"
    elif args.queue and args.take_over:
        usage = "--queue waits for the run going, --take-over ends it: give one"
    elif args.priority is not None and not args.queue:
        usage = "--priority goes with --queue"
    elif args.priority is not None and not -MAX_PRIORITY <= args.priority <= MAX_PRIORITY:
        usage = f"--priority must be in -{MAX_PRIORITY}..{MAX_PRIORITY}, got {args.priority}"
    if usage is not None:
        print(f"{PROG}: {usage}", file=sys.stderr)
        return EXIT_USAGE
    if args.from_records is not None and args.experiment not in (*FROM_RECORDS, "all"):
        print(
            f"{PROG}: {args.experiment} needs a rig; from records: {', '.join(FROM_RECORDS)}", file=sys.stderr
        )
        return EXIT_USAGE
    if not 0 < args.scale <= 1:
        print(f"{PROG}: --scale must be in (0, 1], got {args.scale}", file=sys.stderr)
        return EXIT_USAGE
    started = datetime.datetime.now()
    out: Path = args.out or Path("runs") / f"{args.experiment}-{started:%Y%m%d-%H%M%S}"
    out.mkdir(parents=True, exist_ok=True)
    seed = args.seed if args.seed is not None else secrets.randbelow(2**31)
    progress = rich_progress if sys.stderr.isatty() else no_progress
    ctx = Context(out=out, seed=None, scale=args.scale, progress=progress)  # type: ignore[arg-type]
    try:
        if args.from_records is not None:
            closed = args.experiment == "closed-loop"  # its run is a closed-loop one unless named
            ctx.recorded, where = recorded_run(args.from_records, args.run, args.rig, closed_loop=closed)
            names = [n for n in names if n in FROM_RECORDS]
        elif args.socket is not None and args.queue:
            ctx.rig = QueuedLiveRig(args.socket, args.priority or 0, _say)
            where = f"the live rig at {args.socket}, its turn taken in the daemon's queue"
        elif args.socket is not None:
            ctx.rig, where = LiveRig(args.socket, args.take_over), f"the live rig at {args.socket}"
        else:
            ctx.rig, ctx.seed = SimulatedRig(out / "records.sqlite", seed), seed
            where = "the simulated rig (in-process, virtual time)"
            print(
                f"{PROG}: simulated rig, seed {seed} (replay with --seed {seed}); output in {out}",
                file=sys.stderr,
            )
    except (RecordsFileError, OSError, RuntimeError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_FAILED
    ctx.date = f"{started:%Y-%m-%d %H:%M:%S}"
    if ctx.recorded is not None:
        run = ctx.recorded.run or {}
        ctx.rig_name = run.get("rig") or str(args.rig or args.from_records)
        if run.get("started_wall_ns"):
            ctx.date = wall_text(run["started_wall_ns"])  # when the strokes were made, not read
    elif ctx.rig is not None:
        ctx.rig_name = ctx.rig.name
    if args.from_records is not None:
        data = f"read from {where} (read-only; nothing was written beside this report)"
    elif args.socket is not None:
        data = (
            "the daemon's own records file, on the rig (`usmswitchctl runs` lists the experiment's runs, "
            "`usmswitchctl export --run N` exports one); nothing was written beside this report"
        )
    else:
        data = "`records.sqlite` in this folder (every stroke, `usmswitchctl export --state-dir .`)"
    summary: dict[str, Any] = {
        "meta": {
            "data": data,
            "command": " ".join(["usmswitch-experiment", *(argv if argv is not None else sys.argv[1:])]),
            "where": where,
            "seed": ctx.seed,
            "version": PACKAGE_VERSION,
            "started": started.isoformat(timespec="seconds"),
            "scale": args.scale,
            "notes": ctx.notes,
        }
    }
    status = EXIT_OK
    t0 = time.monotonic()
    try:
        for name in names:
            key, fn = EXPERIMENTS[name]
            ctx.run_ids = []  # each experiment's figures name its own runs
            try:
                section = fn(ctx)
            except (NeedsSimulatedRig, NeedsStrokes) as exc:
                ctx.notes.append(f"{name}: skipped: {exc}")
                if args.experiment != "all":
                    status = EXIT_FAILED
                continue
            if key == "closed_loop":
                summary["closed_loop"] = section.pop("rows")
                summary["closed_loop_runs"] = section
            else:
                summary[key] = section
            print(f"{PROG}: {name} done ({time.monotonic() - t0:.1f} s)", file=sys.stderr)
    finally:
        if ctx.rig is not None:
            ctx.rig.close()  # a live rig: every setting changed is put back, whatever happened
    if isinstance(ctx.rig, LiveRig):
        summary["meta"]["restored"] = ctx.rig.restored
        for line in ctx.rig.restored:
            print(f"{PROG}: restored {line}", file=sys.stderr)
    summary["meta"]["seconds"] = round(time.monotonic() - t0, 1)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_plain) + "\n")
    (out / "report.md").write_text(report.render(summary))
    print(f"{PROG}: report in {out / 'report.md'}", file=sys.stderr)
    return status


def _say(line: str) -> None:
    print(f"{PROG}: {line}", file=sys.stderr, flush=True)


def _plain(value: object) -> object:
    """numpy scalars in summary.json as plain numbers."""
    if hasattr(value, "item"):
        return value.item()  # type: ignore[no-any-return]
    raise TypeError(f"{type(value).__name__} is not JSON")


if __name__ == "__main__":
    sys.exit(main())
