"""The scenario suite: each scenario differs from the default rig as it says, reproducibly by seed."""

from __future__ import annotations

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
