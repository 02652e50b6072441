"""usmswitchctl export and plot: records from the socket, or straight from a records file or the
PostgreSQL copy (`--from`)."""

from __future__ import annotations

import argparse
import itertools
import os
import sqlite3
import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from usmswitch.protocol.record import CycleRecord as Record
from usmswitch.protocol.record_csv import csv_header_line

from ..connection import Client
from ..records import RecordsFileError, RecordsSource
from ..sources import open_records
from ..types import CycleRecord
from .args import EXIT_OK, UsageError
from .output import ExportProgress, print_json, write_csv


def _records_from(
    source: str | Path, first: int, last: int | None, run: int | None = None, rig: str | None = None
) -> Iterator[CycleRecord]:
    """Every stroke, read-only, without the socket's limit: from the daemon's SQLite file (a state
    directory or the file) or from the PostgreSQL copy (`rig` of it). Opened at once, so a bad
    source is said before any output is written."""
    try:
        records = open_records(source, rig)
        if run is not None:
            records.run(run)  # a run the records lack: said before any output is written
    except RecordsFileError as exc:
        raise UsageError(f"export: {exc}") from None

    def rows() -> Iterator[CycleRecord]:
        with records:
            yield from records.records(first, last, run=run)  # type: ignore[misc]

    return rows()


def _latest_run(args: argparse.Namespace, connect: Callable[[], Client]) -> int | None:
    """The newest run's id (None: no run recorded, so every stroke)."""
    source = _source(args)
    if source is None:
        with connect() as client:
            runs = client.runs(1)
    else:
        try:
            with open_records(source, args.rig if args.source else None) as records:
                runs = list(records.runs())
        except RecordsFileError as exc:
            raise UsageError(f"plot: {exc}") from None
    return runs[-1]["run_id"] if runs else None


def _source(args: argparse.Namespace) -> str | None:
    """Where --from or --state-dir say the records are (None: over the socket)."""
    return args.source if args.source is not None else args.state_dir


def _write(records: Iterable[CycleRecord] | _CsvChunks, out: IO[str], where: str, progress: bool) -> int:
    """write_csv, with a records source that fails midway (a corrupt row, a file gone) named as such."""
    try:
        if isinstance(records, _CsvChunks):
            return records.write(out, progress)
        return write_csv(records, out)
    except (RecordsFileError, sqlite3.Error, ValueError) as exc:
        raise UsageError(f"export: reading the records failed partway through {where}: {exc}") from None


def covered(
    runs: Iterable[dict[str, Any]], first: int, last: int | None, run: int | None
) -> list[dict[str, Any]]:
    """The runs an export covers (for their label and notes above its header): the one asked for,
    else those whose cycles meet first..last."""
    top = last if last is not None else 1 << 62
    return [
        r
        for r in runs
        if (
            r["run_id"] == run
            if run is not None
            else r["first_cycle"] <= top and (r["last_cycle"] or top) >= first
        )
    ]


class _CsvChunks:
    """A records source's strokes as CSV text a chunk at a time (built by SQLite for a records file:
    issue 36), written as they come; a progress bar on a terminal's stderr past a second."""

    def __init__(
        self, records: RecordsSource, first: int, last: int | None, run: int | None, label: str | None = None
    ) -> None:
        self.records, self.first, self.last, self.run, self.label = records, first, last, run, label

    def write(self, out: IO[str], progress: bool) -> int:
        n = 0
        with self.records:
            span = None
            if progress and self.label is None:
                span = self.records.cycle_span(self.first, self.last, self.run)
            runs = self.records.runs(self.label)
            out.write(csv_header_line(runs if self.label else covered(runs, self.first, self.last, self.run)))
            chunks = self.records.csv_chunks(self.first, self.last, self.run, label=self.label)
            with ExportProgress(span, sys.stderr if progress else None) as bar:
                for strokes, last_cycle, text in chunks:
                    out.write(text)
                    n += strokes
                    bar.update(last_cycle, n)
        return n


class _SocketChunks(_CsvChunks):
    """Every stroke (of a run, a range) over the socket, a chunk of CSV text a call (`export`)."""

    def __init__(
        self,
        connect: Callable[[], Client],
        first: int,
        last: int | None,
        run: int | None,
        label: str | None = None,
    ) -> None:
        self.connect, self.first, self.last, self.run, self.label = connect, first, last, run, label

    def write(self, out: IO[str], progress: bool) -> int:
        n = 0
        with self.connect() as client:
            span = None
            listed = client.runs(1000, label=self.label)
            if progress and self.run is not None:
                run = {r["run_id"]: r for r in listed}.get(self.run)
                if run is not None:
                    span = (max(self.first, run["first_cycle"]), run["last_cycle"] or self.last or 0)
            elif progress and self.last is not None and self.label is None:
                span = (self.first, self.last)
            covers = listed if self.label else covered(listed, self.first, self.last, self.run)
            chunks = client.export_csv(self.run, self.first, self.last, label=self.label)
            first = next(chunks, None)  # a run the daemon lacks: refused before the header is out
            out.write(csv_header_line(covers))
            with ExportProgress(span, sys.stderr if progress else None) as bar:
                for strokes, last_cycle, text in itertools.chain([first] if first else [], chunks):
                    out.write(text)
                    n += strokes
                    bar.update(last_cycle, n)
        return n


def _csv_chunks_from(
    source: str | Path, first: int, last: int | None, run: int | None, rig: str | None, label: str | None
) -> _CsvChunks:
    try:
        records = open_records(source, rig)
        if run is not None:
            records.run(run)
    except RecordsFileError as exc:
        raise UsageError(f"export: {exc}") from None
    return _CsvChunks(records, first, last, run, label)


def cmd_export(args: argparse.Namespace, connect: Callable[[], Client]) -> int:
    """Write cycle records as CSV: all of them from the SQLite file, or the last n over the socket."""
    if args.csv is None:
        raise UsageError("export needs --csv FILE (or --csv - for standard output)")
    if _source(args) is not None:
        records: Iterable[CycleRecord] | _CsvChunks = _csv_chunks_from(
            _source(args), args.first, args.last, args.run, args.rig if args.source else None, args.label
        )
    elif args.n is not None:
        if args.first != 1 or args.last is not None:
            raise UsageError("export: -n (the last n strokes) or --first/--last, not both")
        if args.label is not None:
            raise UsageError("export: -n (the last n strokes) or --label, not both")
        with connect() as client:
            records = client.history(args.n, args.run)
    else:
        records = _SocketChunks(connect, args.first, args.last, args.run, args.label)
    if args.csv == "-":
        n = _write(records, sys.stdout, "standard output", not args.json)
        sys.stdout.flush()
    else:
        tmp = Path(f"{args.csv}.partial")
        try:
            with open(tmp, "w", newline="", encoding="utf-8") as fh:
                n = _write(records, fh, args.csv, not args.json)
            os.replace(tmp, args.csv)  # a reader never sees half a file
        except OSError as exc:
            raise UsageError(f"export: cannot write {args.csv}: {exc.strerror or exc}") from None
        finally:
            # Whatever ended the export early (the daemon lost, a bad records file, Ctrl-C):
            # no half file is left behind under a name that looks like a result.
            tmp.unlink(missing_ok=True)
    if args.csv != "-":
        message = {"records": n, "file": str(args.csv)}
        if args.json:
            print_json(message)
        else:
            print(f"{n} records written to {args.csv}")
    return EXIT_OK


def cmd_plot(args: argparse.Namespace, connect: Callable[[], Client]) -> int:
    """Draw a run (operating time and t_hat, error against T, its histogram) to an image file."""
    from ..plots import plot_run  # matplotlib: only for this command

    if args.run is None and not args.all and args.first == 1 and args.last is None:
        args.run = _latest_run(args, connect)  # one run, as `stats` shows; --all for every stroke
    if _source(args) is not None:
        rows: Iterable[CycleRecord] = _records_from(
            _source(args), args.first, args.last, args.run, args.rig if args.source else None
        )
    else:
        with connect() as client:
            rows = client.history(args.n, args.run)
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
