"""Scenario suite (issue 15): the simulated rig as real rigs differ from the paper's, stroke by stroke.

Each scenario runs the rig model on its own (no DAQ, no daemon) through `cycles` alternating on/off
strokes `period_ns` apart and returns every stroke's operating time, the conditions a controller knows
before that stroke (drive frequency and voltage, motor temperature, time since the direction's previous
stroke) and the stroke's innovation floor: the std of the part no predictor can know from the past,
`UsmSwitchModel.innovation_floor_ns` at the stroke's conditions. Seeded and reproducible.

| name | what differs from the default rig |
|---|---|
| default | nothing: the calibrated rig at 40 kHz, 500 Vpp, 25 C ambient |
| temperature | the ambient rises 20 C over the run (the resonance falls 10 Hz/C: ~0.15 %/C slower) |
| frequency-step | the drive steps 40 -> 40.5 kHz half way |
| voltage-step | the drive steps 500 -> 450 Vpp half way |
| shift-noise4 | the far sensor moves 0.2 mm (4 %, unreported) half way, and white noise x4 |
| noise4 | white stroke noise x4 (2.2 %) |
| noise8 | white stroke noise x8 (4.4 %) |
| friction-0.8 | friction mean-reverting, phi 0.8 (std 4 % still) |
| idle-120s | a 120 s pause every 500 cycles: the motor cools |
| thermal-idle | the ambient rises 15 C over the run, a 60 s pause every 300 cycles (drift, idle gaps) |
| outliers | the default rig, one stroke in ~250 per direction 10 floors off (a sticky start, a bounce) |
| random-walk | no rig: a random walk (0.3 %/stroke) plus white noise (1 %) around 8.5 ms |
| random-walk-slow | no rig: a random walk (0.1 %/stroke) plus white noise (1 %) |
| random-walk-fast | no rig: a random walk (0.5 %/stroke) plus white noise (0.1 %): the paper's home |
| ar-0.1, ar-0.3, ar-0.6 | no rig: stationary AR(1) (phi 0.1, 0.3, 0.6; std 1.5 %) around 8.5 ms + white 1 % |
| level-shifts | no rig: AR(1) (phi 0.9, std 0.5 %) + white 0.8 %, the mean jumping 3-8 floors ~every 400 |

The rows marked "no rig" are bare processes (each direction its own, independent), so the issue's classes
of process are tested as such; their conditions are constant (40 kHz, 500 Vpp, 25 C) and their floor is
the steady-state Kalman filter's innovation std of the process (at a jump of the mean, or an outlier, the
jump's or the outlier's own size is added in quadrature: no predictor can know it).
"""

from __future__ import annotations

import dataclasses
import math
import random
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
    outlier_every: int = 0  # about one stroke in this many per direction is 10 floors off (0: none)
    process: Process | None = None  # a bare process instead of the rig


@dataclass(frozen=True)
class Process:
    """A bare stroke-time process per direction: ln t = ln mean + J + F + w, F AR(1) (phi, stationary std
    `std`; phi = 1: a random walk of innovation std `std`), w white (`white`), J a level that jumps by
    +-3..8 floors with probability `jump_rate` per stroke (so a random walk never reaches 0)."""

    phi: float
    std: float
    white: float
    jump_rate: float = 0.0
    mean_ns: float = 8_500_000.0

    @property
    def innovation_sd(self) -> float:
        return self.std if self.phi >= 1.0 else self.std * math.sqrt(1.0 - self.phi**2)

    @property
    def floor_relative(self) -> float:
        """The steady-state Kalman filter's one-step innovation std (relative):
        P = phi^2 P r / (P + r) + q."""
        q, r, phi2 = self.innovation_sd**2, self.white**2, min(self.phi, 1.0) ** 2
        c = r * (1.0 - phi2) - q
        big_p = 0.5 * (-c + math.sqrt(c * c + 4.0 * q * r))
        return math.sqrt(big_p + r)


#: The scale of a 10-floor outlier.
OUTLIER_FLOORS = 10.0


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
        Scenario(
            "thermal-idle",
            "ambient +15 C over the run, 60 s pause every 300 cycles",
            ambient_rise_c=15.0,
            idle_every=300,
            idle_ns=60_000_000_000,
        ),
        Scenario("outliers", "one stroke in ~250 per direction 10 floors off", outlier_every=250),
        Scenario("random-walk", "random walk 0.3 % + white 1 %", process=Process(1.0, 0.003, 0.01)),
        Scenario("random-walk-slow", "random walk 0.1 % + white 1 %", process=Process(1.0, 0.001, 0.01)),
        Scenario("random-walk-fast", "random walk 0.5 % + white 0.1 %", process=Process(1.0, 0.005, 0.001)),
        Scenario("ar-0.1", "AR(1) phi 0.1 std 1.5 % + white 1 %", process=Process(0.1, 0.015, 0.01)),
        Scenario("ar-0.3", "AR(1) phi 0.3 std 1.5 % + white 1 %", process=Process(0.3, 0.015, 0.01)),
        Scenario("ar-0.6", "AR(1) phi 0.6 std 1.5 % + white 1 %", process=Process(0.6, 0.015, 0.01)),
        Scenario(
            "level-shifts",
            "AR(1) phi 0.9 std 0.5 % + white 0.8 %, mean jumps 3-8 floors ~every 400",
            process=Process(0.9, 0.005, 0.008, jump_rate=1 / 400),
        ),
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
    jumps: list[int] = field(default_factory=list)  # cycles where a bare process's mean jumped


def run_scenario(
    name: str, seed: int = 0, cycles: int = 4000, period_ns: int = 50_000_000, warm_cycles: int = 0
) -> ScenarioRun:
    """Run scenario `name` for `cycles` strokes (alternating on, off) from `seed`; KeyError names a bad one.

    `warm_cycles` strokes are run first and not returned (the motor warms to its steady state).
    """
    if name not in SCENARIOS:
        raise KeyError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    sc = SCENARIOS[name]
    if sc.process is not None:
        return _run_process(sc, seed, cycles, period_ns)
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
    if sc.outlier_every:
        strokes = _with_outliers(strokes, sc.outlier_every, seed)
    return ScenarioRun(sc, seed, strokes, step_cycle, after_idle)


def with_outlier(stroke: ScenarioStroke, floors: float = OUTLIER_FLOORS) -> ScenarioStroke:
    """The stroke `floors` of its floor off (negative: short), its floor now including that offset."""
    off = floors * stroke.floor_ns
    return dataclasses.replace(
        stroke, operating_ns=stroke.operating_ns + round(off), floor_ns=math.hypot(stroke.floor_ns, off)
    )


def _with_outliers(strokes: list[ScenarioStroke], every: int, seed: int) -> list[ScenarioStroke]:
    rng = random.Random(f"outliers-{seed}")
    return [
        with_outlier(s, rng.choice((-OUTLIER_FLOORS, OUTLIER_FLOORS))) if rng.random() < 1.0 / every else s
        for s in strokes
    ]


def _run_process(sc: Scenario, seed: int, cycles: int, period_ns: int) -> ScenarioRun:
    """A bare process (`Process`) per direction, alternating on/off `period_ns` apart."""
    pr = sc.process
    assert pr is not None
    rng = random.Random(f"{sc.name}-{seed}")
    floor_rel = pr.floor_relative
    q = pr.innovation_sd
    f = [0.0 if pr.phi >= 1.0 else rng.gauss(0.0, pr.std) for _ in range(2)]
    jump = [0.0, 0.0]
    cond = {"frequency_hz": 40_000.0, "voltage_v": 500.0, "temperature_c": 25.0}
    strokes: list[ScenarioStroke] = []
    jumps: list[int] = []
    for k in range(cycles):
        d = Direction.ON if k % 2 == 0 else Direction.OFF
        floor = pr.mean_ns * floor_rel
        if pr.jump_rate and rng.random() < pr.jump_rate:
            jumps.append(k)
            size = rng.uniform(3.0, 8.0) * floor_rel * rng.choice((-1.0, 1.0))
            jump[d] += size
            floor = math.hypot(floor, size * pr.mean_ns)
        level = jump[d] + (pr.phi if pr.phi < 1.0 else 1.0) * f[d]  # what the past can tell
        f[d] = (pr.phi if pr.phi < 1.0 else 1.0) * f[d] + q * rng.gauss(0.0, 1.0)
        t = pr.mean_ns * math.exp(jump[d] + f[d] + pr.white * rng.gauss(0.0, 1.0))
        floor *= math.exp(level)  # the floor at the stroke's level (relative std x its predictable time)
        c: dict[str, float | int] = dict(cond)
        if k >= 2:
            c["idle_ns"] = 2 * period_ns
        strokes.append(ScenarioStroke(k, d, round(t), c, floor))
    return ScenarioRun(sc, seed, strokes, None, [], jumps)
