"""Running statistics of strokes per direction, in fixed memory, for the socket and the summary log.

The loop calls `add` in its slack (after the next stroke is armed); readers take `snapshot()`,
a plain dict of integers and floats, from any thread.
"""

from __future__ import annotations

import math
from array import array

# |error| and lateness percentiles are taken over the most recent strokes only, in fixed memory.
PERCENTILE_WINDOW = 4096


class Running:
    """Count, mean, std (Welford) and max |x| of a stream of integer ns values."""

    __slots__ = ("count", "m2", "max_abs", "mean")

    def __init__(self) -> None:
        self.count = 0
        self.mean = 0.0
        self.m2 = 0.0
        self.max_abs = 0

    def add(self, x: int) -> None:
        self.count += 1
        d = x - self.mean
        self.mean += d / self.count
        self.m2 += d * (x - self.mean)
        if abs(x) > self.max_abs:
            self.max_abs = abs(x)

    @property
    def std(self) -> float:
        return math.sqrt(self.m2 / (self.count - 1)) if self.count > 1 else 0.0

    def as_dict(self, prefix: str) -> dict[str, float | int]:
        return {
            f"{prefix}_mean_ns": round(self.mean, 1),
            f"{prefix}_std_ns": round(self.std, 1),
            f"{prefix}_max_abs_ns": self.max_abs,
        }


class Ring:
    """The last `size` integer values, for percentiles without growth."""

    __slots__ = ("buf", "n", "size")

    def __init__(self, size: int = PERCENTILE_WINDOW) -> None:
        self.size = size
        self.buf = array("q", bytes(8 * size))
        self.n = 0

    def add(self, x: int) -> None:
        self.buf[self.n % self.size] = x
        self.n += 1

    def values(self) -> list[int]:
        return sorted(self.buf[: min(self.n, self.size)])


def percentile(sorted_values: list[int], q: float) -> int | None:
    """Nearest-rank percentile (q in 0..100) of an already sorted list; None when empty."""
    if not sorted_values:
        return None
    k = max(0, min(len(sorted_values) - 1, math.ceil(q / 100 * len(sorted_values)) - 1))
    return sorted_values[k]


class DirectionStats:
    """Everything the stats call reports for one direction."""

    def __init__(self) -> None:
        self.operating = Running()
        self.total = Running()
        self.error = Running()
        self.lateness = Running()
        self.abs_error = Ring()
        self.abs_lateness = Ring()
        self.max_abs_error_pct = 0.0
        self.late = 0
        self.stalls = 0
        self.bounces = 0
        self.faults = 0

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

    def snapshot(self) -> dict[str, object]:
        """A plain-typed dict of this direction's figures (integers are ns)."""
        errs = self.abs_error.values()
        lates = self.abs_lateness.values()
        out: dict[str, object] = {"count": self.operating.count, "strokes": self.error.count + self.stalls}
        out.update(self.operating.as_dict("operating"))
        out.update(self.total.as_dict("total"))
        out.update(self.error.as_dict("error"))
        out["max_abs_error_pct"] = round(self.max_abs_error_pct, 4)
        for q in (50, 95, 99):
            out[f"abs_error_p{q}_ns"] = percentile(errs, q)
        for q in (50, 99, 99.9):
            out[f"lateness_p{q:g}_ns".replace(".", "_")] = percentile(lates, q)
        out["lateness_max_ns"] = lates[-1] if lates else None
        out.update(late=self.late, stalls=self.stalls, bounces=self.bounces, faults=self.faults)
        return out


def combine(a: DirectionStats, b: DirectionStats) -> DirectionStats:
    """Both directions as one (merged moments, merged recent windows)."""
    out = DirectionStats()
    for name in ("operating", "total", "error", "lateness"):
        ra, rb, r = getattr(a, name), getattr(b, name), getattr(out, name)
        r.count = ra.count + rb.count
        if r.count:
            r.mean = (ra.mean * ra.count + rb.mean * rb.count) / r.count
            r.m2 = ra.m2 + rb.m2 + (rb.mean - ra.mean) ** 2 * ra.count * rb.count / r.count
        r.max_abs = max(ra.max_abs, rb.max_abs)
    for ring in ("abs_error", "abs_lateness"):
        for src in (a, b):
            for v in getattr(src, ring).buf[: min(getattr(src, ring).n, getattr(src, ring).size)]:
                getattr(out, ring).add(v)
    out.max_abs_error_pct = max(a.max_abs_error_pct, b.max_abs_error_pct)
    for name in ("late", "stalls", "bounces", "faults"):
        setattr(out, name, getattr(a, name) + getattr(b, name))
    return out
