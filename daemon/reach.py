"""What the rig can be asked for: targets it reaches, periods a stroke fits in, delays the device times.

Pure checks on the loop's predictors and settings, shared by every call that changes them
(set_target, set_mode, start_cycling, the daemon's start-up): each refuses with a message that
names the limit and a value that would do.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from usmswitch.drivers import Direction
from usmswitch.protocol.units import format_ns

from .plan import Mode


class TargetUnreachableError(ValueError):
    """A closed-loop target below the shortest stroke the rig makes; the message names the shortest."""


def shortest_target_ns(predictor: Any, late_margin_ns: int) -> int:
    """The shortest target a direction reaches now: its predicted stroke plus the late margin."""
    return math.ceil(predictor.predict()) + late_margin_ns


def check_reach(predictors: Sequence[Any], targets: Sequence[int], late_margin_ns: int) -> None:
    """Refuse (TargetUnreachableError) a closed-loop target below what the rig reaches: every stroke
    would start at once and arrive late. The message names the shortest reachable target."""
    for d in (Direction.ON, Direction.OFF):
        shortest = shortest_target_ns(predictors[d], late_margin_ns)
        if targets[d] < shortest:
            # Rounded up to 10 us: a target people can type that is surely reachable.
            typed = -(-shortest // 10_000) * 10_000
            hint = (
                " (a bare number is nanoseconds: write the unit, e.g. '12ms')"
                if targets[d] < 1_000_000
                else ""
            )
            name = "on" if d is Direction.ON else "off"
            raise TargetUnreachableError(
                f"target {format_ns(targets[d])}{hint} is below the shortest the rig reaches "
                f"in direction {name}: {format_ns(typed)} (predicted stroke "
                f"{format_ns(shortest - late_margin_ns)} + late margin "
                f"{format_ns(late_margin_ns)}); every stroke would be late. Set a target "
                f">= {format_ns(typed)}, or allow late strokes (allow_late)"
            )


def without_allow_late(message: str) -> str:
    """A reach refusal's message without its `allow_late` way out (a start-up has none)."""
    return message.replace(", or allow late strokes (allow_late)", "")


def reach_warnings(predictors: Sequence[Any], targets: Sequence[int]) -> list[str]:
    """Per direction, a warning when T is shorter than the predicted stroke (it will be late)."""
    out = []
    for d in (Direction.ON, Direction.OFF):
        t_hat = round(predictors[d].predict())
        if targets[d] < t_hat:
            out.append(
                f"target {format_ns(targets[d])} ({d.name.lower()}) is shorter than the predicted stroke "
                f"({format_ns(t_hat)}): those strokes start at once and arrive late"
            )
    return out


def check_period(
    predictors: Sequence[Any], period_ns: int, targets: Sequence[int], mode: Mode, open_delay_ns: int
) -> None:
    """Refuse (ValueError) a period that a stroke from its command (T, or t_hat when late) would not
    fit in."""
    t_hat = max(round(p.predict()) for p in predictors)
    longest = max(*targets, t_hat) if mode is Mode.CLOSED else open_delay_ns + t_hat
    if period_ns <= longest:
        what = "max of T and t_hat" if mode is Mode.CLOSED else "open delay + t_hat"
        raise ValueError(
            f"period {format_ns(period_ns)} is not longer than a stroke from its command"
            f" ({format_ns(longest)}, {what}): commands would overlap"
        )


def check_device(
    predictors: Sequence[Any], longest: int | None, targets: Sequence[int], mode: Mode, open_delay_ns: int
) -> None:
    """Refuse (ValueError) a start delay longer than the device can time (`longest`, its HELLO_ACK
    max_delay_us; None: no limit), naming its limit: the strokes would otherwise each fault at their
    ARM."""
    if longest is None:
        return
    if mode is Mode.OPEN:
        if open_delay_ns > longest:
            raise ValueError(
                f"open-loop delay {format_ns(open_delay_ns)} is longer than the device's longest"
                f" start delay, {format_ns(longest)}"
            )
        return
    for d in (Direction.ON, Direction.OFF):
        t_hat = max(0, math.floor(predictors[d].predict()))
        if targets[d] - t_hat > longest:
            raise TargetUnreachableError(
                f"target {format_ns(targets[d])} needs a start delay of {format_ns(targets[d] - t_hat)}"
                f" (T - t_hat), longer than the device's longest, {format_ns(longest)}: the"
                f" longest target it reaches is {format_ns(longest + t_hat)}"
            )
