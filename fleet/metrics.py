"""The figures of the Prometheus page, counted in the daemon from the records it commits.

`StrokeMetrics` runs on the record writer's thread (`RecordStore.on_commit` and `on_run`): it
counts each committed stroke by direction and outcome and folds its error, operating time and
start lateness into fixed histograms, so the page agrees with the records file by construction.
Its `snapshot()` is a small dict of plain integers that the daemon hands to the socket's server
process, which renders the page (web/metrics_page.py): the loop's process never formats text,
never serves a scrape and never imports prometheus_client. Metric names and meanings: docs/fleet.md.
"""

from __future__ import annotations

from bisect import bisect_left
from typing import Any

from usmswitch.protocol.record import CycleRecord, Flag, RunRecord
from usmswitch.protocol.stats import Running

#: The snapshots the daemon sends the server process for the page (RpcServer feeds): the strokes
#: (record writer's thread) and the state (the loop's slack).
STROKES_FEED = "metrics_strokes"
STATE_FEED = "metrics_state"
FEEDS = (STROKES_FEED, STATE_FEED)
DIRECTION_NAMES = ("on", "off")
#: A stroke's outcome, one per stroke: the first of these its flags match, else "ok" (a clean
#: stroke, which may still carry WARMUP or BOUNCE). STALL and ESTOP come with FAULT, so they go first.
OUTCOME_FLAGS: tuple[tuple[str, int], ...] = (
    ("stall", Flag.STALL),
    ("estop", Flag.ESTOP),
    ("aborted", Flag.ABORTED),
    ("fault", Flag.FAULT),
    ("partial", Flag.PARTIAL),
    ("late", Flag.LATE),
)
OUTCOMES: tuple[str, ...] = ("ok", *(name for name, _ in OUTCOME_FLAGS))

US = 1_000
MS = 1_000_000
#: Histogram bucket upper bounds in ns (the page shows them in seconds). The error is signed:
#: symmetric buckets around 0, finest where a controlled stroke lands (tens of us).
ERROR_BOUNDS_NS: tuple[int, ...] = tuple(
    [-b for b in (5 * MS, 2 * MS, MS, 500 * US, 200 * US, 100 * US, 50 * US, 20 * US)]
    + [0]
    + [20 * US, 50 * US, 100 * US, 200 * US, 500 * US, MS, 2 * MS, 5 * MS]
)
OPERATING_BOUNDS_NS: tuple[int, ...] = tuple(
    int(x * MS) for x in (5, 8, 9, 9.5, 10, 10.5, 11, 11.5, 12, 13, 15, 20, 30, 50)
)
LATENESS_BOUNDS_NS: tuple[int, ...] = tuple(
    x * US for x in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000)
)
HISTOGRAMS: dict[str, tuple[str, tuple[int, ...]]] = {
    # name: (the record field observed, bucket bounds)
    "error": ("error_ns", ERROR_BOUNDS_NS),
    "operating": ("operating_ns", OPERATING_BOUNDS_NS),
    "lateness": ("lateness_ns", LATENESS_BOUNDS_NS),
}


def outcome(flags: int) -> str:
    """The one outcome label of a stroke with these flags."""
    for name, bit in OUTCOME_FLAGS:
        if flags & bit:
            return name
    return "ok"


class Histogram:
    """Counts per bucket (not cumulative; the last is above every bound), the count and the exact sum."""

    __slots__ = ("bounds", "buckets", "count", "sum_ns")

    def __init__(self, bounds: tuple[int, ...]) -> None:
        self.bounds = bounds
        self.buckets = [0] * (len(bounds) + 1)
        self.count = 0
        self.sum_ns = 0

    def observe(self, value_ns: int) -> None:
        """Count one value in its bucket, the count and the sum."""
        # Prometheus buckets are "less than or equal": a value on a bound counts in that bound's.
        self.buckets[bisect_left(self.bounds, value_ns)] += 1
        self.count += 1
        self.sum_ns += value_ns

    def snapshot(self) -> dict[str, Any]:
        """Plain values: the per-bucket counts (not cumulative), the count, the sum in ns."""
        return {"buckets": list(self.buckets), "count": self.count, "sum_ns": self.sum_ns}


class StrokeMetrics:
    """Counters and histograms of the strokes committed since the daemon started (one thread only)."""

    def __init__(self) -> None:
        self.strokes = [dict.fromkeys(OUTCOMES, 0) for _ in DIRECTION_NAMES]
        self.histograms = {
            name: [Histogram(bounds) for _ in DIRECTION_NAMES] for name, (_, bounds) in HISTOGRAMS.items()
        }
        self.last: list[CycleRecord | None] = [None, None]
        self.run_id: int | None = None
        self.run_error = [Running(), Running()]

    def add(self, records: list[CycleRecord]) -> None:
        """Fold committed strokes in (RecordStore.on_commit)."""
        for rec in records:
            d = rec.direction
            self.strokes[d][outcome(rec.flags)] += 1
            for name, (field, _) in HISTOGRAMS.items():
                value = getattr(rec, field)
                if value is not None:
                    self.histograms[name][d].observe(value)
            if rec.error_ns is not None and rec.run_id is not None and rec.run_id == self.run_id:
                self.run_error[d].add(rec.error_ns)
            self.last[d] = rec

    def on_run(self, run: RunRecord) -> None:
        """A run opened (its error figures start afresh) or ended (RecordStore.on_run)."""
        if run.running and run.run_id != self.run_id:
            self.run_id = run.run_id
            self.run_error = [Running(), Running()]

    def snapshot(self) -> dict[str, Any]:
        """Plain values for the server process: counts, histograms, the last stroke's figures."""
        out: dict[str, Any] = {
            "strokes": {name: dict(self.strokes[d]) for d, name in enumerate(DIRECTION_NAMES)},
            "histograms": {
                h: {name: self.histograms[h][d].snapshot() for d, name in enumerate(DIRECTION_NAMES)}
                for h in HISTOGRAMS
            },
            "run_id": self.run_id,
        }
        last: dict[str, Any] = {}
        for d, name in enumerate(DIRECTION_NAMES):
            rec = self.last[d]
            err = self.run_error[d]
            last[name] = {
                "cycle": None if rec is None else rec.cycle,
                "t_hat_ns": None if rec is None else rec.t_hat_ns,
                "target_ns": None if rec is None else rec.target_ns,
                "temperature_c": None if rec is None else rec.temperature_c,
                "run_error_count": err.count,
                "run_error_mean_ns": err.mean if err.count else None,
                "run_error_std_ns": err.std if err.count > 1 else None,
            }
        out["last"] = last
        return out
