"""The loop tells the predictors each stroke's conditions and re-plans the armed stroke when the drive
setting changes (issue 15)."""

from __future__ import annotations

from typing import Any

from usmswitch.daemon.loop import ControlLoop
from usmswitch.drivers import Direction
from usmswitch.predictor import ARPredictor, make_predictor
from usmswitch.protocol.record import CycleRecord
from usmswitch.sim import SimDaq

MS = 1_000_000


class Told(ARPredictor):
    """The paper's AR(1), keeping what the loop told it."""

    def __init__(self) -> None:
        super().__init__(order=1, window=100, nominal_ns=8 * MS)
        self.predicted: list[Any] = []
        self.updated: list[Any] = []

    def predict(self, conditions: Any = None) -> float:
        self.predicted.append(conditions)
        return super().predict(conditions)

    def update(self, t_ns: int, conditions: Any = None) -> None:
        self.updated.append(conditions)
        super().update(t_ns, conditions)


def test_predictors_are_told_temperature_frequency_and_voltage() -> None:
    daq = SimDaq(seed=2)
    daq.open()
    preds = [Told(), Told()]
    loop = ControlLoop(daq, preds, target_ns=12 * MS, sink=lambda rec: None)
    loop.run_cycles(40 * MS, 20)
    told = preds[0].updated
    assert len(told) == 10
    assert set(told[0]) == {"temperature_c", "frequency_hz", "voltage_v"}  # the first: no idle yet
    assert all(set(c) == {"temperature_c", "frequency_hz", "voltage_v", "idle_ns"} for c in told[1:])
    assert all(c["idle_ns"] == 80 * MS for c in told[1:])  # command to command, two periods
    # Planned ahead for the next command: its idle_ns is known before the stroke, as the update's.
    assert all(c is None or c.get("idle_ns") in (None, 80 * MS) for c in preds[0].predicted)
    assert sum(1 for c in preds[0].predicted if c and c.get("idle_ns") == 80 * MS) >= 9
    assert told[-1]["frequency_hz"] == 40_000.0 and told[-1]["voltage_v"] == 500.0
    assert told[-1]["temperature_c"] > told[0]["temperature_c"]  # the motor warms as it works


def test_a_drive_change_re_plans_the_armed_stroke() -> None:
    daq = SimDaq(seed=2)
    daq.open()
    preds = [make_predictor("kalman", nominal_ns=8 * MS) for _ in range(2)]
    recs: list[CycleRecord] = []
    loop = ControlLoop(daq, preds, target_ns=12 * MS, sink=recs.append)
    loop.run_cycles(40 * MS, 400)
    armed = loop._plan
    assert armed is not None and armed.direction is Direction.ON
    # Teach both predictors how the voltage acts: one 500 -> 450 -> 500 round, 40 strokes each.
    for v in (450.0, 500.0):
        daq.set_drive(voltage_vpp=v)
        loop.refresh_conditions()
        loop.run_cycles(40 * MS, 80)
    before = loop._plan
    assert before is not None
    daq.set_drive(voltage_vpp=450.0)
    loop.refresh_conditions()  # what set_drive does on the loop thread
    after = loop._plan
    assert after is not None and after is not before and after.direction is before.direction
    assert after.t_hat_ns > before.t_hat_ns * 1.05  # slower at a lower voltage, known before the stroke
    loop.run_cycles(40 * MS, 2)
    first = recs[-2]
    assert abs(first.operating_ns - first.t_hat_ns) < 400_000  # the step's first stroke, planned for it
    kept = loop._plan
    loop.refresh_conditions()
    assert loop._plan is kept  # the drive did not change: no re-plan
