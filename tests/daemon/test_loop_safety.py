"""An estop or a shutdown is final: once acknowledged, no drive start follows, for every kind of driver.

Real time on the simulated rig (software-timed: the host waits for the start) and on the MCU
emulator over a pty (hardware-timed: the device waits); each test checks the rig itself (the sim's
and the emulator's count of started strokes), not only what the loop says.
"""

from __future__ import annotations

import random
import threading
import time
from pathlib import Path

import pytest

from usmswitch.daemon.loop import ControlLoop, LoopError, Mode, State
from usmswitch.drivers import Direction
from usmswitch.drivers.mcu_protocol import MsgType
from usmswitch.drivers.serial_mcu import SerialMcuDaq
from usmswitch.predictor import ARPredictor
from usmswitch.protocol.record import CycleRecord, Flag
from usmswitch.sim import SimDaq
from usmswitch.sim.mcu_emulator import McuEmulator, PtyLink

MS = 1_000_000
NOMINAL = 10_500_000

pytestmark = pytest.mark.realtime
# Short link timings (those of tests/drivers/mcu_rig.py) keep the MCU test quick.
FAST = {"heartbeat_ns": 20 * MS, "link_timeout_ns": 120 * MS, "watchdog_ms": 150}


def wait_for(pred, timeout_s: float = 3.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not pred():
        time.sleep(0.005)
    return pred()


def _loop(daq, **kw) -> tuple[ControlLoop, list[CycleRecord]]:
    daq.open()
    preds = [ARPredictor(order=1, window=100, model="paper", nominal_ns=NOMINAL) for _ in range(2)]
    recs: list[CycleRecord] = []
    kw.setdefault("target_ns", 12 * MS)
    return ControlLoop(daq, preds, sink=recs.append, **kw), recs


class Running:
    """The loop's run() in a thread, as the daemon runs it in its main thread."""

    def __init__(self, loop: ControlLoop) -> None:
        self.loop = loop
        self.thread = threading.Thread(target=loop.run, daemon=True)
        self.thread.start()

    def do(self, fn, timeout_s: float = 5.0):
        return self.loop.call(fn).result(timeout_s)

    def stop(self) -> None:
        self.loop.shutdown()
        self.thread.join(5)
        assert not self.thread.is_alive()


def test_estop_abandons_a_start_waiting_for_its_instant() -> None:
    """Open loop with a 5 s delay: an estop 50 ms in ends the wait; the drive never comes on."""
    daq = SimDaq(realtime=True, seed=1)
    loop, recs = _loop(daq, mode=Mode.OPEN, open_delay_ns=5_000 * MS)
    run = Running(loop)
    try:
        armed = threading.Event()
        arm = daq.arm
        daq.arm = lambda direction, delay_ns: (arm(direction, delay_ns), armed.set())
        stroke = loop.call(lambda: loop.switch(Direction.ON))
        # The stroke armed and waiting for its instant (the loop thread, descheduled on a busy
        # host, took it up past a fixed 50 ms and met the estop's FAULT first), then 50 ms in.
        assert armed.wait(10.0)
        time.sleep(0.05)
        loop.estop("test estop")
        assert daq.halted and daq.strokes == 0
        rec = stroke.result(1.0)  # not 5 s: the wait was abandoned
        assert rec.t_start_ns is None and rec.flags & Flag.ESTOP
        assert not rec.flags & Flag.STALL
        time.sleep(0.1)
        assert daq.strokes == 0
        assert wait_for(lambda: loop.state is State.FAULT)
        assert loop.fault_reason == "test estop"
        # Nothing starts until the fault is reset, not even a direct switch.
        with pytest.raises(LoopError, match="FAULT"):
            run.do(lambda: loop.switch(Direction.ON))
        run.do(loop.reset_fault)
        assert not daq.halted
    finally:
        run.stop()


def test_no_start_follows_an_acknowledged_estop_while_cycling() -> None:
    """40 estops at random instants of a 13 ms cycle: after each returns, the rig starts nothing."""
    daq = SimDaq(realtime=True, seed=2)
    loop, recs = _loop(daq)
    run = Running(loop)
    rng = random.Random(7)
    try:
        for _ in range(40):
            run.do(lambda: loop.start_cycling(13 * MS))
            time.sleep(rng.uniform(0.0, 0.04))
            loop.estop("estop")
            started = daq.strokes
            time.sleep(0.03)  # longer than a period: a scheduled start would have fired
            assert daq.strokes == started, "a stroke started after the estop was acknowledged"
            assert wait_for(lambda: loop.state is State.FAULT)
            run.do(loop.reset_fault)
        assert not any(r.flags & Flag.STALL for r in recs)
        assert all(r.t_start_ns is None or r.t_arrive_ns is not None or r.flags & Flag.ESTOP for r in recs)
    finally:
        run.stop()


def test_shutdown_during_a_long_delay_returns_at_once_and_records_an_abort() -> None:
    daq = SimDaq(realtime=True, seed=3)
    loop, recs = _loop(daq, target_ns=5_000 * MS)
    run = Running(loop)
    run.do(lambda: loop.start_cycling(6_000 * MS))
    time.sleep(0.05)
    t0 = time.monotonic()
    loop.shutdown()
    run.thread.join(2)
    assert not run.thread.is_alive() and time.monotonic() - t0 < 0.5
    assert daq.strokes == 0 and loop.state is State.STOPPED
    (rec,) = recs
    assert rec.flags & Flag.ABORTED and not rec.flags & (Flag.STALL | Flag.FAULT)


def test_shutdown_while_cycling_leaves_no_false_stall() -> None:
    for seed in range(6):
        daq = SimDaq(realtime=True, seed=seed)
        loop, recs = _loop(daq)
        run = Running(loop)
        run.do(lambda loop=loop: loop.start_cycling(14 * MS))
        time.sleep(0.05 + seed * 0.007)
        loop.shutdown()
        started = daq.strokes
        run.thread.join(2)
        assert daq.strokes == started
        assert not any(r.flags & (Flag.STALL | Flag.FAULT) for r in recs), [Flag(r.flags) for r in recs]
        assert len(recs) >= 3


def test_switch_toward_where_the_mover_rests_is_refused() -> None:
    """The mover starts at A (off): 'off' would push it into the end stop for the stroke timeout."""
    daq = SimDaq(seed=4)
    loop, recs = _loop(daq)
    with pytest.raises(LoopError, match="already rests at sensor A"):
        loop.switch(Direction.OFF)
    assert daq.strokes == 0 and recs == []
    loop.switch(Direction.ON)
    with pytest.raises(LoopError, match="already rests at sensor B"):
        loop.switch(Direction.ON)
    assert [r.flags & Flag.STALL for r in recs] == [0]


def test_targets_and_periods_that_overlap_commands_are_refused_while_cycling() -> None:
    daq = SimDaq(seed=5)
    loop, _ = _loop(daq)
    loop.start_cycling(50 * MS)
    with pytest.raises(LoopError, match="already cycling"):
        loop.start_cycling(50 * MS)
    with pytest.raises(ValueError, match="commands would overlap"):
        loop.set_target(60 * MS)
    assert loop.targets == [12 * MS, 12 * MS]
    with pytest.raises(ValueError, match="commands would overlap"):
        loop.set_mode(Mode.OPEN, 45 * MS)  # 45 ms + t_hat > 50 ms
    assert loop.mode is Mode.CLOSED
    warnings = loop.set_target(5 * MS)  # below the ~10.5 ms stroke: taken, but said
    assert warnings and "shorter than the predicted stroke" in warnings[0]
    loop.stop_cycling()
    # The period is checked against the predicted stroke, not only T.
    with pytest.raises(ValueError, match="max of T and t_hat"):
        loop.start_cycling(8 * MS)


@pytest.fixture
def mcu(tmp_path: Path):
    emu = McuEmulator(seed=3).start()
    link = PtyLink(emu, tmp_path / "usmswitch").plug()
    daq = SerialMcuDaq.from_spec(f"serial:{tmp_path / 'usmswitch'}", **FAST)
    yield emu, daq
    daq.close()
    link.close()
    emu.stop()


def test_estop_disarms_a_hardware_timed_stroke_before_it_is_acknowledged(mcu) -> None:
    """The device holds a 0.9 s delay after the command: the estop's STOP cancels it before returning."""
    emu, daq = mcu
    loop, recs = _loop(daq, mode=Mode.OPEN, open_delay_ns=900 * MS)
    run = Running(loop)
    try:
        stroke = loop.call(lambda: loop.switch(Direction.ON))
        assert wait_for(lambda: emu.received.get(MsgType.COMMAND, 0) >= 1)
        loop.estop("test estop")
        assert emu.strokes_started == 0
        rec = stroke.result(1.0)
        assert rec.flags & Flag.ESTOP and rec.t_arrive_ns is None
        time.sleep(1.0)  # past the instant the device would have started
        assert emu.strokes_started == 0
    finally:
        run.stop()
