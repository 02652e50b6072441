"""One conformance suite for both MCU implementations, so they cannot drift apart:
the firmware in simavr (lockstep, emulated time) and sim/mcu_emulator.py (real time)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from avrsim import FirmwareDevice, Lockstep

from usmswitch.drivers import mcu_protocol as mp
from usmswitch.drivers.mcu_protocol import FrameDecoder, Message, encode_frame
from usmswitch.sim.mcu_emulator import McuEmulator

U32 = 1 << 32


class PythonDevice:
    """sim/mcu_emulator.py behind the same face as FirmwareDevice."""

    def __init__(self, **kw: object) -> None:
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
        with self._lock:
            data, self._buf = bytes(self._buf), bytearray()
        return self.decoder.feed(data)

    def close(self) -> None:
        self.emu.stop()


@pytest.fixture(params=["firmware", "python"])
def device(request: pytest.FixtureRequest) -> Iterator[FirmwareDevice | PythonDevice]:
    if request.param == "firmware":
        avrsim: Path = request.getfixturevalue("avrsim")
        sim = Lockstep(avrsim, avrsim.parent / "usmswitch.elf")
        yield FirmwareDevice(sim)
        sim.close()
    else:
        dev = PythonDevice()
        yield dev
        dev.close()


def _hello(dev: FirmwareDevice | PythonDevice, major: int = 1, watchdog_ms: int = 500) -> mp.HelloAck:
    dev.write(b"\x00")
    dev.send(mp.Hello(major, 0, watchdog_ms), 0)
    got = dev.run(5000)
    assert len(got) == 1 and got[0][0] == 0 and isinstance(got[0][1], mp.HelloAck), got
    return got[0][1]


def _msgs(got: list[tuple[int, Message]]) -> list[Message]:
    return [m for _, m in got]


def test_handshake_and_versions(device: FirmwareDevice | PythonDevice) -> None:
    ack = _hello(device)
    assert (ack.major, ack.minor, ack.caps, ack.fw_version, ack.max_delay_us) == (1, 0, 31, 0x0100, 1_000_000)
    device.send(mp.Ping(7), 1)
    (pong,) = _msgs(device.run(3000))
    assert isinstance(pong, mp.Pong) and pong.token == 7 and pong.state & mp.StateFlags.SYNCED
    assert pong.state & mp.StateFlags.SENSOR_A and (pong.rx_errors, pong.rx_lost) == (0, 0)
    # another major version: a HELLO_ACK, then NOT_SYNCED for every request
    _hello(device, major=2)
    device.send(mp.Arm(1, 0, 1000, 100_000), 1)
    (ack2,) = _msgs(device.run(3000))
    assert isinstance(ack2, mp.Ack) and ack2.status == mp.Status.NOT_SYNCED and ack2.stroke == 0


def test_arm_checks_and_command_refusals(device: FirmwareDevice | PythonDevice) -> None:
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


def test_retransmitted_command_and_late_start(device: FirmwareDevice | PythonDevice) -> None:
    hello = _hello(device)
    device.send(mp.Arm(3, 0, 1000, 100_000), 1)
    t_cmd = (hello.t_us - 20_000) % U32  # 20 ms in the past: the start is late by ~19 ms
    device.send(mp.Command(3, t_cmd, 1), 2)
    device.send(mp.Command(3, (t_cmd + 5) % U32, 1), 3)  # a retransmission: the original instant
    got = _msgs(device.run(40_000))
    acks = [m for m in got if isinstance(m, mp.Ack)]
    assert [(a.acked_seq, a.status, a.t_us) for a in acks[1:]] == [(2, 0, t_cmd), (3, 0, t_cmd)]
    (start,) = [m for m in got if isinstance(m, mp.Start)]
    assert 18_000 < start.late_us < 25_000
    (stroke,) = [m for m in got if isinstance(m, mp.Stroke)]
    assert stroke.flags & mp.StrokeFlags.LATE and stroke.flags & mp.StrokeFlags.ARRIVED


def test_watchdog_stops_a_stroke(device: FirmwareDevice | PythonDevice) -> None:
    hello = _hello(device, watchdog_ms=20)
    device.send(mp.Arm(4, 0, 200_000, 100_000), 1)  # starts 200 ms on: the watchdog acts first
    device.send(mp.Command(4, hello.t_us, 0), 2)
    got = _msgs(device.run(120_000))  # the Python emulator looks at its watchdog every 50 ms
    kinds = [type(m).__name__ for m in got]
    assert kinds[:2] == ["Ack", "Ack"] and "Start" not in kinds
    i = kinds.index("Fault")
    assert kinds[i : i + 3] == ["Fault", "Stroke", "Stopped"]
    assert got[i].code == mp.DeviceFault.HOST_SILENT and got[i].detail == 20
    assert got[i + 2].reason == mp.StopReason.WATCHDOG and got[i + 1].flags & mp.StrokeFlags.WATCHDOG
    device.send(mp.Arm(5, 0, 0, 100_000), 3)
    (ack,) = _msgs(device.run(3000))
    assert ack.status == mp.Status.NOT_SYNCED


def test_unknown_type_and_bad_frames(device: FirmwareDevice | PythonDevice) -> None:
    _hello(device)
    device.send(mp.Pong(1, 2, 3, 4, 5), 1)  # a device-side type sent to the device
    device.write(b"\x05\x01\x02\x03\x04\x00")  # COBS fine, CRC wrong
    device.write(b"\x11" * 80 + b"\x00")  # over-long
    device.send(mp.Ping(9), 5)  # seq 2..4 missing
    got = _msgs(device.run(5000))
    assert isinstance(got[0], mp.Ack) and got[0].status == mp.Status.UNKNOWN_TYPE
    assert isinstance(got[1], mp.Pong) and (got[1].rx_errors, got[1].rx_lost) == (2, 3)
