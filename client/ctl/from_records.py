"""usmswitchctl runs and stats with --state-dir or --from: read from a records file (or a state
directory) or the PostgreSQL copy, read-only, with no daemon running, as export and plot read."""

from __future__ import annotations

import argparse
from typing import Any

from usmswitch.protocol.record import CycleRecord
from usmswitch.protocol.stats import stats_of_records

from ..records import RecordsFileError, RecordsSource
from ..sources import open_records
from .args import UsageError
from .commands import print_runs, print_stats


def records_source(args: argparse.Namespace) -> str | None:
    """Where --from or --state-dir say the records are (None: ask the daemon)."""
    source = getattr(args, "source", None)
    return source if source is not None else getattr(args, "state_dir", None)


def _open(args: argparse.Namespace) -> RecordsSource:
    source = records_source(args)
    assert source is not None
    try:
        return open_records(source, args.rig if args.source is not None else None)
    except RecordsFileError as exc:
        raise UsageError(f"{args.command}: {exc}") from None


def cmd_runs_from(args: argparse.Namespace) -> int:
    """`runs` of a records file: its last -n runs, oldest first."""
    with _open(args) as records:
        runs = records.runs(args.label)
    return print_runs(runs[-args.n :], args)


def cmd_stats_from(args: argparse.Namespace) -> int:
    """`stats` of a records file: a run (default: the last), or cycles --first..--last, every
    stroke read (exact percentiles, as the daemon's for a range)."""
    with _open(args) as records:
        try:
            if args.label is not None:
                return print_stats(_label_stats(records, args.label), args)
            run: dict[str, Any] | None = None
            if args.first is not None:
                rows = records.records(args.first, args.last)
            else:
                runs = records.runs()
                if args.run is not None:
                    run = records.run(args.run)
                elif runs:
                    run = runs[-1]
                rows = records.records(run=None if run is None else run["run_id"])
            stats = stats_of_records(CycleRecord.from_row(r) for r in rows)
        except RecordsFileError as exc:
            raise UsageError(f"stats: {exc}") from None
    stats["run"] = run
    return print_stats(stats, args)


def _label_stats(records: RecordsSource, label: str) -> dict[str, Any]:
    """`stats --label` of a records file: every stroke of the label's runs read (exact, as a range),
    pooled and per run, in the daemon's reply's shape."""
    runs = records.runs(label)
    per_run = []
    for run in runs:
        part = stats_of_records(CycleRecord.from_row(r) for r in records.records(run=run["run_id"]))
        per_run.append({**part, "run": run})
    pooled = stats_of_records(CycleRecord.from_row(r) for r in records.records(label=label))
    return {**pooled, "label": label, "run": None, "runs": runs, "per_run": per_run}
