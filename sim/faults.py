"""Fault injection plan for the simulated rig, as plain data a TOML table can carry.

```toml
[sim.faults.probability]   # per stroke, drawn from the rig's own fault generator
bounce = 0.01
spurious = 0.001
[sim.faults.schedule]      # by stroke number (0 = the first stroke this driver starts)
12 = ["stall"]
40 = "disconnect"
```
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

#: stall: no arrival; bounce: the far sensor chatters; missed: one edge never reported;
#: spurious: a glitch pair on a sensor; disconnect: the device goes away mid-stroke.
FAULT_KINDS: tuple[str, ...] = ("stall", "bounce", "missed", "spurious", "disconnect")


def check_kind(kind: object) -> str:
    """Validate a fault name against FAULT_KINDS."""
    if kind not in FAULT_KINDS:
        raise ValueError(f"unknown fault {kind!r}; known: {', '.join(FAULT_KINDS)}")
    return str(kind)


@dataclass(frozen=True)
class FaultPlan:
    """Per-stroke fault probabilities and a schedule of faults by stroke number."""

    probability: Mapping[str, float] = field(default_factory=dict)
    schedule: Mapping[int, tuple[str, ...]] = field(default_factory=dict)

    @classmethod
    def from_config(cls, config: Mapping[str, object] | FaultPlan | None) -> FaultPlan:
        """Parse `{"probability": {kind: p}, "schedule": {stroke: kind | [kinds]}}`; errors name the key."""
        if config is None:
            return cls()
        if isinstance(config, FaultPlan):
            return config
        if not isinstance(config, Mapping):
            raise ValueError(f"faults must be a table (mapping), got {type(config).__name__}")
        unknown = set(config) - {"probability", "schedule"}
        if unknown:
            raise ValueError(
                f"faults: unknown key(s) {sorted(unknown)!r}; expected 'probability', 'schedule'"
            )
        prob_in = config.get("probability", {})
        if not isinstance(prob_in, Mapping):
            raise ValueError(f"faults.probability must be a table, got {prob_in!r}")
        probability: dict[str, float] = {}
        for kind, p in prob_in.items():
            check_kind(kind)
            if isinstance(p, bool) or not isinstance(p, int | float) or not 0.0 <= p <= 1.0:
                raise ValueError(f"faults.probability.{kind} must be a number in [0, 1], got {p!r}")
            probability[kind] = float(p)
        sched_in = config.get("schedule", {})
        if not isinstance(sched_in, Mapping):
            raise ValueError(f"faults.schedule must be a table, got {sched_in!r}")
        schedule: dict[int, tuple[str, ...]] = {}
        for key, kinds in sched_in.items():
            n = _stroke_number(key)
            items = (kinds,) if isinstance(kinds, str) else kinds
            if not isinstance(items, list | tuple) or not items:
                raise ValueError(
                    f"faults.schedule.{key} must be a fault name or a list of them, got {kinds!r}"
                )
            for kind in items:
                if kind not in FAULT_KINDS:
                    raise ValueError(
                        f"faults.schedule.{key}: unknown fault {kind!r}; known: {', '.join(FAULT_KINDS)}"
                    )
            schedule[n] = schedule.get(n, ()) + tuple(items)
        return cls(probability, schedule)


def _stroke_number(key: object) -> int:
    if isinstance(key, bool):
        raise ValueError(f"faults.schedule key must be a stroke number, got {key!r}")
    if isinstance(key, int):
        n = key
    elif isinstance(key, str) and key.strip().isdigit():
        n = int(key)
    else:
        raise ValueError(f"faults.schedule key must be a stroke number, got {key!r}")
    if n < 0:
        raise ValueError(f"faults.schedule key must be >= 0, got {key!r}")
    return n
