"""Scenario suite (issue 15): the simulated rig as real rigs differ from the paper's, stroke by stroke.

Each scenario runs the rig model on its own (no DAQ, no daemon) through `cycles` alternating on/off
strokes `period_ns` apart and returns every stroke's operating time, the conditions a controller knows
before that stroke (drive frequency and voltage, motor temperature, time since the direction's previous
stroke) and the stroke's innovation floor: the std of the part no predictor can know from the past,
`UsmSwitchModel.innovation_floor_ns` at the stroke's conditions. Seeded and reproducible.

| name | what differs from the default rig |
|---|---|
| default | nothing: the calibrated rig at 40 kHz, 500 Vpp, 25 C ambient |
| temperature | the ambient rises 20 C over the run (the motor slows 1.2 %/C) |
| frequency-step | the drive steps 40 -> 40.5 kHz half way |
| voltage-step | the drive steps 500 -> 450 Vpp half way |
| shift-noise4 | the far sensor moves 0.2 mm (4 %, unreported) half way, and white noise x4 |
| noise4 | white stroke noise x4 (2.2 %) |
| noise8 | white stroke noise x8 (4.4 %) |
| friction-0.8 | friction mean-reverting, phi 0.8 (std 4 % still) |
| idle-120s | a 120 s pause every 500 cycles: the motor cools |
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from usmswitch.drivers.events import Direction

from .model import UsmSwitchModel
from .params import RigParams

_BASE = RigParams()


@dataclass(frozen=True)
class Scenario:
    """One way a rig differs from the default: parameter changes, a drive step, drift, idle pauses."""

    name: str
    what: str
    params: dict[str, Any] = field(default_factory=dict)  # RigParams fields changed from the start
    step: dict[str, float] = field(default_factory=dict)  # half way: frequency_hz, voltage_vpp, stroke_mm
    ambient_rise_c: float = 0.0  # the ambient rises linearly by this much over the run
    idle_every: int = 0  # a pause of idle_ns after every this many cycles (0: none)
    idle_ns: int = 0


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("default", "the calibrated rig at 40 kHz, 500 Vpp, 25 C ambient"),
        Scenario("temperature", "ambient +20 C over the run", ambient_rise_c=20.0),
        Scenario("frequency-step", "drive 40 -> 40.5 kHz half way", step={"frequency_hz": 40_500.0}),
        Scenario("voltage-step", "drive 500 -> 450 Vpp half way", step={"voltage_vpp": 450.0}),
        Scenario(
            "shift-noise4",
            "far sensor +0.2 mm half way (unreported), white noise x4",
            params={"white_std": 4 * _BASE.white_std},
            step={"stroke_mm": _BASE.stroke_mm + 0.2},
        ),
        Scenario("noise4", "white noise x4", params={"white_std": 4 * _BASE.white_std}),
        Scenario("noise8", "white noise x8", params={"white_std": 8 * _BASE.white_std}),
        Scenario("friction-0.8", "friction phi 0.8", params={"friction_phi": 0.8}),
        Scenario("idle-120s", "120 s pause every 500 cycles", idle_every=500, idle_ns=120_000_000_000),
    )
}


@dataclass(frozen=True, slots=True)
class ScenarioStroke:
    """One stroke of a scenario run: what a controller would know before it, and what it took."""

    cycle: int
    direction: Direction
    operating_ns: int
    conditions: dict[str, float | int]  # frequency_hz, voltage_v, temperature_c, idle_ns (none at first)
    floor_ns: float  # std of this stroke's unpredictable part


@dataclass(frozen=True)
class ScenarioRun:
    """A scenario's strokes in cycle order, the cycle of its drive step and the first cycles after a pause."""

    scenario: Scenario
    seed: int
    strokes: list[ScenarioStroke]
    step_cycle: int | None
    after_idle: list[int]


def run_scenario(
    name: str, seed: int = 0, cycles: int = 4000, period_ns: int = 50_000_000, warm_cycles: int = 0
) -> ScenarioRun:
    """Run scenario `name` for `cycles` strokes (alternating on, off) from `seed`; KeyError names a bad one.

    `warm_cycles` strokes are run first and not returned (the motor warms to its steady state).
    """
    if name not in SCENARIOS:
        raise KeyError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    sc = SCENARIOS[name]
    params = dataclasses.replace(_BASE, **sc.params)
    model = UsmSwitchModel(params, seed=seed)
    step_cycle = cycles // 2 if sc.step else None
    t = 0
    last_start: list[int | None] = [None, None]
    strokes: list[ScenarioStroke] = []
    after_idle: list[int] = []
    total = warm_cycles + cycles
    for k in range(total):
        cycle = k - warm_cycles
        if sc.idle_every and cycle > 0 and cycle % sc.idle_every == 0:
            t += sc.idle_ns
            after_idle.extend((cycle, cycle + 1))  # the first stroke of each direction after the pause
        if cycle == step_cycle:
            drive = {k2: v for k2, v in sc.step.items() if k2 != "stroke_mm"}
            if drive:
                model.set_drive(**drive)
            if "stroke_mm" in sc.step:
                model.params = dataclasses.replace(model.params, stroke_mm=sc.step["stroke_mm"])
        if sc.ambient_rise_c and cycle >= 0:
            ambient = _BASE.ambient_c + sc.ambient_rise_c * cycle / cycles
            model.params = dataclasses.replace(model.params, ambient_c=ambient)
        d = Direction.ON if k % 2 == 0 else Direction.OFF
        temp = model.temperature_c(t)
        cond: dict[str, float | int] = {
            "frequency_hz": model.frequency_hz,
            "voltage_v": model.voltage_vpp,
            "temperature_c": temp,
        }
        prev = last_start[d]
        if prev is not None:
            cond["idle_ns"] = t - prev
        last_start[d] = t
        st = model.next_stroke(d, t)
        if cycle >= 0 and st.operating_ns is not None:
            floor = st.motion_nominal_ns * model.innovation_floor_relative
            strokes.append(ScenarioStroke(cycle, d, st.operating_ns, cond, floor))
        t += period_ns
    return ScenarioRun(sc, seed, strokes, step_cycle, after_idle)
