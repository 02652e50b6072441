"""A run's statistics kept as its strokes are written, so reading them costs the same at 10^7 strokes
as at 10 (issue 36).

`RunAggregate` folds records in exactly as `stats.stats_of_records` does, in fixed memory: counts,
exact integer sums (so the mean and std are those of every stroke, not of a window) and extremes,
and the |error| and lateness quantiles through an HDR histogram. **Stated error:** a quantile is the
value of the stroke at that rank to within 0.1 % of it or 1 us, whichever is larger (3 significant
digits, 1 us the lowest discernible value); counts, mean, std and max are exact. It round-trips
through bytes (msgpack, the histograms HDR-encoded), for the records file's `run_aggregates` table.
"""

from __future__ import annotations

import weakref
from typing import Any

import msgpack
from hdrh.histogram import HdrHistogram

from .record import CycleRecord
from .stats import DirectionStats, Running, _rank

#: The sketch's bounds: 1 us discernible, up to an hour, 3 significant digits (0.1 %).
SKETCH_LOWEST_NS = 1_000
SKETCH_HIGHEST_NS = 3_600_000_000_000
SKETCH_DIGITS = 3
#: The quantile error the sketch guarantees, for docs and tests: max(0.1 % of the value, 1 us).
QUANTILE_RELATIVE_ERROR = 0.001
QUANTILE_ABSOLUTE_ERROR_NS = SKETCH_LOWEST_NS
_FORMAT = 1


class ExactRunning(Running):
    """`stats.Running` restored from the sums a run's aggregate keeps."""

    __slots__ = ()

    def __init__(
        self, count: int | str = 0, s: int | str = 0, ss: int | str = 0, max_abs: int | str = 0
    ) -> None:
        self.count, self.s, self.ss, self.max_abs = int(count), int(s), int(ss), int(max_abs)

    def state(self) -> list[int | str]:
        """The sums to keep; one past msgpack's 64 bits as its decimal text (the sum of squared
        operating times passes 2^64 at ~250,000 strokes: the writer thread died on it)."""
        return [
            v if -(1 << 63) <= v < (1 << 64) else str(v) for v in (self.count, self.s, self.ss, self.max_abs)
        ]


def _acyclic(hist: HdrHistogram) -> HdrHistogram:
    """`hist`, its encoder's reference back to it made weak. hdrh's histogram and its encoder refer
    to each other: a cycle only the collector frees, and the daemon runs with the collector off but
    for the young generations (daemon/loop.py), so every sketch a run's aggregates and reads made
    (~94 KB of counts each, six a run) stayed: the abuse bench's daemon grew 54 -> 380 MB over
    11,000 runs, 1,600 sketches alive after 500 estop/restart cycles. Refcounting frees it now."""
    hist.encoder.histogram = weakref.proxy(hist)
    return hist


class Sketch:
    """Quantiles of non-negative ns values in fixed memory (an HDR histogram)."""

    __slots__ = ("hist",)

    def __init__(self, encoded: bytes | None = None) -> None:
        self.hist = _acyclic(HdrHistogram(SKETCH_LOWEST_NS, SKETCH_HIGHEST_NS, SKETCH_DIGITS))
        if encoded:
            self.hist.add(_acyclic(HdrHistogram.decode(encoded, self.hist.b64_wrap)))

    def add(self, x: int) -> None:
        self.hist.record_value(min(max(x, 0), SKETCH_HIGHEST_NS))

    def quantiles(self, qs: tuple[float, ...]) -> list[int | None]:
        """Nearest-rank percentiles `qs` (0..100), as `stats.percentiles_of` takes them over every
        value (the value of rank ceil(q n / 100)), each within the sketch's error; None when empty.
        (HDR's own `get_value_at_percentile` rounds the rank, one stroke off in a short run's tail.)"""
        import numpy as np  # here, not at import: usmswitchctl imports this module without it

        hist = self.hist
        total = hist.get_total_count()
        if total == 0:
            return [None] * len(qs)
        # The counts' running sum in numpy: walking HDR's recorded iterator in Python cost ~30 ms
        # a sketch at 1,000 distinct values, and a run's end (six sketches) held up the record writer.
        running = np.cumsum(np.ctypeslib.as_array(hist.counts), dtype=np.int64)
        out: list[int | None] = []
        for index in np.searchsorted(running, [_rank(q, total) for q in qs], side="left"):
            v = hist.get_value_from_index(int(index))
            lo, hi = hist.get_lowest_equivalent_value(v), hist.get_highest_equivalent_value(v)
            out.append((lo + hi) // 2)  # the bucket's middle: within half its width
        return out

    def encode(self) -> bytes:
        return self.hist.encode() if self.hist.get_total_count() else b""

    def raw(self) -> bytes:
        """Nothing: a sketch keeps no values (`DirectionStats.snapshot` asks; the quantiles are ours)."""
        return b""


class DirectionAggregate(DirectionStats):
    """One direction's (or both's) figures: `DirectionStats` itself (its folding, so the two never
    differ), over exact sums and sketches instead of floats and windows, and as state to keep."""

    def __init__(self, state: dict[str, Any] | None = None) -> None:
        super().__init__(window=1)
        st = state or {}
        self.operating = ExactRunning(*st.get("operating", ()))  # type: ignore[assignment]
        self.total = ExactRunning(*st.get("total", ()))  # type: ignore[assignment]
        self.error = ExactRunning(*st.get("error", ()))  # type: ignore[assignment]
        self.lateness = ExactRunning()  # type: ignore[assignment]  # not reported: not kept
        self.abs_error = Sketch(st.get("abs_error"))  # type: ignore[assignment]
        self.abs_lateness = Sketch(st.get("abs_lateness"))  # type: ignore[assignment]
        self.max_abs_error_pct = float(st.get("max_abs_error_pct", 0.0))
        self.late, self.stalls, self.bounces, self.faults = st.get("counters", (0, 0, 0, 0))
        self.implausible = int(st.get("implausible", 0))
        self.mismatched = int(st.get("mismatched", 0))
        self.cut_short = int(st.get("cut_short", 0))  # absent from aggregates kept before it was counted
        self.commissioning = list(st.get("commissioning", ()))

    def snapshot(self, raw: bool = False) -> dict[str, Any]:
        """The figures in the shape of `DirectionStats.snapshot()`, the quantiles the sketches'."""
        out = super().snapshot(raw=True)
        for key in ("abs_error_raw", "abs_lateness_raw"):
            out.pop(key)
        p50, p95, p99 = self.abs_error.quantiles((50, 95, 99))  # type: ignore[attr-defined]
        out.update(abs_error_p50_ns=p50, abs_error_p95_ns=p95, abs_error_p99_ns=p99)
        l50, l99, l999, lmax = self.abs_lateness.quantiles((50, 99, 99.9, 100))  # type: ignore[attr-defined]
        out.update(lateness_p50_ns=l50, lateness_p99_ns=l99, lateness_p99_9_ns=l999, lateness_max_ns=lmax)
        return out

    def state(self) -> dict[str, Any]:
        return {
            "operating": self.operating.state(),  # type: ignore[attr-defined]
            "total": self.total.state(),  # type: ignore[attr-defined]
            "error": self.error.state(),  # type: ignore[attr-defined]
            "abs_error": self.abs_error.encode(),  # type: ignore[attr-defined]
            "abs_lateness": self.abs_lateness.encode(),  # type: ignore[attr-defined]
            "max_abs_error_pct": self.max_abs_error_pct,
            "counters": [self.late, self.stalls, self.bounces, self.faults],
            "implausible": self.implausible,
            "mismatched": self.mismatched,
            "cut_short": self.cut_short,
            "commissioning": self.commissioning,
        }


class RunAggregate:
    """A run's statistics per direction (on, off) and both, with the cycles they cover."""

    def __init__(self, data: bytes | None = None) -> None:
        st: dict[str, Any] = msgpack.unpackb(data, raw=False) if data else {}
        if st and st.get("format") != _FORMAT:
            raise ValueError(f"run aggregate format {st.get('format')!r}, this reads {_FORMAT}")
        dirs = st.get("dirs", [None, None, None])
        self.per = [DirectionAggregate(dirs[0]), DirectionAggregate(dirs[1])]
        self.both = DirectionAggregate(dirs[2])
        self.first_cycle: int | None = st.get("first_cycle")
        self.last_cycle: int | None = st.get("last_cycle")
        self.records = int(st.get("records", 0))

    def add(self, rec: CycleRecord) -> None:
        """Fold one stroke in (records of a run come in cycle order)."""
        self.per[rec.direction].add_record(rec)
        self.both.add_record(rec)
        if self.first_cycle is None:
            self.first_cycle = rec.cycle
        self.last_cycle = rec.cycle
        self.records += 1

    def to_bytes(self) -> bytes:
        state = {
            "format": _FORMAT,
            "dirs": [self.per[0].state(), self.per[1].state(), self.both.state()],
            "first_cycle": self.first_cycle,
            "last_cycle": self.last_cycle,
            "records": self.records,
        }
        return msgpack.packb(state, use_bin_type=True)
