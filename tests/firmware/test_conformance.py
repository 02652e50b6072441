"""One conformance suite for both MCU implementations, so they cannot drift apart:
the firmware in simavr (lockstep, emulated time) and sim/mcu_emulator.py (real time)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from avrsim import FirmwareDevice, Lockstep, since_us

from usmswitch.drivers import mcu_protocol as mp
from usmswitch.drivers.mcu_protocol import FrameDecoder, Message, cobs_encode, crc16, encode_frame
from usmswitch.sim.mcu_emulator import McuEmulator

U32 = 1 << 32


class PythonDevice:
    """sim/mcu_emulator.py behind the same face as FirmwareDevice."""

    def __init__(self, **kw: object) -> None:
        # the firmware's protocol version (the host's PROTOCOL_MINOR is the emulator's default)
        kw.setdefault("minor", mp.LATEST_MINOR)
        self.emu = McuEmulator(seed=1, **kw)  # type: ignore[arg-type]
        self._buf = bytearray()
        self._lock = threading.Lock()
        self.emu.attach(self._out)
        self.emu.start()
        self.decoder = FrameDecoder()

    def _out(self, data: bytes) -> None:
        with self._lock:
            self._buf += data

    def write(self, data: bytes) -> None:
        self.emu.receive(data)

    def send(self, msg: Message, seq: int) -> None:
        self.write(encode_frame(msg, seq))

    def run(self, us: int) -> list[tuple[int, Message]]:
        time.sleep(us / 1e6)
        self._settle()
        with self._lock:
            data, self._buf = bytes(self._buf), bytearray()
        return self.decoder.feed(data)

    def _settle(self) -> None:
        """What the chip would have done by now, done: the bytes written to it handled at the
        instants they were written and its due timers run, in time order. Its thread, woken late on
        a loaded machine, is not the chip's clock (simavr's lockstep waits for the chip; this
        emulator runs on the wall's), so this does not wait for it."""
        self.emu.catch_up()

    def close(self) -> None:
        self.emu.stop()

    def stall(self) -> None:
        self.emu.inject_stall()

    def bounce(self) -> None:
        self.emu.inject_bounce()

    def power_cycle(self) -> list[tuple[int, Message]]:
        self.emu.power_cycle()
        return self.run(2000)


class Firmware(FirmwareDevice):
    def close(self) -> None:
        self.sim.close()

    def stall(self) -> None:
        self.sim.command("stall")

    def bounce(self) -> None:
        self.sim.command("bounce")

    def power_cycle(self) -> list[tuple[int, Message]]:
        self.sim.command("replug")  # a power-on reset (lockstep has no pty to unplug)
        return self.run(2000)  # the firmware's start-up: bytes before its UART is on are lost


Device = Firmware | PythonDevice
WRAP_START_US = U32 - 32768  # one timer period (the harness takes whole ones) before the wrap


@pytest.fixture(params=["firmware", "python"])
def make_device(request: pytest.FixtureRequest) -> Iterator[Callable[..., Device]]:
    """Build the device under test; `clock_start_us` starts its clock there (near the wrap)."""
    made: list[Device] = []

    def make(clock_start_us: int = 0) -> Device:
        dev: Device
        if request.param == "firmware":
            avrsim: Path = request.getfixturevalue("avrsim")
            args = ["--clock-start-us", str(clock_start_us)] if clock_start_us else []
            dev = Firmware(Lockstep(avrsim, avrsim.parent / "usmswitch.elf", *args))
        else:
            dev = PythonDevice(clock_start_us=clock_start_us)
        made.append(dev)
        return dev

    yield make
    for dev in made:
        dev.close()


@pytest.fixture
def device(make_device: Callable[..., Device]) -> Device:
    return make_device()


def _hello(dev: Device, major: int = 1, watchdog_ms: int = 500, minor: int = 0) -> mp.HelloAck:
    dev.write(b"\x00")
    dev.send(mp.Hello(major, minor, watchdog_ms), 0)
    got = [(seq, m) for seq, m in dev.run(5000) if not isinstance(m, mp.Boot)]  # BOOT: at start-up
    assert len(got) == 1 and got[0][0] == 0 and isinstance(got[0][1], mp.HelloAck), got
    return got[0][1]


def _msgs(got: list[tuple[int, Message]]) -> list[Message]:
    return [m for _, m in got]


def test_handshake_and_versions(device: Device) -> None:
    ack = _hello(device)  # a 1.0 host: the 1.0 layout, no reset cause
    assert (ack.major, ack.minor, ack.caps, ack.fw_version, ack.max_delay_us) == (1, 0, 31, 0x0102, 1_000_000)
    assert ack.reset_cause == 0
    device.send(mp.Ping(7), 1)
    (pong,) = _msgs(device.run(3000))
    assert isinstance(pong, mp.Pong) and pong.token == 7 and pong.state & mp.StateFlags.SYNCED
    assert pong.state & mp.StateFlags.SENSOR_A and (pong.rx_errors, pong.rx_lost) == (0, 0)
    # another major version: a HELLO_ACK, then NOT_SYNCED for every request
    _hello(device, major=2)
    device.send(mp.Arm(1, 0, 1000, 100_000), 1)
    (ack2,) = _msgs(device.run(3000))
    assert isinstance(ack2, mp.Ack) and ack2.status == mp.Status.NOT_SYNCED and ack2.stroke == 0


def test_boot_and_the_reset_cause(device: Device) -> None:
    """1.1: BOOT as it starts, unasked, and HELLO_ACK's reset cause: power-on, also after a
    power cycle."""
    (boot,) = _msgs(device.run(3000))
    assert boot == mp.Boot(int(mp.ResetCause.POWER_ON), 0x0102)
    ack = _hello(device, minor=1)
    assert (ack.minor, ack.reset_cause) == (1, mp.ResetCause.POWER_ON)
    assert _msgs(device.power_cycle()) == [mp.Boot(int(mp.ResetCause.POWER_ON), 0x0102)]
    ack = _hello(device, minor=1)
    assert (ack.minor, ack.reset_cause) == (1, mp.ResetCause.POWER_ON)


def test_arm_checks_and_command_refusals(device: Device) -> None:
    hello = _hello(device)
    now = hello.t_us
    device.send(mp.Arm(1, 2, 1000, 100_000), 1)  # bad direction
    device.send(mp.Arm(1, 0, 1_000_001, 100_000), 2)  # over max_delay_us
    device.send(mp.Arm(1, 0, 1000, 999), 3)  # timeout under 1 ms
    device.send(mp.Command(1, now, 1), 4)  # nothing armed
    device.send(mp.Arm(1, 0, 1_000_000, 100_000), 5)  # the maximum delay is accepted
    device.send(mp.Command(1, (now + 3_000_000) % U32, 1), 6)  # 3 s away: BAD_TIME
    got = _msgs(device.run(5000))
    assert [(m.acked_seq, m.status) for m in got if isinstance(m, mp.Ack)] == [
        (1, mp.Status.BAD_ARG),
        (2, mp.Status.BAD_ARG),
        (3, mp.Status.BAD_ARG),
        (4, mp.Status.NOT_ARMED),
        (5, mp.Status.OK),
        (6, mp.Status.BAD_TIME),
    ]


def test_retransmitted_command_and_late_start(device: Device) -> None:
    t0 = time.monotonic()  # before the HELLO: its stamp is where the ~20 ms is counted from
    hello = _hello(device)
    device.send(mp.Arm(3, 0, 1000, 100_000), 1)
    t_cmd = (hello.t_us - 20_000) % U32  # 20 ms in the past: the start is late by ~19 ms
    device.send(mp.Command(3, t_cmd, 1), 2)
    device.send(mp.Command(3, (t_cmd + 5) % U32, 1), 3)  # a retransmission: the original instant
    # ~19 ms, and as much again as the COMMAND took to reach a device whose clock runs on the
    # wall's (the Python emulator on a loaded machine; in lockstep the chip waits for it).
    slack_us = int((time.monotonic() - t0) * 1e6)
    got = _msgs(device.run(40_000))
    acks = [m for m in got if isinstance(m, mp.Ack)]
    assert [(a.acked_seq, a.status, a.t_us) for a in acks[1:]] == [(2, 0, t_cmd), (3, 0, t_cmd)]
    (start,) = [m for m in got if isinstance(m, mp.Start)]
    assert 18_000 < start.late_us < 25_000 + slack_us, (start.late_us, slack_us)
    (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
    assert stroke.flags & mp.StrokeFlags.LATE and stroke.flags & mp.StrokeFlags.ARRIVED


def test_a_start_later_than_its_stall_limit_still_runs_its_stroke(device: Device) -> None:
    """A COMMAND that comes more than the stall limit after its due instant (a host held up): the
    drive goes on at once, flagged late, and the limit runs from there. Counted from the due
    instant, the firmware cut such a stroke as a stall a frame's time after it went on."""
    hello = _hello(device, watchdog_ms=5000)
    device.send(mp.Arm(4, 0, 1000, 30_000), 1)  # a stall limit of 30 ms
    t_cmd = (hello.t_us - 60_000) % U32  # due 59 ms ago: late by twice the limit
    device.send(mp.Command(4, t_cmd, 1), 2)
    got = _msgs(device.run(40_000))
    (start,) = [m for m in got if isinstance(m, mp.Start)]
    assert start.late_us > 30_000, start
    assert not [m for m in got if isinstance(m, mp.Fault)], got
    (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
    assert stroke.flags & mp.StrokeFlags.ARRIVED and stroke.flags & mp.StrokeFlags.LATE, stroke
    assert not stroke.flags & mp.StrokeFlags.STALL, stroke


def test_requests_during_a_stroke_are_busy(device: Device) -> None:
    _hello(device, watchdog_ms=5000)
    device.send(mp.Arm(1, 0, 1000, 100_000), 1)
    device.send(mp.Command(1, 0, 0), 2)
    first = _msgs(device.run(4000))  # started 1 ms in: about 3 ms into a stroke of 8 ms or more
    kinds = [type(m).__name__ for m in first]
    assert "Start" in kinds and "Stroke" not in kinds, kinds
    device.send(mp.Arm(2, 1, 1000, 100_000), 3)
    device.send(mp.Command(2, 0, 0), 4)
    got = _msgs(device.run(30_000))
    assert [(m.acked_seq, m.status, m.stroke) for m in got if isinstance(m, mp.Ack)] == [
        (3, mp.Status.BUSY, 2),
        (4, mp.Status.BUSY, 2),
    ]
    (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
    assert stroke.stroke == 1 and stroke.flags & mp.StrokeFlags.ARRIVED  # the running one goes on


def test_watchdog_stops_a_stroke(device: Device) -> None:
    hello = _hello(device, watchdog_ms=20)
    device.send(mp.Arm(4, 0, 200_000, 100_000), 1)  # starts 200 ms on: the watchdog acts first
    device.send(mp.Command(4, hello.t_us, 0), 2)
    got = _msgs(device.run(60_000))
    kinds = [type(m).__name__ for m in got]
    assert kinds[:2] == ["Ack", "Ack"] and "Start" not in kinds
    i = kinds.index("Fault")
    assert kinds[i : i + 3] == ["Fault", "Stroke", "Stopped"]
    assert got[i].code == mp.DeviceFault.HOST_SILENT and got[i].detail == 20
    # on time: 20 ms after the last host frame (the COMMAND, acked at its receipt), not a poll later
    assert 20_000 < (got[i].t_us - got[1].t_us) % U32 <= 23_000, (got[1], got[i])
    assert got[i + 2].reason == mp.StopReason.WATCHDOG and got[i + 1].flags & mp.StrokeFlags.WATCHDOG
    device.send(mp.Arm(5, 0, 0, 100_000), 3)
    (ack,) = _msgs(device.run(3000))
    assert ack.status == mp.Status.NOT_SYNCED


def test_unknown_type_and_bad_frames(device: Device) -> None:
    _hello(device)
    device.send(mp.Pong(1, 2, 3, 4, 5), 1)  # a device-side type sent to the device
    device.write(b"\x05\x01\x02\x03\x04\x00")  # COBS fine, CRC wrong
    device.write(b"\x11" * 80 + b"\x00")  # over-long
    device.write(_raw_frame(0x06, 5, b"\x01\x02\x03"))  # a type of a newer minor version
    device.send(mp.Ping(9), 7)  # seq 2..4 and 6 missing
    got = _msgs(device.run(5000))
    assert isinstance(got[0], mp.Ack) and got[0].status == mp.Status.UNKNOWN_TYPE
    assert (got[1].acked_type, got[1].acked_seq, got[1].status) == (0x06, 5, mp.Status.UNKNOWN_TYPE)
    assert isinstance(got[2], mp.Pong) and (got[2].rx_errors, got[2].rx_lost) == (2, 4)


def _raw_frame(mtype: int, seq: int, body: bytes) -> bytes:
    payload = bytes([mtype]) + seq.to_bytes(2, "little") + body
    return cobs_encode(payload + crc16(payload).to_bytes(2, "little")) + b"\x00"


def _stroke(dev: Device, stroke: int, direction: int, seq: int, delay_us: int = 1000) -> list[Message]:
    """ARM and COMMAND (at arrival) one stroke, run 40 ms, return what the device sent."""
    dev.send(mp.Arm(stroke, direction, delay_us, 100_000), seq)
    dev.send(mp.Command(stroke, 0, 0), seq + 1)
    return _msgs(dev.run(40_000))


def test_stall_stops_the_drive(device: Device) -> None:
    _hello(device, watchdog_ms=5000)
    device.stall()
    device.send(mp.Arm(1, 0, 1000, 30_000), 1)  # device stall limit 30 ms from the start
    device.send(mp.Command(1, 0, 0), 2)
    got = _msgs(device.run(60_000))
    kinds = [type(m).__name__ for m in got]
    (start,) = [m for m in got if isinstance(m, mp.Start)]
    i = kinds.index("Fault")
    assert kinds[i:] == ["Fault", "Stroke", "Stopped"], kinds
    fault, stroke, stopped = got[i:]
    assert fault.code == mp.DeviceFault.STALL and fault.detail == 30
    assert stroke.flags & mp.StrokeFlags.STALL and not stroke.flags & mp.StrokeFlags.ARRIVED
    assert stopped.reason == mp.StopReason.STALL
    assert 30_000 <= (stopped.t_us - start.t_us) % U32 <= 31_000  # on time
    # the session goes on: the next stroke runs (from where the jam left the mover)
    device.send(mp.Ping(1), 3)
    (pong,) = _msgs(device.run(2000))
    assert pong.state & mp.StateFlags.SYNCED and not pong.state & mp.StateFlags.DRIVE_ON


def test_a_start_away_from_the_source_sensor_is_said(device: Device) -> None:
    """1.2: a stroke that starts with its source sensor not active (a jam left the mover between
    the sensors) runs, and a FAULT SENSORS (detail: the sensors active, none here) says so after
    its START; a 1.1 session is not told."""
    _hello(device, watchdog_ms=5000, minor=2)
    device.stall()
    got = _stroke(device, 1, 0, 1, delay_us=1000)
    got += _msgs(device.run(100_000))  # the jammed stroke's own stall limit: 100 ms
    assert any(isinstance(m, mp.Fault) and m.code == mp.DeviceFault.STALL for m in got), got
    got = _stroke(device, 2, 1, 3)  # back to A, from half way
    kinds = [type(m).__name__ for m in got]
    i = kinds.index("Start")
    assert kinds[i + 1] == "Fault" and got[i + 1].code == mp.DeviceFault.SENSORS and got[i + 1].detail == 0, (
        got
    )
    (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
    assert stroke.flags & mp.StrokeFlags.ARRIVED and not stroke.flags & mp.StrokeFlags.DEPARTED
    _hello(device, watchdog_ms=5000, minor=1)  # a 1.1 host: the same start, not said
    device.stall()
    _msgs(device.run(2000))
    got = _stroke(device, 3, 0, 1) + _msgs(device.run(100_000))
    got = _stroke(device, 4, 1, 3)
    assert not [m for m in got if isinstance(m, mp.Fault)], got


def test_bounce_is_reported_edge_by_edge(device: Device) -> None:
    _hello(device, watchdog_ms=5000)
    device.bounce()
    got = _stroke(device, 1, 0, 1)
    edges = [(m.channel, m.level) for m in got if isinstance(m, mp.Edge)]
    # depart A, arrive B (the drive is cut), then B bounces: released and active again
    assert edges == [(0, 0), (1, 1), (1, 0), (1, 1)], edges
    (stopped,) = [m for m in got if isinstance(m, mp.Stopped)]
    b_edges = [m for m in got if isinstance(m, mp.Edge) and m.channel == 1]
    assert stopped.reason == mp.StopReason.ARRIVED and stopped.t_us == b_edges[0].t_us
    assert 0 < (b_edges[2].t_us - b_edges[0].t_us) % U32 < 1000  # the chatter is tens of us


@pytest.mark.parametrize("delay_us", [40_000, 1_000_000])
def test_delays_over_timer_periods_start_on_time(device: Device, delay_us: int) -> None:
    """Past one 16-bit period (32.768 ms at 0.5 us ticks), up to max_delay_us (30 periods): the
    start falls in the right period, on the tick."""
    hello = _hello(device, watchdog_ms=5000)
    t_cmd = (hello.t_us + 3000) % U32
    device.send(mp.Arm(1, 0, delay_us, 100_000), 1)
    device.send(mp.Command(1, t_cmd, 1), 2)
    got = _msgs(device.run(delay_us + 20_000))
    due = (t_cmd + delay_us) % U32
    (start,) = [m for m in got if isinstance(m, mp.Start)]
    assert start.late_us == 0 and abs(since_us(start.t_us, due)) <= 1, (start, due)
    (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
    assert stroke.flags & mp.StrokeFlags.ARRIVED and not stroke.flags & mp.StrokeFlags.LATE
    if isinstance(device, Firmware):  # the drive pin itself, from emulator cycles
        (on_us,) = [fw_us for level, _, fw_us in device.sim.drive if level == 1]
        assert abs(since_us(on_us, due)) <= 1, (on_us, due)


def test_clock_wrap_inside_a_stroke(make_device: Callable[..., Device]) -> None:
    for _ in range(5):
        dev = make_device(clock_start_us=WRAP_START_US)
        hello = _hello(dev, watchdog_ms=5000)
        assert WRAP_START_US <= hello.t_us < U32  # before the wrap
        # due 8 ms before the wrap, commanded for that instant (exact however long the COMMAND took
        # to come, if it came before), it arrives after the wrap
        dev.send(mp.Arm(1, 0, 1000, 100_000), 1)
        dev.send(mp.Command(1, U32 - 9000, 1), 2)
        got = _msgs(dev.run(40_000))
        (start,) = [m for m in got if isinstance(m, mp.Start)]
        (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
        if start.late_us == 0:
            break
        # The Python emulator's clock is the wall's: on a loaded machine its COMMAND came after
        # that instant (~20 ms after the HELLO_ACK; an immediate COMMAND of before had 8 ms, and
        # beside make run and two CPU hogs missed it 5 times running). Again, anew.
    assert U32 - 12_000 < start.t_us < U32 - 5000 and start.late_us == 0
    assert stroke.flags & mp.StrokeFlags.ARRIVED and stroke.t_arrive_us < 100_000  # after the wrap
    assert 8_000 < (stroke.t_arrive_us - stroke.t_start_us) % U32 < 14_000
    dev.send(mp.Ping(3), 3)
    (pong,) = _msgs(dev.run(2000))
    assert pong.t_us < 100_000 and pong.state & mp.StateFlags.SENSOR_B


def test_power_cycle_forgets_the_session(device: Device) -> None:
    hello = _hello(device, watchdog_ms=5000)
    device.send(mp.Arm(1, 0, 200_000, 100_000), 1)
    device.send(mp.Command(1, 0, 0), 2)  # due in 200 ms: the power goes first
    device.run(20_000)
    t_power = time.monotonic()
    device.power_cycle()
    device.send(mp.Ping(1), 3)
    device.send(mp.Arm(2, 0, 1000, 100_000), 4)
    got = _msgs(device.run(300_000))
    # Since power-on: at most what the wall took since (the Python emulator's clock is the wall's;
    # a loaded machine makes it tens of ms), while the old clock would read 20 ms and that more.
    since_power_us = max(20_000, int((time.monotonic() - t_power) * 1e6))
    assert [type(m).__name__ for m in got] == ["Pong", "Ack"], got  # no START: the stroke is gone
    pong, ack = got
    assert not pong.state & (mp.StateFlags.SYNCED | mp.StateFlags.ARMED | mp.StateFlags.DRIVE_ON)
    assert ack.status == mp.Status.NOT_SYNCED
    assert pong.t_us < hello.t_us + since_power_us, (pong, since_power_us)  # the clock restarted
    again = _hello(device)
    assert again.t_us > pong.t_us


def test_a_new_session_forgets_the_last_ones_stroke(device: Device) -> None:
    """A host restarted on a board that was not reset numbers its strokes from 1 again: after the
    second HELLO, stroke 1 is a new stroke and starts (issue 33: it was answered as a
    retransmission of the last session's stroke 1, never started, and the host saw a stall)."""
    _hello(device, watchdog_ms=5000, minor=2)
    got = _stroke(device, 1, 0, 1)  # A to B
    (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
    assert stroke.flags & mp.StrokeFlags.ARRIVED
    _hello(device, watchdog_ms=5000, minor=2)  # a new host: its sequence and stroke ids from scratch
    got = _stroke(device, 1, 1, 1)  # B to A, also numbered 1
    acks = [m for m in got if isinstance(m, mp.Ack)]
    assert [(a.acked_type, a.status) for a in acks] == [(mp.MsgType.ARM, 0), (mp.MsgType.COMMAND, 0)]
    assert since_us(acks[1].t_us, acks[0].t_us) >= 0  # its own command instant, not the old one's
    (start,) = [m for m in got if isinstance(m, mp.Start)]
    (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
    assert (start.stroke, start.direction) == (1, 1)
    assert stroke.stroke == 1 and stroke.direction == 1 and stroke.flags & mp.StrokeFlags.ARRIVED
