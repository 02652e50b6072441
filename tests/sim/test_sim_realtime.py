"""SimDaq on the wall clock: events at their instants, and stop() from another thread."""

from __future__ import annotations

import threading
import time

import pytest

from usmswitch.drivers import Direction, EventKind, MonotonicClock
from usmswitch.sim import SimDaq

pytestmark = pytest.mark.realtime


def test_events_arrive_at_their_wall_clock_instants():
    daq = SimDaq(realtime=True, seed=4)
    daq.open()
    assert isinstance(daq.clock, MonotonicClock)
    late_ns = []
    direction = Direction.ON
    cpu0, wall0 = time.process_time_ns(), time.monotonic_ns()
    for _ in range(8):  # ~100 ms of strokes
        daq.arm(direction, 500_000)
        cmd = daq.command()
        assert cmd.t_start_ns >= cmd.t_cmd_ns + 500_000
        while True:
            ev = daq.recv(50_000_000)
            got = time.monotonic_ns()
            assert ev is not None
            late_ns.append(got - ev.t_ns)
            if ev.kind is EventKind.EDGE and ev.level == 1:
                break
        direction = direction.opposite
    cpu_ns, wall_ns = time.process_time_ns() - cpu0, time.monotonic_ns() - wall0
    daq.close()
    # recv waits without spinning (only command()'s last ~0.3 ms before each start spins).
    assert cpu_ns < 0.5 * wall_ns, (cpu_ns, wall_ns)
    assert min(late_ns) >= -1_000  # never early (clock read granularity aside)
    # How late (within 1 ms of this machine's own wake-up lateness) is a speed target, measured by
    # benchmarks/bench_sim.py: beside make test's load a timed bound here failed on the machine's
    # moment (a p90 of 6.9 ms read against 6.6 ms allowed from a sleep measured just after).


def test_recv_times_out_in_real_time():
    daq = SimDaq(realtime=True)
    daq.open()
    t0 = time.monotonic_ns()
    assert daq.recv(20_000_000) is None
    assert 20_000_000 <= time.monotonic_ns() - t0 < 200_000_000
    assert daq.recv(None) is None  # nothing scheduled, no drive on: nothing can come


def test_stop_from_another_thread_wakes_a_waiting_recv():
    daq = SimDaq(realtime=True, seed=6)
    daq.open()
    daq.inject("stall")
    daq.arm(Direction.ON, 0)
    daq.command()
    assert daq.recv(0).kind is EventKind.START
    assert daq.recv(None).kind is EventKind.EDGE  # departed; it will never arrive
    stopped_at = []

    def estop() -> None:
        stopped_at.append(time.monotonic_ns())
        daq.stop("estop")

    timer = threading.Timer(0.05, estop)
    timer.start()
    try:
        ev = daq.recv(None)  # blocks: a held drive can only end by stop()
        woke = time.monotonic_ns()
    finally:
        timer.cancel()
    assert ev.kind is EventKind.STOP and ev.detail == "estop"
    assert woke - stopped_at[0] < 20_000_000
    assert daq.levels() == (0, 0)
    daq.close()


def test_a_recv_waiting_in_another_thread_sees_a_new_stroke():
    daq = SimDaq(realtime=True, seed=8)
    daq.open()
    got = []

    def consume() -> None:
        while (ev := daq.recv(200_000_000)) is not None:
            got.append((ev, time.monotonic_ns()))
            if ev.kind is EventKind.EDGE and ev.level == 1:
                return

    reader = threading.Thread(target=consume)
    reader.start()
    time.sleep(0.02)  # the reader is now waiting, with nothing scheduled
    daq.arm(Direction.ON, 0)
    daq.command()
    reader.join(1.0)
    assert not reader.is_alive()
    kinds = [ev.kind for ev, _ in got]
    assert kinds == [EventKind.START, EventKind.EDGE, EventKind.EDGE]
    arrive, seen = got[-1]
    assert seen - arrive.t_ns < 20_000_000  # delivered at its instant, not at the 200 ms deadline
    daq.close()
