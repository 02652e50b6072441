"""The default model on each class of process (issue 24), on seeds the quality bench does not use.

benchmarks/bench_quality.py holds the targets over 5 seeds x 4000 strokes (seeds 1-5); here 2 other
seeds per class: the default within 1.03x the innovation floor and never worse than the paper's AR(1),
the outlier rule, a level shift followed (and the belief in shifts learned), robustness while cold, and
the state with a suspect pending.
"""

from __future__ import annotations

import math
import random

import msgpack
import pytest

from usmswitch.predictor import DEFAULT_MODEL, SOUND_FIT, make_predictors
from usmswitch.predictor.kalman import KalmanPredictor
from usmswitch.sim.scenarios import SCENARIOS, ScenarioRun, run_scenario, with_outlier

SEEDS = (21, 22)
NOMINAL = 8_000_000
SKIP = 200


#: The drive sensitivities (per kHz, per 100 V, per C) that `usmswitch-experiment drive-sensitivity`
#: measures on seed 1001 of the simulated rig (`make bench BENCH=quality` prints them).
COMMISSIONED = (0.1498, -0.2316, None)
DRIVE_STEPS = ("frequency-step", "voltage-step")


def _ratio(
    model: str, runs: list[ScenarioRun], leave_out: set[tuple[int, int]] = frozenset(), **options: object
) -> float:
    se = sf = 0.0
    for k, run in enumerate(runs):
        ps = make_predictors(model, [NOMINAL, NOMINAL], **options)
        for s in run.strokes:
            p = ps[s.direction]
            e = s.operating_ns - p.predict(s.conditions)
            p.update(s.operating_ns, s.conditions)
            if s.cycle >= SKIP and (k, s.cycle) not in leave_out:
                se += e * e
                sf += s.floor_ns * s.floor_ns
    return math.sqrt(se / sf)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_the_default_is_near_the_floor_and_never_worse_than_the_paper(name: str) -> None:
    runs = [run_scenario(name, seed=seed, cycles=4000) for seed in SEEDS]
    ours = _ratio(DEFAULT_MODEL, runs)
    paper = _ratio("paper", runs)
    assert ours <= paper
    if name in DRIVE_STEPS:
        # Told nothing, the first step of a kind is news (~1 ms twice a run: 1.02-1.04x the floor);
        # commissioned, it is predicted.
        assert ours <= 1.045
        ours = _ratio(DEFAULT_MODEL, runs, sensitivities=COMMISSIONED)
    assert ours <= 1.03


def _stationary(n: int, seed: int, phi: float, std: float = 0.015) -> tuple[list[int], list[float]]:
    """A stationary AR(1) in ln t around 8.5 ms (phi, stationary std `std`) with no stroke noise: the
    strokes, and each stroke's best prediction from the past (mean and phi known)."""
    rng = random.Random(seed)
    q = std * math.sqrt(1.0 - phi * phi)
    f = rng.gauss(0.0, std)
    strokes, best = [], []
    for _ in range(n):
        best.append(8.5e6 * math.exp(phi * f))
        f = phi * f + rng.gauss(0.0, q)
        strokes.append(round(8.5e6 * math.exp(f)))
    return strokes, best


@pytest.mark.parametrize("phi", [0.3, 0.6, 0.9])
def test_a_stationary_friction_without_stroke_noise_is_predicted_at_its_floor(phi: float) -> None:
    # Issue 37: at phi 0.6 with no stroke noise the grid's nearest filters, (0.6, 0.65) and (0.8, 1),
    # are 2-3 % off the floor, and picking between them read 1.03-1.035x on the quality bench's
    # seeds (here 1.029 pooled, a seed 1.037; 1.026 at phi 0.9). The fitted filter (phi by least
    # squares, K = 1) is the floor's own predictor whatever phi is (1.004-1.007 here). The floor is
    # each stroke's innovation as drawn (the error of the best prediction, mean and phi known), so a
    # seed's luck is not counted; 10 seeds x 4000 strokes, none of them seen while tuning.
    seeds = range(501, 511)
    se = sf = 0.0
    for seed in seeds:
        strokes, best = _stationary(4000, seed, phi)
        p = KalmanPredictor(nominal_ns=NOMINAL)
        e2 = f2 = 0.0
        for k, (t, b) in enumerate(zip(strokes, best, strict=True)):
            if k >= SKIP:
                e2 += (t - p.predict()) ** 2
                f2 += (t - b) ** 2
            p.update(t)
        assert math.sqrt(e2 / f2) <= 1.03, (seed, math.sqrt(e2 / f2))
        se += e2
        sf += f2
    assert math.sqrt(se / sf) <= 1.015


def test_level_shifts_are_followed_and_the_stroke_after_one_is_what_costs() -> None:
    # The stroke right after a jump of the mean cannot be told from an outlier until the rig has
    # shown which it does; the rest is at the floor.
    runs = [run_scenario("level-shifts", seed=seed, cycles=4000) for seed in SEEDS]
    after = {(k, j + 2) for k, run in enumerate(runs) for j in run.jumps}
    assert len(after) >= 10
    assert _ratio(DEFAULT_MODEL, runs, after) <= 1.02
    assert _ratio(DEFAULT_MODEL, runs) < 0.9 * _ratio("paper", runs)


def _errors_after(events: list[tuple[int, float]], n: int = 3000, seed: int = 11) -> list[float]:
    """Errors (in floors) of the stroke after each event of a series: (stroke, factor) a level shift
    from that stroke on when the factor is kept (> 0), a lone outlier when negative (its magnitude)."""
    t = [round(8e6 * s) for s in _scales(n, seed=seed)]
    for at, factor in events:
        if factor > 0:
            t[at:] = [round(v * factor) for v in t[at:]]
        else:
            t[at] = round(t[at] * -factor)
    p = KalmanPredictor(nominal_ns=NOMINAL)
    errors = []
    for v in t:
        errors.append((v - p.predict()) / (8e6 * 0.0089))
        p.update(v)
    return [errors[at + 1] for at, _ in events]


def test_a_rig_that_shifts_is_believed_at_the_stroke_after_its_next_shift() -> None:
    # Six shifts of ~9 floors, each kept: the first is taken at its second stroke (an outlier is as
    # likely, nothing is known of this rig); once the rig has shown that it shifts, the stroke after
    # a shift leans toward it.
    # (Without the belief the six read 6.3, 10.7, 5.4, 6.3, 9.9, 9.5 floors.)
    ups = [(400 + 300 * k, 1.08 if k % 2 == 0 else 1 / 1.08) for k in range(6)]
    after = [abs(e) for e in _errors_after(ups)]
    assert min(after[:2]) > 4
    assert max(after[-3:]) < 0.6 * min(after[:2])
    # The same strokes, each 9 floors off for one stroke only: the prediction after moves no more
    # than without the belief (2.7, 1.7, 3.2, 1.6, 0.9, 0.1).
    outs = [(at, -(1.08 if k % 2 == 0 else 1 / 1.08)) for k, (at, _) in enumerate(ups)]
    assert max(abs(e) for e in _errors_after(outs)) < 3.5


def test_outliers_after_shifts_unlearn_the_belief() -> None:
    # Two shifts, then many outliers: the belief in a shift fades and the outliers stop moving it.
    events = [(400, 1.08), (700, 1 / 1.08)] + [(1000 + 100 * k, -1.08) for k in range(16)]
    after = [abs(e) for e in _errors_after(events)]
    assert after[2] > 5  # the first outlier after two shifts is believed a shift
    assert max(after[-4:]) < 0.4 * after[2]


def _next_square_errors(model: str, strokes: list, at: int, after: int = 20) -> float:
    ps = make_predictors(model, [NOMINAL, NOMINAL])
    acc = 0.0
    for s in strokes[: at + 2 * after + 1]:
        p = ps[s.direction]
        e = s.operating_ns - p.predict(s.conditions)
        p.update(s.operating_ns, s.conditions)
        if s.cycle > at and (s.cycle - at) % 2 == 0:
            acc += e * e
    return acc


@pytest.mark.parametrize("name", ["default", "random-walk"])
def test_a_stroke_10_floors_off_does_not_spoil_the_next_20(name: str) -> None:
    ratios = {}
    for model in (DEFAULT_MODEL, "paper"):
        hit = clean = 0.0
        for seed in SEEDS:
            run = run_scenario(name, seed=seed, cycles=3000)
            for at in (1200, 1801, 2400):
                c = _next_square_errors(model, run.strokes, at)
                for sign in (1.0, -1.0):
                    strokes = list(run.strokes)
                    strokes[at] = with_outlier(strokes[at], 10.0 * sign)
                    hit += _next_square_errors(model, strokes, at)
                    clean += c
        ratios[model] = math.sqrt(hit / clean)
    assert ratios[DEFAULT_MODEL] <= 1.1
    assert ratios["paper"] > 1.5  # the paper's AR(1) follows the outlier: the rule is not free


def _scales(n: int, seed: int) -> list[float]:
    import random

    rng = random.Random(seed)
    f, out = 0.0, []
    for _ in range(n):
        f = 0.975 * f + rng.gauss(0, 0.04 * math.sqrt(1 - 0.975**2))
        out.append(1 + f + rng.gauss(0, 0.0055))
    return out


def test_an_outlier_while_cold_does_not_move_the_cold_fit() -> None:
    t = [round(8e6 * s) for s in _scales(SOUND_FIT, seed=7)]
    bad = list(t)
    bad[15] = round(t[15] * 1.12)  # ~12 floors off, while the paper's AR(1) predicts
    clean, hit = KalmanPredictor(nominal_ns=NOMINAL), KalmanPredictor(nominal_ns=NOMINAL)
    for i in range(SOUND_FIT - 1):
        clean.update(t[i])
        hit.update(bad[i])
        if i == 15:  # the outlier just taken
            assert not hit.ready
            assert abs(hit.predict() - clean.predict()) < 150_000  # ~1.7 floors, not ~12
    floor = 8e6 * 0.0089
    assert abs(hit.predict() - clean.predict()) < floor


def test_a_level_shift_is_taken_at_its_second_stroke() -> None:
    t = [round(8e6 * s) for s in _scales(1000, seed=8)]
    shifted = t[:600] + [round(v * 1.08) for v in t[600:]]  # ~9 floors, for good
    p = KalmanPredictor(nominal_ns=NOMINAL)
    errors = []
    for v in shifted:
        errors.append((v - p.predict()) / (8e6 * 0.0089))
        p.update(v)
    assert abs(errors[600]) > 7 and abs(errors[601]) > 5  # news, then not yet told from an outlier
    assert max(abs(e) for e in errors[602:620]) < 3.5  # followed from the third stroke


def test_the_state_round_trips_with_a_suspect_pending_and_a_bad_one_is_named() -> None:
    t = [round(8e6 * s) for s in _scales(500, seed=9)]
    t[300] = round(t[300] * 1.1)
    k = KalmanPredictor(nominal_ns=NOMINAL)
    for v in t[:301]:
        k.update(v)
    state = k.state()
    assert state["pending"] is not None
    q = KalmanPredictor.from_state(msgpack.unpackb(msgpack.packb(state)))
    for v in t[301:]:
        assert q.predict() == k.predict()
        q.update(v)
        k.update(v)
    with pytest.raises(ValueError, match="pending"):
        KalmanPredictor.from_state({**state, "pending": [1.0]})
    with pytest.raises(ValueError, match="shifts"):
        KalmanPredictor.from_state({**state, "judged": 1.0, "shifts": 2.0})
    # A state written before the belief in shifts was kept: none seen, the suspect's lean none.
    old = {k: v for k, v in state.items() if k not in ("judged", "shifts")}
    old["pending"] = state["pending"][:2]
    assert KalmanPredictor.from_state(old).state()["judged"] == 0.0
    with pytest.raises(ValueError, match="format"):
        KalmanPredictor.from_state({**state, "format": "usmswitch.predictor.kalman/1"})
