"""Issue 29, the MCU driver's checks of what the device says, in process: the clock rate, the bounded
event queue, and a property-based fuzz of valid-CRC frame sequences (hypothesis) asserting that no
exception escapes the driver, no stamp outside the band is delivered, memory stays bounded, and the
link and the strokes recover once the line is good again."""

from __future__ import annotations

import re
import time
from pathlib import Path

import faultmcu
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcu_rig import FAST, run_stroke, wait_for

from usmswitch.drivers import DaqError, Direction, EventKind, FaultCode
from usmswitch.drivers.mcu import STAMP_AHEAD_NS
from usmswitch.drivers.mcu_protocol import (
    U16_MOD,
    U32_MOD,
    Ack,
    Boot,
    Edge,
    Fault,
    HelloAck,
    Message,
    Pong,
    Start,
    Stopped,
    Stroke,
)
from usmswitch.drivers.serial_mcu import SerialMcuDaq
from usmswitch.sim import RigParams, UsmSwitchModel

MS = 1_000_000


def _open(port: Path, **kwargs: object) -> SerialMcuDaq:
    daq = SerialMcuDaq.from_spec(f"serial:{port}?reset_wait_ms=0", **{**FAST, **kwargs})  # type: ignore[arg-type]
    daq.open()
    return daq


def test_a_device_clock_rate_far_off_is_refused_naming_it(tmp_path: Path) -> None:
    """Item 3: a device whose clock runs 10 % fast (a wrong prescaler) passed; every stamp was 10 %
    off. Now the heartbeat finds it within a few round trips, the session is dropped with a FAULT
    that names the rate, and the handshakes after it are refused while the device runs on."""
    with faultmcu.plugged(tmp_path, seed=1, drift_ppm=100_000) as (emu, port), _open(port) as daq:
        assert wait_for(lambda: not daq.connected, 3.0)
        # A busy host may be silent past the device's watchdog first (its HOST_SILENT FAULT): the
        # session's end is the DISCONNECT.
        ev = daq.recv(500 * MS)
        while ev is not None and not (ev.kind is EventKind.FAULT and ev.fault is FaultCode.DISCONNECT):
            ev = daq.recv(500 * MS)
        assert ev is not None
        # The rate is measured over a few heartbeat round trips, each with the host's scheduling
        # jitter in it (CI read +9.856 % for the true +10 %, a host at load 6 +14.2 %): the message
        # must name a rate fast by about that much, far past the 0.5 % allowed.
        said = re.search(r"the device clock runs at (\d\.\d+) us per us \(\+(\d+\.\d+) %\)", ev.detail)
        assert said is not None, ev.detail
        assert 1.05 < float(said.group(1)) < 1.2 and 5.0 < float(said.group(2)) < 20.0, ev.detail
        assert wait_for(lambda: daq.link_stats()["handshake_failures"] >= 1, 3.0)
        assert not daq.connected
        with pytest.raises(DaqError):
            daq.arm(Direction.ON, MS)


def test_a_crystal_within_tolerance_is_taken(tmp_path: Path) -> None:
    with faultmcu.plugged(tmp_path, seed=2, drift_ppm=1000) as (emu, port), _open(port) as daq:
        time.sleep(0.3)
        assert daq.connected and daq.link_stats()["disconnects"] == 0
        assert run_stroke(daq, Direction.ON).events[-1].detail == "arrived"


def test_the_event_queue_is_bounded_and_an_overflow_in_a_stroke_is_a_fault(tmp_path: Path) -> None:
    """Item 4: the link thread's queue grew without bound while nothing read it (2.8 million events
    in 20 s). Now it keeps the newest max_queued_events: the oldest are dropped and counted, and a
    stroke in progress gets a SEQUENCE fault saying events were lost."""
    # A slow rig (a stroke of ~1 s): the flood is inside the stroke, after its start, whatever the
    # host's load. At 8 ms a stroke and the flood begun 35 ms before its start, beside make run and
    # two CPU hogs the queue lost nothing of the stroke's own before its STOP (loaded run 61).
    slow = UsmSwitchModel(RigParams(nominal_operating_ns=1000 * MS), seed=3)
    with (
        faultmcu.plugged(tmp_path, model=slow, seed=3) as (emu, port),
        _open(port, max_queued_events=64, stroke_timeout_ns=5000 * MS) as daq,
    ):
        daq.arm(Direction.ON, 1 * MS)
        commanded = daq.now_ns() + 5 * MS
        daq.command(commanded)
        while daq.now_ns() <= commanded + 1 * MS:  # past its start: the flood's drops are its own
            time.sleep(0.001)
        # Sensor B (not the mover's) says "released", again and again, until the queue overflows
        # (a busy host sends fewer a second).
        end = time.monotonic() + 5.0
        while daq.link_stats()["events_dropped"] == 0 and time.monotonic() < end:
            emu.flood(0.1, channel=1)
        assert wait_for(lambda: daq.link_stats()["events_dropped"] > 0, 2.0)
        assert len(daq._events) <= 64
        seen = []
        while (ev := daq.recv(5000 * MS)) is not None:
            seen.append(ev)
            if ev.kind is EventKind.STOP:
                break
        faults = [e for e in seen if e.kind is EventKind.FAULT]
        lost = [f for f in faults if f.fault is FaultCode.SEQUENCE and "events lost" in f.detail]
        assert lost, faults
        assert seen[-1].kind is EventKind.STOP and seen[-1].detail == "arrived", seen[-3:]
        # The next stroke is accounted whole again.
        daq.arm(Direction.OFF, 1 * MS)
        daq.command(daq.now_ns() + 5 * MS)
        after = []
        while (ev := daq.recv(5000 * MS)) is not None and ev.kind is not EventKind.STOP:
            after.append(ev)
        assert ev is not None and ev.detail == "arrived", after
        assert not [e for e in after if e.kind is EventKind.FAULT], after


def test_a_flood_still_queued_from_between_strokes_does_not_fault_the_next(tmp_path: Path) -> None:
    """The queue full of a flood that came between two strokes (nothing reads the driver then) as
    the next is commanded and runs: each of its own events pushes out a stale edge, stamped before
    its due start, which the stroke never had. No SEQUENCE fault: there was one, and a busy host
    that was still decoding a flood as the next stroke went faulted it (test_daemon_hw_checks'
    flood, stroke 6, in make test)."""
    with faultmcu.plugged(tmp_path, seed=3) as (emu, port), _open(port, max_queued_events=64) as daq:
        end = time.monotonic() + 5.0
        while daq.link_stats()["events_dropped"] == 0 and time.monotonic() < end:
            emu.flood(0.1, channel=1)  # sensor B (not the mover's) says "released", no stroke going
        assert wait_for(lambda: daq.link_stats()["events_dropped"] > 0, 2.0)
        time.sleep(0.1)  # the flood's last frames decoded: what the stroke drops is its own doing
        dropped = daq.link_stats()["events_dropped"]
        direction = Direction.OFF if emu.rig.sensors()[1] else Direction.ON
        daq.arm(direction, 1 * MS)
        daq.command(daq.now_ns() + 2 * MS)
        # The stroke runs while nothing reads: its START, edges and STOP each push a stale edge out.
        assert wait_for(lambda: daq.link_stats()["events_dropped"] >= dropped + 3, 5.0)
        seen = []
        while (ev := daq.recv(1000 * MS)) is not None:
            seen.append(ev)
            if ev.kind is EventKind.STOP:
                break
        not_edges = [e for e in seen if e.kind is not EventKind.EDGE]
        assert not [e for e in seen if e.kind is EventKind.FAULT], not_edges
        assert not_edges[-1].kind is EventKind.STOP and not_edges[-1].detail == "arrived", not_edges


# -- the fuzz ---------------------------------------------------------------------------------------

# Offsets from the device clock (us): inside the band, just outside, far out, across the wrap.
_OFFSETS = st.sampled_from(
    [
        0,
        -1,
        -500,
        -50_000,
        -399_000,
        -450_000,
        3_000,
        6_000,
        10_000_000,
        -10_000_000,
        2**31 - 1,
        2**31,
        2**32 - 2,
    ]
)
_U32 = st.integers(0, U32_MOD - 1)
_U16 = st.integers(0, U16_MOD - 1)


@st.composite
def _frame(draw: st.DrawFn) -> tuple[str, tuple[int, ...]]:
    kind = draw(
        st.sampled_from(
            ["edge", "edge", "start", "stopped", "stroke", "fault", "pong", "ack", "hello", "boot"]
        )
    )
    off = draw(_OFFSETS)
    sid = draw(st.integers(0, 2))  # this stroke, the next one, any
    return kind, (off, draw(st.integers(0, 3)), draw(st.integers(0, 2)), draw(_U16), draw(_U32), sid)


def _message(kind: str, args: tuple[int, ...], now_us: int, stroke: int) -> Message:
    off, a, b, x16, x32, which = args
    t = (now_us + off) % U32_MOD
    sid = (stroke, (stroke + 1) % U16_MOD, x16)[which]
    if kind == "edge":
        return Edge(a, b, t)
    if kind == "start":
        return Start(sid, b, t, x32 % 5000)
    if kind == "stopped":
        return Stopped(sid, a, t)
    if kind == "stroke":
        return Stroke(sid, b, x16 & 0x3F, t, t, (t + 1000) % U32_MOD, (t + 9000) % U32_MOD)
    if kind == "fault":
        return Fault(a + 1, t, x16)
    if kind == "pong":
        return Pong(a + 1, t, x16 & 0x1F, 0, 0)
    if kind == "ack":
        return Ack(a + 1, x16, b, sid, t)
    if kind == "hello":
        return HelloAck(1, 1, 31, 0x0101, t, x32, 0)
    return Boot(8 if a == 0 else 1, 0x0101)


def test_fuzz_valid_frames_never_break_the_driver_and_it_recovers(tmp_path: Path) -> None:
    """Sequences of frames with valid CRCs (stamps in and out of the band, other strokes' ids,
    restarts, PONGs and ACKs nobody asked for) said during a stroke: the driver raises nothing but
    DaqError, delivers no stamp outside the band, keeps its queues bounded, and once the line is
    good again the link is up and a stroke is exact."""
    import resource

    emu, link, port = faultmcu.plug(tmp_path, seed=5)
    daq = _open(port, max_queued_events=2000)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    examples = [0]

    @settings(
        max_examples=25,
        deadline=None,
        derandomize=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    )
    @given(st.lists(_frame(), min_size=1, max_size=12), st.booleans())
    def one(frames: list[tuple[str, tuple[int, ...]]], boot_ok: bool) -> None:
        examples[0] += 1
        try:
            direction = Direction.OFF if emu.rig.sensors()[1] else Direction.ON
            daq.arm(direction, 2 * MS)
            daq.command(daq.now_ns() + 5 * MS)
        except DaqError:
            pass  # a session the last example's BOOT ended: the fuzz goes on, the recovery is checked
        stroke = daq._stroke_id
        for kind, args in frames:
            if kind == "boot" and not boot_ok:
                continue
            emu.say(_message(kind, args, emu.device_us(), stroke))
        end = time.monotonic() + 0.08
        while time.monotonic() < end:
            try:
                ev = daq.recv(10 * MS)
            except DaqError:
                continue
            if ev is None:
                continue
            now = daq.now_ns()
            # A delivered stamp is within the band the driver keeps (its host-stamped events are now).
            assert (
                now - 2 * daq.link_timeout_ns - daq.stroke_timeout_ns
                <= ev.t_ns
                <= now + STAMP_AHEAD_NS + 5 * MS
            ), (
                ev,
                now,
            )
        assert len(daq._events) <= daq.max_queued_events
        assert daq.strokes.ctx is None or len(daq.strokes.ctx.held) <= 64

    try:
        one()
        # The line is good again: the link comes back on its own, and a stroke is exact.
        assert wait_for(lambda: daq.connected, 5.0)
        while daq.recv(50 * MS) is not None:
            pass
        direction = Direction.OFF if emu.rig.sensors()[1] else Direction.ON
        seen = run_stroke(daq, direction)
        assert seen.events[-1].detail == "arrived", seen.events
        true_ns = emu.log[-1].t_arrive_ns - emu.log[-1].t_start_ns
        assert abs(seen.edge(direction.dest, 1).t_ns - seen.start.t_ns - true_ns) <= 2_000
    finally:
        daq.close()
        link.close()
        emu.stop()
    assert examples[0] >= 10
    grown_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0
    assert grown_kb < 50_000, grown_kb


def test_an_edge_older_than_the_sensor_snapshot_does_not_overwrite_it(tmp_path: Path) -> None:
    """Issue 34 item 9: an EDGE stamped in the past overwrote the newer PONG snapshot of the sensors
    (a `switch` was then refused as "already rests at sensor ..."). Now an edge moves the levels
    only when it is newer than what they are as of; a newer one still does."""
    # A slow heartbeat: the newer edge's levels stand until the next PONG, long enough to be seen.
    slow = {"heartbeat_ns": 400 * MS, "link_timeout_ns": 2000 * MS, "watchdog_ms": 1500}
    with faultmcu.plugged(tmp_path, seed=41) as (emu, port), _open(port, **slow) as daq:
        assert wait_for(lambda: daq.levels() is not None)
        time.sleep(0.05)
        assert daq.levels() == (1, 0)
        emu.say(Edge(0, 0, (emu.device_us() - 100_000) % U32_MOD))  # "A released", 100 ms ago
        time.sleep(0.01)
        assert daq.levels() == (1, 0)
        emu.say(Edge(1, 1, emu.device_us()))  # "B active", now: taken until the next PONG
        assert wait_for(lambda: daq.levels() == (1, 1), 0.5)


def test_a_stroke_after_a_slow_handshake_loses_none_of_its_events(tmp_path: Path) -> None:
    """Loaded run 23: the first stroke after a handshake whose replies reached the host late (a busy
    host reads its port late) came without its START and departure. The clock stood on samples
    whose round trips were all on the way back, so it ran half a round trip behind the device; the
    link took the stroke's stamps within that uncertainty, and `recv` then dropped them as from the
    future, against a bound without it. Now `recv` allows the driver clock's own uncertainty."""
    # A slow heartbeat: the clock stands on the handshake's samples through the stroke.
    slow = {"heartbeat_ns": 1000 * MS, "link_timeout_ns": 5000 * MS, "watchdog_ms": 4000}
    with faultmcu.plugged(tmp_path, seed=42) as (emu, port):
        emu.latency_ns = 20 * MS  # every reply 20 ms on its way back (under the 25 ms reply timeout)
        with _open(port, **slow) as daq:
            assert wait_for(lambda: daq.levels() is not None)  # the session's first PONG, as slow
            emu.behave()  # then a quick line: the stroke's frames are read as they come
            ahead_us = emu.device_us() - daq.timeline.to_raw_us(daq.clock.now_ns())
            assert 8_000 <= ahead_us <= daq.timeline.err_ns(time.monotonic_ns()) // 1000, ahead_us
            seen = run_stroke(daq, Direction.ON)
            kinds = [e.kind for e in seen.events]
            assert kinds[0] is EventKind.START, kinds
            assert seen.edge(Direction.ON.source, 0).t_ns < seen.edge(Direction.ON.dest, 1).t_ns
            assert seen.events[-1].detail == "arrived" and daq.future_stamps == 0
