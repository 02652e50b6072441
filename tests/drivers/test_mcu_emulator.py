"""The firmware emulator's safety rules, spoken to frame by frame over a raw pty (no host driver)."""

from __future__ import annotations

import os
import select
import time

import pytest

from usmswitch.drivers.mcu_protocol import (
    Ack,
    Arm,
    Command,
    DeviceFault,
    Fault,
    FrameDecoder,
    Hello,
    HelloAck,
    Message,
    Ping,
    Start,
    Status,
    Stopped,
    StopReason,
    Stroke,
    StrokeFlags,
    encode_frame,
)
from usmswitch.sim.mcu_emulator import McuEmulator, PtyLink


class RawHost:
    """A bare host: writes frames to the pty and collects what comes back."""

    def __init__(self, path: str) -> None:
        import tty

        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.dec = FrameDecoder()
        self.seq = 0
        self.got: list[Message] = []

    def send(self, msg: Message) -> int:
        seq = self.seq
        self.seq += 1
        os.write(self.fd, encode_frame(msg, seq))
        return seq

    def collect(self, until, timeout_s: float = 1.0) -> Message:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for m in self.got:
                if until(m):
                    self.got.remove(m)
                    return m
            r, _, _ = select.select([self.fd], [], [], 0.01)
            if r:
                self.got += [m for _, m in self.dec.feed(os.read(self.fd, 4096))]
        raise AssertionError(f"nothing matched; got {self.got}")

    def ack_of(self, seq: int) -> Ack:
        return self.collect(lambda m: isinstance(m, Ack) and m.acked_seq == seq)  # type: ignore[return-value]


@pytest.fixture
def host(tmp_path):
    emu = McuEmulator(seed=5).start()
    link = PtyLink(emu, tmp_path / "mcu").plug()
    h = RawHost(str(tmp_path / "mcu"))
    yield emu, h
    os.close(h.fd)
    link.close()
    emu.stop()


def test_never_starts_unasked(host) -> None:
    emu, h = host
    assert h.ack_of(h.send(Arm(1, 0, 1000, 100_000))).status == Status.NOT_SYNCED  # no HELLO yet
    h.send(Hello(1, 0, 1000))
    h.collect(lambda m: isinstance(m, HelloAck))
    assert h.ack_of(h.send(Command(1, 0, 0))).status == Status.NOT_ARMED
    assert h.ack_of(h.send(Arm(2, 0, 1000, 100_000))).status == Status.OK
    assert h.ack_of(h.send(Command(3, 0, 0))).status == Status.NOT_ARMED  # not the armed stroke
    assert h.ack_of(h.send(Arm(4, 5, 1000, 100_000))).status == Status.BAD_ARG
    ack = h.ack_of(h.send(Command(2, 0, 0)))
    assert ack.status == Status.OK
    again = h.ack_of(h.send(Command(2, 0, 0)))  # a retransmission: same instant, no second start
    assert again.status == Status.OK and again.t_us == ack.t_us
    h.collect(lambda m: isinstance(m, Stopped) and m.reason == StopReason.ARRIVED)
    assert emu.strokes_started == 1
    assert h.ack_of(h.send(Command(2, 0, 0))).status == Status.OK  # still the same stroke
    assert h.ack_of(h.send(Command(2, 0, 0))).t_us == ack.t_us
    time.sleep(0.02)
    assert emu.strokes_started == 1  # an armed stroke is used once


def test_watchdog_stops_the_drive_when_the_host_goes_silent(host) -> None:
    emu, h = host
    h.send(Hello(1, 0, 60))
    h.collect(lambda m: isinstance(m, HelloAck))
    emu.inject_stall()  # jams: without the watchdog the drive would run to the 5 s timeout
    h.send(Arm(1, 0, 0, 5_000_000))
    h.send(Command(1, 0, 0))
    h.collect(lambda m: isinstance(m, Start))
    t_quiet = time.monotonic()
    f = h.collect(lambda m: isinstance(m, Fault))
    assert isinstance(f, Fault) and f.code == DeviceFault.HOST_SILENT
    assert time.monotonic() - t_quiet < 0.5
    rep = h.collect(lambda m: isinstance(m, Stroke))
    assert isinstance(rep, Stroke) and StrokeFlags.WATCHDOG in StrokeFlags(rep.flags)
    assert StrokeFlags.ARRIVED not in StrokeFlags(rep.flags)
    h.collect(lambda m: isinstance(m, Stopped) and m.reason == StopReason.WATCHDOG)
    assert not emu.drive_on and not emu.synced
    assert h.ack_of(h.send(Arm(2, 1, 0, 100_000))).status == Status.NOT_SYNCED  # a new HELLO first
    h.send(Ping(9))
    h.send(Hello(1, 0, 500))
    h.collect(lambda m: isinstance(m, HelloAck))
    assert h.ack_of(h.send(Arm(3, 1, 0, 100_000))).status == Status.OK


def test_late_command_starts_at_once_and_says_so(host) -> None:
    emu, h = host
    h.send(Hello(1, 0, 1000))
    hello = h.collect(lambda m: isinstance(m, HelloAck))
    assert isinstance(hello, HelloAck)
    h.send(Arm(1, 0, 1000, 100_000))
    now_us = emu.device_us()
    h.send(Command(1, (now_us - 5_000) % (1 << 32), 1))  # the instant was 4 ms ago
    start = h.collect(lambda m: isinstance(m, Start))
    assert isinstance(start, Start) and start.late_us >= 4_000
    rep = h.collect(lambda m: isinstance(m, Stroke))
    assert isinstance(rep, Stroke) and StrokeFlags.LATE in StrokeFlags(rep.flags)
    h.send(Arm(2, 1, 1000, 100_000))
    assert h.ack_of(h.send(Command(2, (now_us + 5_000_000) % (1 << 32), 1))).status == Status.BAD_TIME
