"""One stroke's record: what was asked, what was predicted, what the sensors stamped, what went wrong.

The loop builds one `CycleRecord` per stroke (`CycleRecord.build` derives the durations from the
stamps, in one place); the record store, the socket and the CSV export all read the same fields.
Every time is integer nanoseconds on the driver's clock, except `wall_ns` (time.time_ns(), for people).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from enum import IntFlag
from typing import Any


class Flag(IntFlag):
    """What went wrong in a stroke (a bit mask; 0 = a clean stroke)."""

    # The motor started more than `control.late_margin` after command + delay (host-timed
    # lateness), or the delay was clamped (see CLAMPED): the total will exceed the target.
    LATE = 1 << 0
    # T_d = T - t_hat came out negative (target shorter than the predicted stroke) and was
    # clamped to 0. Always set together with LATE.
    CLAMPED = 1 << 1
    # No arrival within `control.stroke_timeout`: the drive was stopped and FAULT latched.
    STALL = 1 << 2
    # The debouncer dropped sensor edges during this stroke (the stroke itself still counts).
    BOUNCE = 1 << 3
    # The driver reported a fault during the stroke (disconnect, wire, sequence, drive board).
    FAULT = 1 << 4
    # The stroke was cut short by an emergency stop.
    ESTOP = 1 << 5
    # The predictor was still cold (fewer strokes than it needs): t_hat was the configured nominal.
    WARMUP = 1 << 6
    # The stroke was cut short or never started because the daemon was shutting down (SIGTERM,
    # SIGINT, SIGHUP): not a stall, not a fault of the rig.
    ABORTED = 1 << 7
    # The mover did not start from the source sensor (an estop or a fault had stopped it midway):
    # a part of a stroke, recorded but not fed to the predictor.
    PARTIAL = 1 << 8


#: Flags after which `operating_ns` is not a real stroke time (the predictor must not learn it).
UNUSABLE = Flag.STALL | Flag.FAULT | Flag.ESTOP | Flag.ABORTED | Flag.PARTIAL

MODES = ("closed", "open")


@dataclass(slots=True)
class CycleRecord:
    """One stroke. Treat as immutable once submitted (not frozen: building one is on the loop)."""

    cycle: int  # global stroke number, 1-based, continues across restarts
    direction: int  # 0 = on (A -> B), 1 = off (B -> A)
    mode: str  # "closed" (T_d = T - t_hat) or "open" (fixed delay)
    target_ns: int  # T: the wanted command-to-arrival time
    order: int  # AR model order m used for t_hat
    coefficients: tuple[float, ...]  # the AR coefficients used (with the intercept first for "centered")
    t_hat_ns: int  # predicted operating time, rounded to ns
    delay_ns: int  # T_d armed for this stroke (>= 0)
    t_cmd_ns: int  # command instant
    t_start_ns: int | None  # motor start instant (None: the device never reported one)
    t_depart_ns: int | None  # the source sensor released (None: edge missed)
    t_arrive_ns: int | None  # the destination sensor reached (None: stall, estop)
    operating_ns: int | None  # arrive - start: the stroke's operating time t
    total_ns: int | None  # arrive - cmd: what the user sees, should equal target
    error_ns: int | None  # total - target
    dead_ns: int | None  # depart - start: the motor's start dead time
    lateness_ns: int | None  # start - (cmd + delay); host-timed strokes only
    temperature_c: float | None  # motor temperature when known
    frequency_hz: float | None  # drive excitation frequency when known
    flags: int  # Flag bits
    wall_ns: int  # time.time_ns() at arrival (or at the stroke's end), for people
    # Where the stroke came from. The loop leaves them None; the record store stamps its own
    # (the daemon's driver name and rig identity) at submit, so every stored row says its source.
    driver: str | None = None  # "sim", "serial", "usb" (None: unknown, e.g. a schema 1 row)
    rig: str | None = None  # [daemon] rig, by default the host name

    @classmethod
    def build(
        cls,
        *,
        cycle: int,
        direction: int,
        mode: str,
        target_ns: int,
        order: int,
        coefficients: Sequence[float],
        t_hat_ns: int,
        delay_ns: int,
        t_cmd_ns: int,
        t_start_ns: int | None,
        t_depart_ns: int | None,
        t_arrive_ns: int | None,
        lateness_ns: int | None = None,
        temperature_c: float | None = None,
        frequency_hz: float | None = None,
        flags: int = 0,
        wall_ns: int,
        driver: str | None = None,
        rig: str | None = None,
    ) -> CycleRecord:
        """Make a record from the stamps, deriving operating, total, error and dead time in one place."""
        operating = total = error = dead = None
        if t_arrive_ns is not None:
            total = t_arrive_ns - t_cmd_ns
            error = total - target_ns
            if t_start_ns is not None:
                operating = t_arrive_ns - t_start_ns
        if t_depart_ns is not None and t_start_ns is not None:
            dead = t_depart_ns - t_start_ns
        return cls(
            cycle=cycle,
            direction=int(direction),
            mode=mode,
            target_ns=target_ns,
            order=order,
            coefficients=tuple(coefficients),
            t_hat_ns=t_hat_ns,
            delay_ns=delay_ns,
            t_cmd_ns=t_cmd_ns,
            t_start_ns=t_start_ns,
            t_depart_ns=t_depart_ns,
            t_arrive_ns=t_arrive_ns,
            operating_ns=operating,
            total_ns=total,
            error_ns=error,
            dead_ns=dead,
            lateness_ns=lateness_ns,
            temperature_c=temperature_c,
            frequency_hz=frequency_hz,
            flags=int(flags),
            wall_ns=wall_ns,
            driver=driver,
            rig=rig,
        )

    def to_dict(self) -> dict[str, Any]:
        """The record as plain types (ints, floats, str, None, a list) for msgpack, JSON and CSV."""
        d = {name: getattr(self, name) for name in FIELDS}
        d["coefficients"] = [float(c) for c in self.coefficients]
        d["flags"] = int(self.flags)
        return d

    def to_row(self) -> tuple[Any, ...]:
        """The record in `FIELDS` order with the coefficients as JSON text: one SQLite row."""
        return (
            self.cycle,
            self.direction,
            self.mode,
            self.target_ns,
            self.order,
            json.dumps([float(c) for c in self.coefficients]),
            self.t_hat_ns,
            self.delay_ns,
            self.t_cmd_ns,
            self.t_start_ns,
            self.t_depart_ns,
            self.t_arrive_ns,
            self.operating_ns,
            self.total_ns,
            self.error_ns,
            self.dead_ns,
            self.lateness_ns,
            self.temperature_c,
            self.frequency_hz,
            int(self.flags),
            self.wall_ns,
            self.driver,
            self.rig,
        )

    @classmethod
    def from_row(cls, row: Mapping[str, Any] | Sequence[Any]) -> CycleRecord:
        """Rebuild a record from `to_dict()`, `to_row()`, a sqlite3.Row or a CSV row (all text).

        `driver` and `rig` may be missing (a row or CSV from before they existed): they read as None.
        """
        if isinstance(row, Mapping) or hasattr(row, "keys"):
            keys = set(row.keys())
            missing = [f for f in FIELDS if f not in keys and f not in SOURCE_FIELDS]
            if missing:
                raise ValueError(f"cycle record row lacks field(s) {', '.join(missing)}")
            values = [row[f] if f in keys else None for f in FIELDS]
        else:
            values = list(row)
            if len(values) == len(FIELDS) - len(SOURCE_FIELDS):
                values += [None] * len(SOURCE_FIELDS)
            if len(values) != len(FIELDS):
                raise ValueError(f"cycle record row has {len(values)} values, expected {len(FIELDS)}")
        kwargs = {}
        for name, value in zip(FIELDS, values, strict=True):
            kwargs[name] = _convert(name, value)
        return cls(**kwargs)


FIELDS: tuple[str, ...] = tuple(f.name for f in fields(CycleRecord))
#: The fields that say where a record came from (schema 2); absent from older rows and exports.
SOURCE_FIELDS: tuple[str, ...] = ("driver", "rig")


def _to_int(value: Any) -> int:
    if isinstance(value, bool | float):
        raise ValueError("expected an integer")
    return int(value)


def _opt_int(value: Any) -> int | None:
    return None if value is None or value == "" else _to_int(value)


def _opt_str(value: Any) -> str | None:
    if value is None or value == "":
        return None
    if not isinstance(value, str):
        raise ValueError("expected text")
    return value


def _opt_float(value: Any) -> float | None:
    return None if value is None or value == "" else float(value)


def _mode(value: Any) -> str:
    if value not in MODES:
        raise ValueError(f"not one of {MODES}")
    return value


def _coefficients(value: Any) -> tuple[float, ...]:
    if isinstance(value, str):
        value = json.loads(value)
    return tuple(float(c) for c in value)


_CONVERT = (
    {name: _to_int for name in FIELDS}
    | {
        "mode": _mode,
        "coefficients": _coefficients,
        "temperature_c": _opt_float,
        "frequency_hz": _opt_float,
        "driver": _opt_str,
        "rig": _opt_str,
    }
    | {
        name: _opt_int
        for name in (
            "t_start_ns",
            "t_depart_ns",
            "t_arrive_ns",
            "operating_ns",
            "total_ns",
            "error_ns",
            "dead_ns",
            "lateness_ns",
        )
    }
)


def _convert(name: str, value: Any) -> Any:
    """One field from a stored or exported form back to its Python type; a bad value names the field."""
    try:
        return _CONVERT[name](value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"cycle record field {name}={value!r}: {exc}") from None
