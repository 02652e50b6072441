"""One stroke's record: what was asked, what was predicted, what the sensors stamped, what went wrong.

The loop builds one `CycleRecord` per stroke (`CycleRecord.build` derives the durations from the
stamps, in one place); the record store, the socket and the CSV export all read the same fields.
Every time is integer nanoseconds on the driver's clock, except `wall_ns` (time.time_ns(), for people).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
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
    # A direction's first stroke on a rig nothing was known of (no records, no configured nominal,
    # no model of the rig): t_hat was a guess. Its error is shown apart in the statistics.
    COMMISSIONING = 1 << 9
    # The hardware side reported something that is not physically a stroke: an arrival with no
    # departure before it, a departure after the arrival, an operating time below the plausible
    # band. Kept with its stamps, never fed to the predictor; the fault it latches says which.
    IMPLAUSIBLE = 1 << 10
    # The device's own account of the stroke (its STROKE report, its sensor levels, the instant the
    # host commanded) disagrees with the stamps on the wire: kept with its stamps, never fed to the
    # predictor, counted in `status.mismatched_strokes`; the log line says what disagreed.
    MISMATCH = 1 << 11
    # Sensor edges the stroke does not explain (chatter, a spurious edge) came during it; counted
    # per sensor in `status.noise`. The stroke's stamps still count when nothing else is wrong.
    NOISE = 1 << 12


#: Flags after which `operating_ns` is not a real stroke time (the predictor must not learn it).
UNUSABLE = (
    Flag.STALL | Flag.FAULT | Flag.ESTOP | Flag.ABORTED | Flag.PARTIAL | Flag.IMPLAUSIBLE | Flag.MISMATCH
)

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
    run_id: int | None = None  # the run this stroke belongs to (None: a stroke outside any run)

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
        run_id: int | None = None,
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
            run_id=run_id,
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
            self.run_id,
        )

    @classmethod
    def from_row(cls, row: Mapping[str, Any] | Sequence[Any]) -> CycleRecord:
        """Rebuild a record from `to_dict()`, `to_row()`, a sqlite3.Row or a CSV row (all text).

        The fields added since schema 1 (`driver`, `rig`, `run_id`) may be missing (a row or CSV
        from before they existed): they read as None.
        """
        if isinstance(row, Mapping) or hasattr(row, "keys"):
            keys = set(row.keys())
            missing = [f for f in FIELDS if f not in keys and f not in LATER_FIELDS]
            if missing:
                raise ValueError(f"cycle record row lacks field(s) {', '.join(missing)}")
            values = [row[f] if f in keys else None for f in FIELDS]
        else:
            values = list(row)
            for n_later in (len(LATER_FIELDS), 1):  # schema 1 rows, then schema 2 rows
                if len(values) == len(FIELDS) - n_later:
                    values += [None] * n_later
            if len(values) != len(FIELDS):
                raise ValueError(f"cycle record row has {len(values)} values, expected {len(FIELDS)}")
        kwargs = {}
        for name, value in zip(FIELDS, values, strict=True):
            kwargs[name] = _convert(name, value)
        return cls(**kwargs)


FIELDS: tuple[str, ...] = tuple(f.name for f in fields(CycleRecord))
#: The fields that say where a record came from (schema 2); absent from older rows and exports.
SOURCE_FIELDS: tuple[str, ...] = ("driver", "rig")
#: Fields that older rows and exports lack: the source (schema 2) and the run (schema 3).
LATER_FIELDS: tuple[str, ...] = (*SOURCE_FIELDS, "run_id")


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
            "run_id",
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


RUN_KINDS = ("cycling", "experiment")


@dataclass(slots=True)
class RunRecord:
    """One run: a `start_cycling` (or an experiment) from its first stroke to its last.

    Written when it opens (`last_cycle`, `ended_wall_ns` and `end_reason` None) and again when it
    ends. Its strokes are the cycles first_cycle..last_cycle that carry its `run_id`.
    """

    run_id: int
    kind: str  # "cycling" or "experiment"
    first_cycle: int  # the number its first stroke got (or would have got)
    started_wall_ns: int  # time.time_ns() at the open, for people
    settings: dict[str, Any] = field(default_factory=dict)  # period_ns, count, targets, mode, model ...
    last_cycle: int | None = None  # None while running; first_cycle - 1 for a run without strokes
    ended_wall_ns: int | None = None
    end_reason: str | None = None  # "done" (count reached), "stopped", "fault: ...", "shutdown"
    driver: str | None = None
    rig: str | None = None
    label: str | None = None  # what the run is for, short (check_label): filtered on, indexed
    notes: str | None = None  # free text, editable after the run (check_notes)

    @property
    def running(self) -> bool:
        return self.end_reason is None

    @property
    def strokes(self) -> int | None:
        """How many strokes the run has (None while it runs)."""
        return None if self.last_cycle is None else self.last_cycle - self.first_cycle + 1

    def to_dict(self) -> dict[str, Any]:
        """Plain types for msgpack and JSON."""
        d = {name: getattr(self, name) for name in RUN_FIELDS}
        d["settings"] = dict(self.settings)
        return d

    def to_row(self) -> tuple[Any, ...]:
        """In `RUN_FIELDS` order with the settings as JSON text: one SQLite row."""
        return tuple(
            json.dumps(self.settings, sort_keys=True) if name == "settings" else getattr(self, name)
            for name in RUN_FIELDS
        )

    @classmethod
    def from_row(cls, row: Mapping[str, Any] | Any) -> RunRecord:
        """From `to_dict()` or a sqlite3.Row; `label` and `notes` may be missing (a file or a
        database from before them): None."""
        keys = set(row.keys())
        missing = [f for f in RUN_FIELDS if f not in keys and f not in LATER_RUN_FIELDS]
        if missing:
            raise ValueError(f"run row lacks field(s) {', '.join(missing)}")
        values = {name: row[name] for name in RUN_FIELDS if name in keys}
        if isinstance(values["settings"], str):
            values["settings"] = json.loads(values["settings"])
        return cls(**values)


RUN_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(RunRecord))
#: Run fields that older files and databases lack (added to schema 3 without a new version).
LATER_RUN_FIELDS: tuple[str, ...] = ("label", "notes")

#: A label: a short word of letters, digits and `_ . : / + -`, starting with a letter or digit (no
#: spaces: it is typed on command lines, `usmswitchctl runs --label X`, and compared exactly).
LABEL_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.:/+-]{0,63}")
MAX_LABEL = 64
#: Notes are free text of at most this many bytes of UTF-8 (under the socket's 4,096-byte strings).
MAX_NOTES_BYTES = 4000


def check_label(label: object) -> str:
    """`label` if it is one (LABEL_PATTERN); ValueError saying what a label may be."""
    if not isinstance(label, str) or not LABEL_PATTERN.fullmatch(label):
        shown = repr(label) if len(repr(label)) <= 60 else repr(label)[:57] + "..."
        raise ValueError(
            f"label {shown} is not a label: 1 to {MAX_LABEL} letters, digits or _ . : / + -,"
            " starting with a letter or digit (no spaces)"
        )
    return label


def check_notes(notes: object) -> str:
    """`notes` if it is text of at most MAX_NOTES_BYTES bytes of UTF-8; ValueError saying why not."""
    if not isinstance(notes, str):
        raise ValueError(f"notes must be text, got {type(notes).__name__}")
    size = len(notes.encode("utf-8", "surrogatepass"))
    if size > MAX_NOTES_BYTES:
        raise ValueError(f"notes are {size:,} bytes of UTF-8; at most {MAX_NOTES_BYTES:,}")
    return notes
