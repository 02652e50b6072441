"""The armed next stroke (`Plan`) and what planning it takes: the mode, the start direction, the
predictor's view of the drive conditions. Apart from `loop.py`, which re-exports these names."""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from usmswitch.drivers import Conditions, Direction
from usmswitch.protocol.record import CycleRecord, Flag


class Mode(StrEnum):
    CLOSED = "closed"  # T_d = T - t_hat (Eq. 7)
    OPEN = "open"  # a fixed delay, for characterisation


@dataclass(slots=True)
class Plan:
    """The armed next stroke: what the predictor said and the delay that follows from it."""

    direction: Direction
    target_ns: int
    mode: Mode
    t_hat_ns: int
    delay_ns: int
    late: bool
    order: int
    coefficients: tuple[float, ...]
    flags: Flag  # LATE|CLAMPED when T < t_hat, WARMUP while the predictor gives its nominal

    def record(
        self,
        cycle: int,
        t_cmd: int,
        t_start: int | None,
        t_depart: int | None,
        t_arrive: int | None,
        operating: int | None,
        lateness: int | None,
        flags: Flag,
        *,
        cond: Conditions | None,
        run_id: int | None,
    ) -> CycleRecord:
        """The record of the stroke this plan armed, from its stamps (driver clock, ns)."""
        total = None if t_arrive is None else t_arrive - t_cmd
        return CycleRecord(
            cycle=cycle,
            direction=int(self.direction),
            mode=str(self.mode),
            target_ns=self.target_ns,
            order=self.order,
            coefficients=self.coefficients,
            t_hat_ns=self.t_hat_ns,
            delay_ns=self.delay_ns,
            t_cmd_ns=t_cmd,
            t_start_ns=t_start,
            t_depart_ns=t_depart,
            t_arrive_ns=t_arrive,
            operating_ns=operating,
            total_ns=total,
            error_ns=None if total is None else total - self.target_ns,
            dead_ns=None if t_depart is None or t_start is None else t_depart - t_start,
            lateness_ns=lateness,
            temperature_c=None if cond is None else cond.temperature_c,
            frequency_hz=None if cond is None else cond.frequency_hz,
            flags=int(flags),
            wall_ns=time.time_ns(),
            run_id=run_id,
        )


def direction_from_levels(levels: tuple[int, int] | None, otherwise: Direction) -> Direction:
    """The stroke that leaves the sensor the mover rests on; `otherwise` when that is not known."""
    if levels is not None:
        a, b = levels
        if a and not b:
            return Direction.ON
        if b and not a:
            return Direction.OFF
    return otherwise


def flags_for_failure(plan: Plan) -> Flag:
    """Flags of a stroke whose command never reached the drive."""
    return plan.flags | Flag.FAULT


def predictor_conditions(cond: Conditions | None) -> dict[str, Any] | None:
    """The conditions as the predictors take them (`usmswitch.predictor.CONDITION_KEYS`), known ones only."""
    if cond is None:
        return None
    out: dict[str, Any] = {}
    if cond.temperature_c is not None:
        out["temperature_c"] = cond.temperature_c
    if cond.frequency_hz is not None:
        out["frequency_hz"] = cond.frequency_hz
    if cond.voltage_vpp is not None:
        out["voltage_v"] = cond.voltage_vpp
    return out


def drive_of(cond: Conditions | None) -> tuple[float | None, float | None]:
    """The drive setting (frequency, voltage) of the conditions: a change re-plans the armed stroke."""
    return (None, None) if cond is None else (cond.frequency_hz, cond.voltage_vpp)
