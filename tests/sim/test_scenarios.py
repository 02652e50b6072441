"""The scenario suite: each scenario differs from the default rig as it says, reproducibly by seed."""

from __future__ import annotations

import math
import statistics

import pytest

from usmswitch.drivers.events import Direction
from usmswitch.sim import RigParams, UsmSwitchModel
from usmswitch.sim.scenarios import SCENARIOS, run_scenario

CYCLES = 1000


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_runs_reproducibly_with_a_floor_per_stroke(name: str) -> None:
    a = run_scenario(name, seed=4, cycles=CYCLES)
    b = run_scenario(name, seed=4, cycles=CYCLES)
    assert a.strokes == b.strokes
    assert len(a.strokes) == CYCLES
    assert [s.direction for s in a.strokes[:4]] == [Direction.ON, Direction.OFF] * 2
    assert all(0 < s.floor_ns < 0.15 * s.operating_ns for s in a.strokes)  # an outlier: 10 floors
    assert "idle_ns" not in a.strokes[0].conditions and a.strokes[2].conditions["idle_ns"] == 100_000_000
    assert run_scenario(name, seed=5, cycles=CYCLES).strokes != a.strokes


def test_the_default_floor_is_the_models_floor_at_the_strokes_conditions() -> None:
    run = run_scenario("default", seed=1, cycles=10)
    model = UsmSwitchModel(RigParams(), seed=1)
    for s in run.strokes:
        want = model.innovation_floor_ns(s.direction, temperature_c=s.conditions["temperature_c"])
        assert s.floor_ns == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize(
    ("name", "key", "before", "after"),
    [("frequency-step", "frequency_hz", 40_000.0, 40_500.0), ("voltage-step", "voltage_v", 500.0, 450.0)],
)
def test_a_drive_step_half_way_is_reported_in_the_conditions(
    name: str, key: str, before: float, after: float
):
    run = run_scenario(name, seed=2, cycles=CYCLES)
    assert run.step_cycle == CYCLES // 2
    assert {s.conditions[key] for s in run.strokes if s.cycle < run.step_cycle} == {before}
    assert {s.conditions[key] for s in run.strokes if s.cycle >= run.step_cycle} == {after}
    # The stroke time jumps at the step by far more than a stroke's floor.
    pre = statistics.mean(s.operating_ns for s in run.strokes[run.step_cycle - 20 : run.step_cycle])
    post = statistics.mean(s.operating_ns for s in run.strokes[run.step_cycle : run.step_cycle + 20])
    assert abs(post - pre) > 5 * run.strokes[0].floor_ns


def test_the_unreported_level_shift_and_the_noise_scenarios() -> None:
    shift = run_scenario("shift-noise4", seed=3, cycles=CYCLES)
    assert shift.step_cycle == CYCLES // 2
    drive = {(s.conditions["frequency_hz"], s.conditions["voltage_v"]) for s in shift.strokes}
    assert drive == {(40_000.0, 500.0)}  # the shift is not in the conditions
    pre = statistics.mean(s.operating_ns for s in shift.strokes[shift.step_cycle - 40 : shift.step_cycle])
    post = statistics.mean(s.operating_ns for s in shift.strokes[shift.step_cycle : shift.step_cycle + 40])
    assert post - pre > 0.01 * pre  # 0.2 mm more of a 5 mm stroke
    base, n4, n8 = (run_scenario(n, seed=3, cycles=CYCLES) for n in ("default", "noise4", "noise8"))
    assert base.strokes[0].floor_ns < n4.strokes[0].floor_ns < n8.strokes[0].floor_ns


def test_temperature_rises_and_idle_pauses_cool_the_motor() -> None:
    warm = run_scenario("temperature", seed=1, cycles=CYCLES)
    assert warm.strokes[-1].conditions["temperature_c"] - warm.strokes[0].conditions["temperature_c"] > 19.0
    idle = run_scenario("idle-120s", seed=1, cycles=CYCLES)
    assert idle.after_idle == [500, 501]
    first = idle.strokes[500]
    assert first.conditions["idle_ns"] == 120_000_000_000 + 100_000_000
    assert first.conditions["temperature_c"] < idle.strokes[499].conditions["temperature_c"] - 0.3


def test_an_unknown_scenario_is_named() -> None:
    with pytest.raises(KeyError, match="'storm'"):
        run_scenario("storm")


def test_outliers_are_the_default_rig_with_strokes_10_floors_off() -> None:
    base, hit = run_scenario("default", seed=6, cycles=4000), run_scenario("outliers", seed=6, cycles=4000)
    off = [(a, b) for a, b in zip(base.strokes, hit.strokes, strict=True) if a != b]
    assert 8 <= len(off) <= 30  # ~1 in 250
    for a, b in off:
        assert abs(abs(b.operating_ns - a.operating_ns) - 10 * a.floor_ns) <= 1
        assert b.floor_ns == pytest.approx(a.floor_ns * 101**0.5)
    assert {b.operating_ns > a.operating_ns for a, b in off} == {True, False}


@pytest.mark.parametrize("name", ["random-walk", "ar-0.3", "random-walk-fast"])
def test_a_bare_processs_floor_is_what_its_own_kalman_filter_reaches(name: str) -> None:
    # The exact filter of the process (in ln t, knowing phi, q, r and the mean) errs by the floor.
    pr = SCENARIOS[name].process
    assert pr is not None
    run = run_scenario(name, seed=3, cycles=8000)
    phi = min(pr.phi, 1.0)
    q, r = pr.innovation_sd**2, pr.white**2
    f, var = [0.0, 0.0], [pr.std**2 if phi < 1 else 0.0] * 2
    se = sf = 0.0
    for s in run.strokes:
        d = s.direction
        fp, vp = phi * f[d], phi * phi * var[d] + q
        pred = pr.mean_ns * math.exp(fp)
        if s.cycle >= 400:
            se += (s.operating_ns - pred) ** 2
            sf += s.floor_ns**2
        y = math.log(s.operating_ns / pr.mean_ns)
        k = vp / (vp + r)
        f[d], var[d] = fp + k * (y - fp), (1 - k) * vp
    assert math.sqrt(se / sf) == pytest.approx(1.0, abs=0.03)


def test_level_shifts_record_their_jumps_and_count_them_in_the_floor() -> None:
    run = run_scenario("level-shifts", seed=2, cycles=4000)
    assert 4 <= len(run.jumps) <= 25  # ~1 in 400 per direction
    usual = statistics.median(s.floor_ns for s in run.strokes)
    for j in run.jumps:
        assert run.strokes[j].floor_ns > 3 * usual
    assert sum(s.floor_ns > 3 * usual for s in run.strokes) == len(run.jumps)
