"""Prediction quality (issue 15): every shipped model on the scenario suite, against the rig's floor.

Each predictor (one per direction, told each stroke's conditions) predicts every stroke of every
scenario (`usmswitch.sim.scenarios`, 5 seeds x 4000 strokes). Printed per predictor x scenario: the RMS
one-step error over the innovation floor (strokes from cycle 200), the worst error within three strokes
of each direction after a drive step, and the error of each direction's first stroke after a 120 s
pause. Beside the shipped models: a statsmodels AutoReg(1, trend="c") refitted on the last 100 strokes
every 25 strokes. Then the cost per stroke. The targets are the issue's, for the default model.

The default runs twice: told nothing beforehand (its step column is the first step of a kind it has
ever seen: news, as for the paper's AR(1)), and told the drive sensitivities that the commissioning
experiment (`usmswitch-experiment drive-sensitivity`) measured on another seed of the rig
(`COMMISSION_SEED`, not a scenario's): the daemon's configuration after commissioning. The step target
binds that one.

Last, an oracle that no controller has: the simulated rig's own physics at each stroke's conditions
and the exact Kalman filter of its friction and noise. Its step column is what the step metric reads
at the floor (the worst of six strokes' errors, with the slower motor's larger scatter after the
step): the least any predictor can reach on these seeds.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.table import print_table
from usmswitch.drivers.events import Direction
from usmswitch.experiments.context import Context
from usmswitch.experiments.drive_sensitivity import DriveSensitivity, measure
from usmswitch.experiments.rig import SimulatedRig
from usmswitch.predictor import AR_MODELS, DEFAULT_MODEL, MODELS, ARPredictor, make_predictors
from usmswitch.sim.model import UsmSwitchModel
from usmswitch.sim.params import RigParams
from usmswitch.sim.scenarios import SCENARIOS, ScenarioRun, run_scenario

SEEDS = (1, 2, 3, 4, 5)
CYCLES = 4000
SKIP = 200  # cold start, left out of the ratio
NOMINAL_NS = 8_000_000
REFIT_EVERY = 25
TARGET_RATIO = 1.03
TARGET_VS_PAPER = 1.01
TARGET_STEP_NS = 150_000
TARGET_IDLE_NS = 120_000
TARGET_COST_US = 5.0
TARGET_RESELECT_US = 50.0
#: The simulated rig's seed the commissioning runs on: none of SEEDS.
COMMISSION_SEED = 1001
COMMISSIONED = " + commissioned"
ORACLE = "oracle: the rig's physics + exact Kalman"
#: The step metric is also taken this many cycles before the step, where nothing stepped: the worst of
#: six strokes' errors is ~1.7 innovation sds (~150 us on the default rig) with no step at all.
QUIET = 1000


class StatsmodelsRefit:
    """statsmodels AutoReg(1, trend="c") on the last 100 strokes, refitted every REFIT_EVERY strokes."""

    def __init__(self) -> None:
        self.window: list[int] = []
        self.params: tuple[float, float] | None = None
        self.n = 0

    def predict(self, conditions: Any = None) -> float:
        if not self.window:
            return float(NOMINAL_NS)
        if self.params is None:
            return float(self.window[-1])
        c, a = self.params
        return c + a * self.window[-1]

    def update(self, t_ns: int, conditions: Any = None) -> None:
        from statsmodels.tsa.ar_model import AutoReg

        self.window = [*self.window[-99:], t_ns]
        self.n += 1
        if self.n >= 30 and self.n % REFIT_EVERY == 0:
            fit = AutoReg(np.asarray(self.window, dtype=float), lags=1, trend="c").fit()
            self.params = (float(fit.params[0]), float(fit.params[1]))


class Oracle:
    """Not a predictor a controller can have: the scenario rig's deterministic stroke time at the
    stroke's conditions (dead time + motion at friction's mean) and the exact steady Kalman filter of
    the motion's scale 1 + F + w (F AR(1), w white, the rig's parameters). Its one-step error is the
    innovation floor (it knows all but the unreported sensor shift)."""

    def __init__(self, params: RigParams, direction: Direction) -> None:
        self.rig = UsmSwitchModel(params)
        self.direction = direction
        self.dead = self.rig.dead_time_ns(direction)
        self.phi = params.friction_phi
        self.q = params.friction_std**2 * (1.0 - params.friction_phi**2)
        self.r = params.white_std**2
        self.f = 0.0  # friction's estimate
        self.var = params.friction_std**2

    def _motion(self, c: dict[str, Any]) -> float:
        return self.rig.motion_ns(
            self.direction,
            frequency_hz=c["frequency_hz"],
            voltage_vpp=c["voltage_v"],
            temperature_c=c["temperature_c"],
        )

    def predict(self, conditions: dict[str, Any]) -> float:
        return self.dead + self._motion(conditions) * (1.0 + self.phi * self.f)

    def update(self, t_ns: int, conditions: dict[str, Any]) -> None:
        y = (t_ns - self.dead) / self._motion(conditions) - 1.0
        f, var = self.phi * self.f, self.phi**2 * self.var + self.q
        gain = var / (var + self.r)
        self.f, self.var = f + gain * (y - f), (1.0 - gain) * var


def commission() -> DriveSensitivity:
    """The drive sensitivities as `usmswitch-experiment drive-sensitivity` measures them, on a rig of
    another seed than the scenarios'."""
    with tempfile.TemporaryDirectory() as tmp:
        rig = SimulatedRig(Path(tmp) / "records.sqlite", COMMISSION_SEED)
        try:
            return measure(Context(out=Path(tmp), rig=rig, seed=COMMISSION_SEED))
        finally:
            rig.close()


def _makers(known: DriveSensitivity) -> dict[str, Callable[[ScenarioRun], list[Any]]]:
    """Each row's pair of predictors (on, off) for a run."""
    out: dict[str, Callable[[ScenarioRun], list[Any]]] = {}
    for model in MODELS:
        label = f"{model} AR(1)" if model in AR_MODELS else model
        if model == DEFAULT_MODEL:
            label += " (default)"
        out[label] = lambda run, model=model: make_predictors(model, [NOMINAL_NS, NOMINAL_NS])
        if model == DEFAULT_MODEL:
            out[label + COMMISSIONED] = lambda run, model=model: make_predictors(
                model, [NOMINAL_NS, NOMINAL_NS], sensitivities=known.sensitivities
            )
    out["statsmodels AutoReg(1, c) refit"] = lambda run: [StatsmodelsRefit(), StatsmodelsRefit()]
    out[ORACLE] = lambda run: [
        Oracle(dataclasses.replace(RigParams(), **run.scenario.params), d) for d in Direction
    ]
    return out


def _score(
    make: Callable[[ScenarioRun], list[Any]], run: ScenarioRun
) -> tuple[float, float, list[float], list[float], list[float]]:
    """(sum e^2, sum floor^2) from cycle SKIP; |e| within 3 strokes per direction of the step; after
    idles; |e| over the same window QUIET cycles before the step (the metric with no step: its floor)."""
    ps = make(run)  # one per direction, as the daemon makes them
    se = sf = 0.0
    step: list[float] = []
    quiet: list[float] = []
    idle: list[float] = []
    step_at = run.step_cycle
    after = set(run.after_idle)
    for s in run.strokes:
        p = ps[s.direction]
        e = s.operating_ns - p.predict(s.conditions)
        p.update(s.operating_ns, s.conditions)
        if s.cycle >= SKIP:
            se += e * e
            sf += s.floor_ns * s.floor_ns
        if step_at is not None and step_at <= s.cycle < step_at + 6:
            step.append(abs(e))
        if step_at is not None and step_at - QUIET <= s.cycle < step_at - QUIET + 6:
            quiet.append(abs(e))
        if s.cycle in after:
            idle.append(abs(e))
    return se, sf, step, idle, quiet


def _cost(model: str, runs: list[ScenarioRun]) -> np.ndarray:
    """update + predict per stroke (us, timer pair included) on the default scenario."""
    out = []
    clock = time.perf_counter_ns
    for run in runs:
        ps = make_predictors(model, [NOMINAL_NS, NOMINAL_NS])
        for s in run.strokes:
            p = ps[s.direction]
            t0 = clock()
            p.predict(s.conditions)
            p.update(s.operating_ns, s.conditions)
            out.append(clock() - t0)
    return np.asarray(out[2 * SKIP :], dtype=float) / 1e3


def _reselect_cost(runs: list[ScenarioRun]) -> tuple[float, float]:
    """(median, max) us of the strokes that re-select the order (AIC up to 3, every 100 strokes) or take
    the order selected of the paper's AR with `order="auto"`: each timed on 5 copies, the least kept,
    gc off (a collection or a preemption on this shared machine is not the predictor's cost)."""
    took = []
    clock = time.perf_counter_ns
    for run in runs:
        p = ARPredictor(order="auto", window=100, max_order=3, nominal_ns=NOMINAL_NS)
        for s in run.strokes:
            if s.direction:
                continue
            copies = [ARPredictor.from_state(p.state()) for _ in range(5)]
            switching = p._pending is not None  # this stroke takes the order chosen at the last one
            p.update(s.operating_ns)
            if p._since_select != 0 and not switching:  # neither selects nor switches
                continue
            best = math.inf
            gc.disable()
            try:
                for q in copies:
                    t0 = clock()
                    q.predict()
                    q.update(s.operating_ns)
                    best = min(best, (clock() - t0) / 1e3)
            finally:
                gc.enable()
            took.append(best)
    return float(np.median(took)), max(took)


def main() -> int:
    runs = {name: [run_scenario(name, seed=seed, cycles=CYCLES) for seed in SEEDS] for name in SCENARIOS}
    known = commission()
    print(
        f"commissioned on seed {COMMISSION_SEED}: {known.per_khz:.4f} +- {known.stderr_per_khz:.4f} per kHz, "
        f"{known.per_100v:.4f} +- {known.stderr_per_100v:.4f} per 100 V (d ln t)"
    )
    makers = _makers(known)
    ratio: dict[str, dict[str, float]] = {}
    steps: dict[str, list[float]] = {}  # drive steps (frequency, voltage): told in the conditions
    shifts: dict[str, list[float]] = {}  # the sensor moved: unreported, no predictor can know it
    quiets: dict[str, list[float]] = {}
    idles: dict[str, list[float]] = {}
    for label, make in makers.items():
        ratio[label] = {}
        steps[label] = []
        shifts[label] = []
        quiets[label] = []
        idles[label] = []
        for name, rs in runs.items():
            se = sf = 0.0
            for run in rs:
                a, b, st, idle, quiet = _score(make, run)
                if quiet and SCENARIOS[name].step.keys() - {"stroke_mm"}:
                    quiets[label].append(max(quiet))
                se += a
                sf += b
                if st:
                    (steps if SCENARIOS[name].step.keys() - {"stroke_mm"} else shifts)[label].append(max(st))
                idles[label].extend(idle)
            ratio[label][name] = math.sqrt(se / sf)
    paper = next(k for k in makers if k.startswith("paper"))
    default = next(k for k in makers if k.endswith("(default)"))
    commissioned = default + COMMISSIONED
    rows = []
    for label in makers:
        rows.append(
            [label, *[f"{ratio[label][n]:.3f}" for n in SCENARIOS],
             f"{np.mean(steps[label]) / 1e3:.0f}", f"{np.max(steps[label]) / 1e3:.0f}",
             f"{np.mean(quiets[label]) / 1e3:.0f}", f"{np.mean(shifts[label]) / 1e3:.0f}",
             f"{np.mean(idles[label]) / 1e3:.0f}"]
        )  # fmt: skip
    print_table(
        ["predictor", *SCENARIOS, "step us mean", "step us max", "no step us", "shift us", "idle us"],
        rows,
        title=(
            f"RMS one-step error / innovation floor, {len(SEEDS)} seeds x {CYCLES} strokes per scenario; "
            "step: worst |error| within 3 strokes per direction of the drive step (frequency, voltage), "
            f"the first such step the predictor ever sees; no step: the same metric {QUIET} cycles before "
            "the step (its floor); shift: the same at the far sensor's unreported "
            "move (shift-noise4); idle: |error| of the first stroke per "
            f"direction after 120 s; {COMMISSIONED.strip()}: told the drive sensitivities measured on "
            f"seed {COMMISSION_SEED}; oracle: the rig's own physics and Kalman filter (no controller has"
            " them): what each column reads at the floor"
        ),
    )
    missed = []
    for label in (default, commissioned):
        for n in SCENARIOS:
            r, rp = ratio[label][n], ratio[paper][n]
            if r > TARGET_RATIO:
                missed.append(f"{n}: {label} {r:.3f}x the floor > {TARGET_RATIO}")
            if r > TARGET_VS_PAPER * rp:
                missed.append(f"{n}: {label} {r:.3f} worse than the paper's {rp:.3f} by more than 1 %")
    step_mean = float(np.mean(steps[commissioned]))  # the target: a drive step
    if step_mean > TARGET_STEP_NS:
        quiet_mean = float(np.mean(quiets[commissioned]))
        missed.append(
            f"step error, commissioned, {step_mean / 1e3:.0f} us > {TARGET_STEP_NS / 1e3:.0f} us"
            f" (the same metric with no step: {quiet_mean / 1e3:.0f} us; the oracle at the step:"
            f" {np.mean(steps[ORACLE]) / 1e3:.0f} us)"
        )
    idle_mean = float(np.mean(idles[default]))
    if idle_mean > TARGET_IDLE_NS:
        missed.append(f"first stroke after idle {idle_mean / 1e3:.0f} us > {TARGET_IDLE_NS / 1e3:.0f} us")

    cost_rows = []
    base = None
    for model in MODELS:
        t = _cost(model, runs["default"][:2])
        med = float(np.median(t))
        base = med if model == "paper" else base
        target = ""
        if model == DEFAULT_MODEL:
            target = f"median <= {TARGET_COST_US:g} us: " + ("ok" if med <= TARGET_COST_US else "MISSED")
            if med > TARGET_COST_US:
                missed.append(f"default costs {med:.2f} us per stroke > {TARGET_COST_US:g} us")
        cost_rows.append([model, f"{med:.2f}", f"{np.percentile(t, 99):.2f}", target])
    med_sel, worst = _reselect_cost(runs["default"])
    ok = worst <= TARGET_RESELECT_US
    if not ok:
        missed.append(f"an AIC re-selecting stroke costs {worst:.0f} us > {TARGET_RESELECT_US:g} us")
    cost_rows.append(
        ["paper AR auto, a re-selecting stroke", f"{med_sel:.2f}", f"max {worst:.0f}",
         f"max <= {TARGET_RESELECT_US:g} us: " + ("ok" if ok else "MISSED")]
    )  # fmt: skip
    print()
    print_table(
        ["predictor", "median us", "p99 us", "target"],
        cost_rows,
        title="update + predict per stroke, told the conditions (timer pair included)",
    )
    for m in missed:
        print(f"TARGET MISSED: {m}")
    return 1 if missed else 0
