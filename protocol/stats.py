"""Running statistics of strokes per direction, in fixed memory, for the socket and the summary log.

The loop calls `add` in its slack (after the next stroke is armed); readers take `snapshot()`,
a plain dict of integers and floats, from any thread. Percentiles cost a millisecond or more (a
sort of 4096 values, several times): the daemon takes `snapshot(raw=True)`, which carries the
percentile windows as bytes, and the socket's server process `finish`es it, off the loop.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterable
from fractions import Fraction
from typing import Any

from .record import CycleRecord, Flag, RunRecord

# |error| and lateness percentiles are taken over the most recent strokes only, in fixed memory.
PERCENTILE_WINDOW = 4096
# Commissioning strokes listed apart per direction (a rig has one per direction in its life).
COMMISSIONING_KEPT = 8


class Running:
    """Count, mean, std and max |x| of a stream of integer ns values, from exact integer sums: the
    figures of every value, the same however they are split or merged (a run's kept aggregate,
    `aggregate.ExactRunning`, rounds to what a live run says; Welford's floats rounded a mean of
    an exact half the other way)."""

    __slots__ = ("count", "max_abs", "s", "ss")

    def __init__(self) -> None:
        self.count = self.s = self.ss = self.max_abs = 0

    def add(self, x: int) -> None:
        self.count += 1
        self.s += x
        self.ss += x * x
        if abs(x) > self.max_abs:
            self.max_abs = abs(x)

    @property
    def mean(self) -> float:
        return self.s / self.count if self.count else 0.0

    @property
    def std(self) -> float:
        n = self.count
        if n < 2:
            return 0.0
        return math.sqrt((n * self.ss - self.s * self.s) / (n * (n - 1)))

    def as_dict(self, prefix: str) -> dict[str, float | int]:
        return {
            f"{prefix}_mean_ns": round(self.mean, 1),
            f"{prefix}_std_ns": round(self.std, 1),
            f"{prefix}_max_abs_ns": self.max_abs,
        }


class Ring:
    """The last `size` integer values, for percentiles without growth (size 0: every value, for
    statistics of a finished run read from the records, where the percentiles must be exact)."""

    __slots__ = ("buf", "n", "size")

    def __init__(self, size: int = PERCENTILE_WINDOW) -> None:
        self.size = size
        self.buf = array("q", bytes(8 * size))
        self.n = 0

    def add(self, x: int) -> None:
        if self.size:
            self.buf[self.n % self.size] = x
        else:
            self.buf.append(x)
        self.n += 1

    def raw(self) -> bytes:
        """The values held, as native int64 bytes (any order): what `percentiles_of` takes."""
        return self.buf[: min(self.n, self.size or self.n)].tobytes()

    def percentiles(self, qs: tuple[float, ...]) -> list[int | None]:
        """Nearest-rank percentiles (q in 0..100) of the values held; None when empty."""
        return percentiles_of(self.raw(), qs)


def percentiles_of(raw: bytes, qs: tuple[float, ...]) -> list[int | None]:
    """Nearest-rank percentiles (q in 0..100) of int64 values packed in `raw`; None when empty."""
    if not raw:
        return [None] * len(qs)
    import numpy as np  # here, not at import: usmswitchctl uses Running without it

    values = np.sort(np.frombuffer(raw, dtype=np.int64))
    # The rank in exact arithmetic: numpy's float rank is one off at some boundaries (99.9 % of
    # 51,000 strokes read rank 50,950 for 50,949), and in a tail adjacent strokes differ by far.
    return [int(values[_rank(q, len(values)) - 1]) for q in qs]


def _rank(q: float, n: int) -> int:
    """The nearest rank of percentile `q` (0..100) among `n` values: ceil(q n / 100), at least 1."""
    f = Fraction(str(q)) * n / 100
    return min(n, max(1, math.ceil(f)))


_ERROR_QS = (50, 95, 99)
_LATENESS_QS = (50, 99, 99.9, 100)
_RAW_KEYS = ("abs_error_raw", "abs_lateness_raw")
_NOT_A_STROKE = int(Flag.IMPLAUSIBLE | Flag.MISMATCH)
_IMPLAUSIBLE, _FAULT, _COMMISSIONING = int(Flag.IMPLAUSIBLE), int(Flag.FAULT), int(Flag.COMMISSIONING)
_LATE, _STALL, _BOUNCE = int(Flag.LATE), int(Flag.STALL), int(Flag.BOUNCE)


def finish_direction(out: dict[str, object]) -> dict[str, object]:
    """Replace a raw direction snapshot's percentile windows by the percentiles (in place)."""
    if "abs_error_raw" in out:
        p50, p95, p99 = percentiles_of(out.pop("abs_error_raw"), _ERROR_QS)  # type: ignore[arg-type]
        out.update(abs_error_p50_ns=p50, abs_error_p95_ns=p95, abs_error_p99_ns=p99)
    if "abs_lateness_raw" in out:
        l50, l99, l999, lmax = percentiles_of(out.pop("abs_lateness_raw"), _LATENESS_QS)  # type: ignore[arg-type]
        out.update(lateness_p50_ns=l50, lateness_p99_ns=l99, lateness_p99_9_ns=l999, lateness_max_ns=lmax)
    return out


def finish_snapshot(snapshot: dict[str, object]) -> dict[str, object]:
    """A loop's raw stats snapshot made whole: every direction's percentiles computed (in place)."""
    for value in snapshot.values():
        if isinstance(value, dict) and any(k in value for k in _RAW_KEYS):
            finish_direction(value)
    return snapshot


class DirectionStats:
    """Everything the stats call reports for one direction."""

    def __init__(self, window: int = PERCENTILE_WINDOW) -> None:
        self.operating = Running()
        self.total = Running()
        self.error = Running()
        self.lateness = Running()
        self.abs_error = Ring(window)
        self.abs_lateness = Ring(window)
        self.max_abs_error_pct = 0.0
        self.late = 0
        self.stalls = 0
        self.bounces = 0
        self.faults = 0
        # Commissioning strokes (a first stroke predicted from nothing known): apart, never in
        # the error figures. At most two a rig's life, so a short list is fixed memory enough.
        self.commissioning: list[dict[str, int | None]] = []
        self.implausible = 0  # strokes the hardware side reported that were not strokes
        self.mismatched = 0  # strokes whose stamps the device's own account did not bear out
        # Strokes ended before an arrival by an estop, a fault or the daemon's stop, not a stall: in
        # the run's cycles as every stroke is, so `strokes` counts what `runs` counts.
        self.cut_short = 0

    def add(
        self,
        *,
        operating_ns: int | None,
        total_ns: int | None,
        error_ns: int | None,
        target_ns: int,
        lateness_ns: int | None,
        late: bool,
        stall: bool,
        bounce: bool,
        fault: bool,
    ) -> None:
        """Fold one stroke in; completed strokes feed the timing statistics, all feed the counters."""
        if operating_ns is not None:
            self.operating.add(operating_ns)
        if total_ns is not None:
            self.total.add(total_ns)
        if error_ns is not None:
            self.error.add(error_ns)
            self.abs_error.add(abs(error_ns))
            if target_ns > 0:
                self.max_abs_error_pct = max(self.max_abs_error_pct, 100.0 * abs(error_ns) / target_ns)
        if lateness_ns is not None:
            self.lateness.add(lateness_ns)
            self.abs_lateness.add(lateness_ns)
        self.late += late
        self.stalls += stall
        self.bounces += bounce
        self.faults += fault

    def add_record(self, rec: CycleRecord) -> None:
        """Fold one stroke's record in (what the loop and a read of the records file both do).

        A commissioning stroke feeds the operating time and the counters; its error is kept apart.
        The flags are tested as a plain int: an IntFlag's `&` builds an enum member each time, and
        this runs four times a stroke on the loop and twice on the record writer."""
        flags = int(rec.flags)
        if flags & _NOT_A_STROKE:
            # Not a stroke, or one whose stamps the device does not bear out: counted apart, none of
            # its times believed.
            if flags & _IMPLAUSIBLE:
                self.implausible += 1
            else:
                self.mismatched += 1
            self.faults += bool(flags & _FAULT)
            return
        commissioning = bool(flags & _COMMISSIONING) and rec.error_ns is not None
        if commissioning and len(self.commissioning) < COMMISSIONING_KEPT:
            self.commissioning.append(
                {
                    "cycle": rec.cycle,
                    "direction": rec.direction,
                    "error_ns": rec.error_ns,
                    "t_hat_ns": rec.t_hat_ns,
                }
            )
        operating = rec.operating_ns
        if operating is not None:
            self.operating.add(operating)
        if not commissioning:
            total, error = rec.total_ns, rec.error_ns
            if total is not None:
                self.total.add(total)
            if error is not None:
                self.error.add(error)
                a = -error if error < 0 else error
                self.abs_error.add(a)
                target = rec.target_ns
                if target > 0:
                    pct = 100.0 * a / target
                    if pct > self.max_abs_error_pct:
                        self.max_abs_error_pct = pct
            self.stalls += bool(flags & _STALL)
            self.cut_short += rec.error_ns is None and not flags & _STALL
        lateness = rec.lateness_ns
        if lateness is not None:
            self.lateness.add(lateness)
            self.abs_lateness.add(lateness)
        self.late += bool(flags & _LATE)
        self.bounces += bool(flags & _BOUNCE)
        self.faults += bool(flags & _FAULT)

    def snapshot(self, raw: bool = False) -> dict[str, object]:
        """A plain-typed dict of this direction's figures (integers are ns).

        `raw=True` leaves the percentiles to `finish_direction`: the windows travel as bytes.
        """
        strokes = (
            self.error.count
            + self.stalls
            + self.cut_short
            + len(self.commissioning)
            + self.implausible
            + self.mismatched
        )
        out: dict[str, object] = {"count": self.operating.count, "strokes": strokes}
        out.update(self.operating.as_dict("operating"))
        out.update(self.total.as_dict("total"))
        out.update(self.error.as_dict("error"))
        out["max_abs_error_pct"] = round(self.max_abs_error_pct, 4)
        out["abs_error_raw"] = self.abs_error.raw()
        out["abs_lateness_raw"] = self.abs_lateness.raw()
        out.update(late=self.late, stalls=self.stalls, bounces=self.bounces, faults=self.faults)
        out["commissioning"] = list(self.commissioning)
        out["implausible"] = self.implausible
        out["mismatched"] = self.mismatched
        out["cut_short"] = self.cut_short
        return out if raw else finish_direction(out)


def stats_of_records(records: Iterable[CycleRecord], run: RunRecord | None = None) -> dict[str, Any]:
    """The statistics of stored strokes (a past run, a range of cycles) in the shape of the
    daemon's `stats` reply: `on`, `off` and `all` with exact percentiles over every stroke, each
    direction's model as its last stroke used it, the run and the cycles covered."""
    per = (DirectionStats(window=0), DirectionStats(window=0))
    both = DirectionStats(window=0)
    last: list[CycleRecord | None] = [None, None]
    first_cycle = last_cycle = None
    for rec in records:
        per[rec.direction].add_record(rec)
        both.add_record(rec)
        last[rec.direction] = rec
        if first_cycle is None:
            first_cycle = rec.cycle
        last_cycle = rec.cycle
    out: dict[str, Any] = {
        "run": None if run is None else run.to_dict(),
        "first_cycle": first_cycle,
        "last_cycle": last_cycle,
        "all": both.snapshot(),
    }
    for d, name in ((0, "on"), (1, "off")):
        out[name] = {**per[d].snapshot(), **model_of(last[d])}
    return out


def model_of(rec: CycleRecord | None) -> dict[str, Any]:
    """A direction's model as its last stroke (`rec`, None: none) used it, for a stats reply."""
    return {
        "order": None if rec is None else rec.order,
        "coefficients": [] if rec is None else list(rec.coefficients),
        "ready": rec is not None and not rec.flags & Flag.WARMUP,
        "target_ns": None if rec is None else rec.target_ns,
    }
