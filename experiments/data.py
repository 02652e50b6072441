"""A run's strokes as numpy columns, from wherever they came: the in-process rig, a live daemon, a
records file. Every experiment reads `Strokes`; none cares where the strokes were made.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from usmswitch.protocol.record import UNUSABLE, Flag

#: The record fields an experiment reads (the rest stay in the records file).
COLUMNS = (
    "cycle",
    "direction",
    "target_ns",
    "t_hat_ns",
    "delay_ns",
    "operating_ns",
    "total_ns",
    "error_ns",
    "flags",
    "temperature_c",
    "frequency_hz",
    "lateness_ns",
)


@dataclass(frozen=True)
class Strokes:
    """One run's strokes, oldest first; a missing time (a stall) is NaN in its column."""

    cycle: np.ndarray
    direction: np.ndarray
    target_ns: np.ndarray
    t_hat_ns: np.ndarray
    delay_ns: np.ndarray
    operating_ns: np.ndarray
    total_ns: np.ndarray
    error_ns: np.ndarray
    flags: np.ndarray
    temperature_c: np.ndarray
    frequency_hz: np.ndarray
    lateness_ns: np.ndarray
    run_id: int | None = None
    #: The run's record (settings: model, order, mode, ...) when read from the records.
    run: Mapping[str, Any] | None = None

    @classmethod
    def from_records(cls, records: Iterable[Mapping[str, Any]], run_id: int | None = None) -> Strokes:
        """From CycleRecord dicts (a subscription, `history`, a records file)."""
        cols: dict[str, list[Any]] = {c: [] for c in COLUMNS}
        for rec in records:
            for c in COLUMNS:
                cols[c].append(rec[c])
        return cls(**{c: _array(c, v) for c, v in cols.items()}, run_id=run_id)

    def __len__(self) -> int:
        return len(self.cycle)

    def of(self, direction: int) -> Strokes:
        """The strokes of one direction (0 on, 1 off)."""
        keep = self.direction == direction
        return Strokes(**{c: getattr(self, c)[keep] for c in COLUMNS}, run_id=self.run_id)

    @property
    def late(self) -> int:
        return int(np.count_nonzero(self.flags & int(Flag.LATE)))

    @property
    def stalls(self) -> int:
        return int(np.count_nonzero(self.flags & int(Flag.STALL)))

    @property
    def failed(self) -> int:
        """Strokes that did not complete (stall, fault, estop, aborted, partial)."""
        return int(np.count_nonzero(self.flags & int(UNUSABLE)))

    @property
    def arrived(self) -> int:
        return int(np.count_nonzero(~np.isnan(self.operating_ns)))

    def settled(self, skip: int) -> Strokes:
        """Without the first `skip` strokes of each direction (the predictor's cold start)."""
        keep = np.ones(len(self), dtype=bool)
        for d in (0, 1):
            idx = np.flatnonzero(self.direction == d)[:skip]
            keep[idx] = False
        return Strokes(**{c: getattr(self, c)[keep] for c in COLUMNS}, run_id=self.run_id)


def _array(column: str, values: list[Any]) -> np.ndarray:
    if column in ("cycle", "direction", "flags", "target_ns", "t_hat_ns", "delay_ns"):
        return np.asarray(values, dtype=np.int64)
    return np.asarray([np.nan if v is None else v for v in values], dtype=np.float64)


def describe_ns(values: np.ndarray) -> dict[str, float | int | None]:
    """Mean, sample std, min, max and max |x| of ns values (NaN dropped), as plain numbers."""
    v = values[~np.isnan(values)] if values.dtype.kind == "f" else values
    if len(v) == 0:
        return {"n": 0, "mean_ns": None, "std_ns": None, "min_ns": None, "max_ns": None, "max_abs_ns": None}
    return {
        "n": len(v),
        "mean_ns": round(float(np.mean(v)), 1),
        "std_ns": round(float(np.std(v, ddof=1)), 1) if len(v) > 1 else 0.0,
        "min_ns": int(np.min(v)),
        "max_ns": int(np.max(v)),
        "max_abs_ns": int(np.max(np.abs(v))),
    }
