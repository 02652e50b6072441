"""The loop's runs: each start_cycling opens one, its strokes carry its id and have statistics of
their own; a run ended during a stroke ends once that stroke is recorded."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from usmswitch.protocol.record import CycleRecord, RunRecord
from usmswitch.protocol.stats import DirectionStats


class RunBook:
    """The open run (else the last one), its statistics, and where each change of it is sent."""

    def __init__(self, first_run_id: int, sink: Callable[[RunRecord], None] | None) -> None:
        self.sink = sink
        self.latest: RunRecord | None = None  # the open run, else the last one
        self.stats = [DirectionStats(), DirectionStats()]  # the latest run's, per direction
        self.stats_all = DirectionStats()  # both directions together
        self._next_id = first_run_id
        self._ending: str | None = None  # why the open run ends, once its last stroke is recorded

    @property
    def running_id(self) -> int | None:
        """The open run's id (None when no run is open)."""
        run = self.latest
        return run.run_id if run is not None and run.running else None

    def open(
        self,
        kind: str,
        first_cycle: int,
        settings: dict[str, Any],
        label: str | None = None,
        notes: str | None = None,
    ) -> RunRecord:
        """A new run from `first_cycle`; an open one is ended first ("superseded", at the cycle
        before)."""
        self.end("superseded", first_cycle - 1, in_stroke=False)  # never two open runs
        run = RunRecord(
            run_id=self._next_id,
            kind=kind,
            first_cycle=first_cycle,
            started_wall_ns=time.time_ns(),
            settings=settings,
            label=label,
            notes=notes,
        )
        self._next_id += 1
        self.latest = run
        self._ending = None
        self.stats = [DirectionStats(), DirectionStats()]
        self.stats_all = DirectionStats()
        self._send(run)
        return run

    def end(self, reason: str, last_cycle: int, in_stroke: bool) -> None:
        """End the open run (if any) with `reason` at `last_cycle`; `in_stroke`: once that stroke is
        recorded (`after_stroke`)."""
        run = self.latest
        if run is None or not run.running:
            return
        if in_stroke:
            self._ending = self._ending or reason
            return
        run.last_cycle = last_cycle
        run.ended_wall_ns = time.time_ns()
        run.end_reason = reason
        self._ending = None
        self._send(run)

    def after_stroke(self, last_cycle: int) -> None:
        """A stroke is recorded: a run ended during it ends now."""
        if self._ending is not None:
            self.end(self._ending, last_cycle, in_stroke=False)

    def add(self, rec: CycleRecord) -> None:
        """A stroke of the open run into its statistics."""
        self.stats[rec.direction].add_record(rec)
        self.stats_all.add_record(rec)

    def _send(self, run: RunRecord) -> None:
        if self.sink is not None:
            self.sink(run)
