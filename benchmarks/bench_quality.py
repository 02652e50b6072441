"""Prediction quality (issues 15, 24): every shipped model on the scenario suite, against the floor.

Each predictor (one per direction, told each stroke's conditions) predicts every stroke of every
scenario (`usmswitch.sim.scenarios`, 5 seeds x 4000 strokes): the simulated rig as real rigs differ,
and bare processes (random walk plus noise, stationary AR(1) around a mean, level shifts). Printed per
scenario x predictor: the RMS one-step error over the innovation floor (strokes from cycle 200). Then
per predictor: the worst error within three strokes of each direction after a drive step, the error of
each direction's first stroke after a 120 s pause, and the outlier rule (issue 24): one stroke 10 floors
off, the error RMS of that direction's next 20 strokes over what it is without the outlier. Beside the
shipped models: a statsmodels AutoReg(1, trend="c") refitted on the last 100 strokes every 25 strokes.
Then the cost per stroke. The targets are the issue's, for the default model: <= 1.03x the floor on
every scenario and never worse than the paper's AR(1); the first drive step, commissioned, <= 300 us;
the outlier rule <= 1.1x.

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
from usmswitch.sim.scenarios import (
    SCENARIOS,
    Process,
    Scenario,
    ScenarioRun,
    _run_process,
    run_scenario,
    with_outlier,
)

SEEDS = (1, 2, 3, 4, 5)
CYCLES = 4000
SKIP = 200  # cold start, left out of the ratio
NOMINAL_NS = 8_000_000
REFIT_EVERY = 25
TARGET_RATIO = 1.03
TARGET_VS_PAPER = 1.0
TARGET_STEP_NS = 300_000  # issue 24: the worst first drive step, commissioned
TARGET_IDLE_NS = 120_000
TARGET_COST_US = 10.0
TARGET_OUTLIER = 1.1
#: The outlier rule: a stroke 10 floors off (each sign) at these cycles of each seed's run, scored on
#: these scenarios; the next OUTLIER_AFTER strokes of its direction.
OUTLIER_CYCLES = (1000, 1601, 2200, 2801, 3400)
OUTLIER_SCENARIOS = ("default", "noise4", "random-walk", "ar-0.3")
OUTLIER_AFTER = 20
TARGET_RESELECT_US = 50.0
#: The simulated rig's seed the commissioning runs on: none of SEEDS.
COMMISSION_SEED = 1001
COMMISSIONED = " + commissioned"
ORACLE = "oracle: the rig's physics + exact Kalman"
#: Issue 37's held-out check: a class the scenarios do not hold, a stationary friction seen without
#: stroke noise (AR(1) in ln t around 8.5 ms, std 1.5 %, these phis), on SEEDS and on seeds no model
#: choice was tuned on. The default was 1.035x the floor at phi 0.6 here (its grid's nearest filters
#: are 2-3 % off there).
CLEAN_PHIS = (0.3, 0.6, 0.9)
HELD_OUT_SEEDS = tuple(range(21, 31))
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


class ProcessOracle:
    """A bare stationary process's own one-step predictor, its mean and phi known: mean exp(phi ln(t /
    mean)) of the last stroke. Over a seed it reads the floor as that seed drew it (its luck)."""

    def __init__(self, process: Process) -> None:
        self.mean = process.mean_ns
        self.phi = process.phi
        self.last: float | None = None

    def predict(self, conditions: Any = None) -> float:
        return self.mean if self.last is None else self.mean * (self.last / self.mean) ** self.phi

    def update(self, t_ns: int, conditions: Any = None) -> None:
        self.last = float(t_ns)


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
    ]  # the rig's scenarios only (a bare process has no rig physics)
    return out


def _next_errors(
    make: Callable[[ScenarioRun], list[Any]], run: ScenarioRun, strokes: list[Any], at: int
) -> list[float]:
    """Errors of the OUTLIER_AFTER strokes of stroke `at`'s direction after it, predicting `strokes`."""
    ps = make(run)
    out = []
    for s in strokes[: at + 2 * OUTLIER_AFTER + 1]:
        p = ps[s.direction]
        e = s.operating_ns - p.predict(s.conditions)
        p.update(s.operating_ns, s.conditions)
        if s.cycle > at and (s.cycle - at) % 2 == 0:
            out.append(e)
    return out


def _outlier_rule(make: Callable[[ScenarioRun], list[Any]], runs: list[ScenarioRun]) -> tuple[float, float]:
    """(RMS over all cases, worst case) of the next OUTLIER_AFTER strokes' error with a 10-floor outlier
    over the same without it, each case the same run and predictor, the outlier +-10 floors at each of
    OUTLIER_CYCLES."""
    num = den = 0.0
    worst = 0.0
    for run in runs:
        for at in OUTLIER_CYCLES:
            clean = _next_errors(make, run, run.strokes, at)
            c2 = sum(e * e for e in clean)
            for sign in (1.0, -1.0):
                strokes = list(run.strokes)
                strokes[at] = with_outlier(strokes[at], 10.0 * sign)
                hit = _next_errors(make, run, strokes, at)
                h2 = sum(e * e for e in hit)
                num += h2
                den += c2
                worst = max(worst, math.sqrt(h2 / c2))
    return math.sqrt(num / den), worst


def _without_after_jump(make: Callable[[ScenarioRun], list[Any]], runs: list[ScenarioRun]) -> float:
    """The ratio to the floor leaving out the stroke of each direction right after a jump of the mean:
    the one stroke that the outlier rule does not let a predictor follow (it cannot tell it from an
    outlier yet)."""
    se = sf = 0.0
    for run in runs:
        ps = make(run)
        skip = {j + 2 for j in run.jumps}
        for s in run.strokes:
            p = ps[s.direction]
            e = s.operating_ns - p.predict(s.conditions)
            p.update(s.operating_ns, s.conditions)
            if s.cycle >= SKIP and s.cycle not in skip:
                se += e * e
                sf += s.floor_ns * s.floor_ns
    return math.sqrt(se / sf)


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


def _known(run: ScenarioRun) -> list[Any]:
    """Each direction's `ProcessOracle` of a bare process's run."""
    process = run.scenario.process
    assert process is not None
    return [ProcessOracle(process), ProcessOracle(process)]


def _clean(makers: dict[str, Callable[[ScenarioRun], list[Any]]], default: str, paper: str) -> list[str]:
    """The held-out table: each stationary class without stroke noise on SEEDS and HELD_OUT_SEEDS, the
    default, the process's own predictor and the paper's AR(1) over the floor (pooled, and the worst
    seed); returns the targets missed."""
    rows, missed = [], []
    for phi in CLEAN_PHIS:
        # Not one of SCENARIOS (the suite is sim's): the same bare-process runner, its own name and seeds.
        what = f"AR(1) phi {phi} std 1.5 %, no stroke noise"
        sc = Scenario(f"ar-{phi}-clean", what, process=Process(phi, 0.015, 0.0))
        for seeds in (SEEDS, HELD_OUT_SEEDS):
            runs = [_run_process(sc, seed, CYCLES, 50_000_000) for seed in seeds]
            where = f"{sc.name} seeds {seeds[0]}-{seeds[-1]}"
            cells = [sc.name, f"{seeds[0]}-{seeds[-1]}"]
            got = []
            for make in (makers[default], _known, makers[paper]):
                scored = [_score(make, run)[:2] for run in runs]
                got.append(math.sqrt(sum(a for a, _ in scored) / sum(b for _, b in scored)))
                cells += [f"{got[-1]:.3f}", f"{max(math.sqrt(a / b) for a, b in scored):.3f}"]
            d, pp = got[0], got[2]
            rows.append([*cells[:-1], f"{d / pp:.3f}"])  # the paper's worst seed: not shown
            if d > TARGET_RATIO:
                missed.append(f"{where}: {default} {d:.3f}x the floor > {TARGET_RATIO}")
            if d > TARGET_VS_PAPER * pp:
                missed.append(f"{where}: {default} {d:.3f} worse than the paper's {pp:.3f}")
    print()
    held = f"{HELD_OUT_SEEDS[0]}-{HELD_OUT_SEEDS[-1]}"
    print_table(
        ["class", "seeds", "default", "worst seed", "phi and mean known", "worst seed", "paper AR(1)",
         "default / paper"],
        rows,
        title=(
            "held-out check: a stationary friction seen without stroke noise (AR(1) in ln t, std 1.5 %), "
            f"not one of the scenarios, on the scenarios' seeds and on seeds {held} (RMS one-step error / "
            f"innovation floor, {CYCLES} strokes a seed, from cycle {SKIP}); phi and mean known: the "
            "process's own one-step predictor, the floor as each seed drew it"
        ),
    )  # fmt: skip
    return missed


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
            if label == ORACLE and SCENARIOS[name].process is not None:
                continue
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
    others = [k for k in makers if k not in (default, commissioned, paper)]
    rows = []
    for n in SCENARIOS:
        d, dc, pp = ratio[default][n], ratio[commissioned][n], ratio[paper][n]
        rows.append(
            [n, f"{d:.3f}", f"{dc:.3f}", f"{pp:.3f}", f"{d / pp:.3f}",
             *[f"{ratio[k][n]:.3f}" if n in ratio[k] else "-" for k in others]]
        )  # fmt: skip
    print_table(
        ["scenario", "default", "default commissioned", "paper AR(1)", "default / paper", *others],
        rows,
        title=(
            f"RMS one-step error / innovation floor, {len(SEEDS)} seeds x {CYCLES} strokes per scenario "
            f"(from cycle {SKIP}); default: {default}; commissioned: told the drive sensitivities measured "
            f"on seed {COMMISSION_SEED}; oracle: the rig's own physics and Kalman filter (no controller has "
            "them; rig scenarios only)"
        ),
    )
    clean_missed = _clean(makers, default, paper)
    rule = {label: _outlier_rule(makers[label], [r for n in OUTLIER_SCENARIOS for r in runs[n]])
            for label in makers if label != ORACLE}  # fmt: skip
    after_jump = {
        label: _without_after_jump(makers[label], runs["level-shifts"]) for label in (default, paper)
    }
    rows = []
    for label in makers:
        rows.append(
            [label, f"{np.mean(steps[label]) / 1e3:.0f}", f"{np.max(steps[label]) / 1e3:.0f}",
             f"{np.mean(quiets[label]) / 1e3:.0f}", f"{np.mean(shifts[label]) / 1e3:.0f}",
             f"{np.mean(idles[label]) / 1e3:.0f}",
             f"{rule[label][0]:.3f}" if label in rule else "-",
             f"{rule[label][1]:.3f}" if label in rule else "-",
             f"{after_jump[label]:.3f}" if label in after_jump else "-"]
        )  # fmt: skip
    print()
    print_table(
        ["predictor", "step us mean", "step us max", "no step us", "shift us", "idle us",
         "outlier rule", "outlier worst", "level-shifts less the stroke after a jump"],
        rows,
        title=(
            "step: worst |error| within 3 strokes per direction of the drive step (frequency, voltage), the "
            f"first such step the predictor ever sees; no step: the same metric {QUIET} cycles before the "
            "step (its floor); shift: the same at the far sensor's unreported move (shift-noise4); idle: "
            "|error| of the first stroke per direction after 120 s; outlier rule: one stroke 10 floors off "
            f"(+ and -, cycles {', '.join(map(str, OUTLIER_CYCLES))}, on {', '.join(OUTLIER_SCENARIOS)}), "
            f"the error RMS of its direction's next {OUTLIER_AFTER} strokes over the same without it (all "
            "cases pooled; worst: the worst case); level-shifts less ...: the ratio to the floor leaving out "
            "each direction's stroke right after a jump of the mean"
        ),
    )  # fmt: skip
    missed = list(clean_missed)
    for label in (default, commissioned):
        for n in SCENARIOS:
            r, rp = ratio[label][n], ratio[paper][n]
            if r > TARGET_RATIO:
                missed.append(f"{n}: {label} {r:.3f}x the floor > {TARGET_RATIO}")
            if r > TARGET_VS_PAPER * rp:
                missed.append(f"{n}: {label} {r:.3f} worse than the paper's {rp:.3f}")
        if rule[label][0] > TARGET_OUTLIER:
            missed.append(f"outlier rule: {label} {rule[label][0]:.3f}x > {TARGET_OUTLIER}")
    step_max = float(np.max(steps[commissioned]))  # the target: the first drive step, commissioned
    if step_max > TARGET_STEP_NS:
        missed.append(
            f"first drive step, commissioned, worst {step_max / 1e3:.0f} us > {TARGET_STEP_NS / 1e3:.0f} us"
        )
    idle_mean = float(np.mean(idles[default]))
    if idle_mean > TARGET_IDLE_NS:
        missed.append(f"first stroke after idle {idle_mean / 1e3:.0f} us > {TARGET_IDLE_NS / 1e3:.0f} us")

    cost_rows = []
    for model in MODELS:
        t = _cost(model, runs["default"][:2])
        med = float(np.median(t))
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
        title="update + predict per stroke, told the conditions (timer pair included; the default's "
        "worst strokes: make bench BENCH=predictor)",
    )
    for m in missed:
        print(f"TARGET MISSED: {m}")
    return 1 if missed else 0
