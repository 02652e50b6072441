"""The firmware's hardware watchdog, in simavr.

The test image build/usmswitch-hang.elf (USMSWITCH_TEST_HANG_ON_START, never flashed) hangs its
main loop as a stroke starts, the drive on. With the mover jammed (no arrival to cut the drive
from the capture interrupt) only the watchdog can stop it: the drive pin must be low within the
watchdog's period (32 ms, WDTO_30MS) of the start, by a reset, and the firmware must then say why
it restarted (BOOT, and HELLO_ACK's reset cause in a 1.1 session). Through the serial driver over a
pty in real time, the same hang must come out as a FAULT DRIVE event naming the watchdog, and the
driver must handshake the restarted board again on its own. The production image must meanwhile
never be reset by it: its longest main-loop pass, as the harness measures between two kicks, stays
far inside the period. And usmswitchd on the hang image latches the reset as its FAULT, which
`status` shows: "drive: device reset by its hardware watchdog (MCUSR 0x08)".
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import daemonproc
import pytest
from avrsim import FirmwareDevice, Lockstep, since_us
from conftest import BUILD, make

from usmswitch.client import Client
from usmswitch.drivers import Direction, EventKind, FaultCode
from usmswitch.drivers import mcu_protocol as mp
from usmswitch.drivers.serial_mcu import SerialMcuDaq

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "drivers"))
from mcu_rig import FAST, wait_for  # the driver tests' helpers

WDT_PERIOD_US = 32_000  # WDTO_30MS: 4096 cycles of the 128 kHz watchdog oscillator
F_CPU = 16_000_000


@pytest.fixture(scope="module")
def hang_elf(avrsim: Path) -> Path:
    make("build/usmswitch-hang.elf")
    return BUILD / "usmswitch-hang.elf"


def _msgs(dev: FirmwareDevice, us: int) -> list[mp.Message]:
    return [m for _, m in dev.run(us)]


def test_a_hung_main_loop_is_reset_by_the_watchdog_drive_off(avrsim: Path, hang_elf: Path) -> None:
    sim = Lockstep(avrsim, hang_elf, "--seed", "2")
    dev = FirmwareDevice(sim)
    try:
        dev.write(b"\x00")
        dev.send(mp.Hello(1, 1, 60_000), 0)
        got = _msgs(dev, 5000)
        assert got[0] == mp.Boot(int(mp.ResetCause.POWER_ON), 0x0102)
        assert isinstance(got[1], mp.HelloAck) and got[1].reset_cause == mp.ResetCause.POWER_ON
        sim.command("stall")  # the mover jams half way: no arrival will cut the drive
        dev.send(mp.Arm(1, 0, 1000, 100_000), 1)
        dev.send(mp.Command(1, 0, 0), 2)
        got = _msgs(dev, 60_000)
        # START went out (the UART drains by interrupt), then nothing until the reset's BOOT
        assert [type(m).__name__ for m in got] == ["Ack", "Ack", "Start", "Boot"], got
        assert got[-1] == mp.Boot(int(mp.ResetCause.WATCHDOG), 0x0102)
        (on, off) = sim.drive
        assert (on[0], off[0]) == (1, 0)
        ((reset_cycle, _),) = sim.resets
        assert off[1] == reset_cycle  # the reset took the pin low
        on_to_off_us = (off[1] - on[1]) * 1e6 / F_CPU
        assert 0.9 * WDT_PERIOD_US < on_to_off_us <= WDT_PERIOD_US + 100, on_to_off_us
        print(f"drive on to off by the watchdog: {on_to_off_us:.0f} us")
        # a new session says why the board restarted; the stroke is gone
        dev.send(mp.Hello(1, 1, 60_000), 0)
        (ack,) = _msgs(dev, 5000)
        assert isinstance(ack, mp.HelloAck) and ack.reset_cause == mp.ResetCause.WATCHDOG
        dev.send(mp.Ping(1), 1)
        (pong,) = _msgs(dev, 3000)
        assert not pong.state & mp.StateFlags.DRIVE_ON and since_us(pong.t_us, ack.t_us) > 0
    finally:
        sim.close()


def test_an_interrupt_without_a_handler_cuts_the_drive_and_waits_for_the_watchdog(
    avrsim: Path, firmware_elf: Path
) -> None:
    """An interrupt the firmware has no handler for (the harness enables INT0 behind its back) in
    the middle of a jammed stroke: BADISR_vect takes the drive off at once and waits, interrupts
    off, for the watchdog, whose reset then says why (BOOT WATCHDOG). avr-libc's default jumps to
    0, a restart with no reset (7f3fa01: a BOOT with reset cause 0, the I/O left as it was)."""
    sim = Lockstep(avrsim, firmware_elf, "--seed", "2")
    dev = FirmwareDevice(sim)
    try:
        dev.write(b"\x00")
        dev.send(mp.Hello(1, 1, 60_000), 0)
        _msgs(dev, 5000)
        sim.command("stall")  # no arrival will cut the drive
        dev.send(mp.Arm(1, 0, 1000, 100_000), 1)
        dev.send(mp.Command(1, 0, 0), 2)
        while not sim.drive:
            dev.run(100)
        dev.run(2000)
        at = sim.cycle
        sim.command("badirq")
        got = _msgs(dev, 60_000)
        (on, off) = sim.drive
        assert (on[0], off[0]) == (1, 0)
        assert (off[1] - at) / 16 < 10, (off, at)  # off at once, not at the watchdog's reset
        ((reset_cycle, _),) = sim.resets
        assert 0.9 * WDT_PERIOD_US < (reset_cycle - at) / 16 <= WDT_PERIOD_US + 100, (reset_cycle, at)
        assert got[-1] == mp.Boot(int(mp.ResetCause.WATCHDOG), 0x0102), got
    finally:
        sim.close()


def _stat(lines: list[str], word: str) -> list[str]:
    (line,) = [ln for ln in lines if ln.startswith(word + " ")]
    return line.split()[1:]


def test_the_production_image_kicks_it_well_inside_its_period(avrsim: Path, firmware_elf: Path) -> None:
    """Strokes, heartbeats and a burst of requests: no watchdog reset, and the longest main-loop
    pass (from one kick to the next, sleeping included) stays under half the period."""
    sim = Lockstep(avrsim, firmware_elf, "--seed", "4")
    dev = FirmwareDevice(sim)
    try:
        dev.open_session()
        seq = 1
        for stroke in range(1, 21):
            dev.send(mp.Arm(stroke, (stroke + 1) % 2, 1000, 100_000), seq)
            dev.send(mp.Command(stroke, 0, 0), seq + 1)
            seq += 2
            for _ in range(8):  # a burst of pings while it runs: the rings fill
                dev.send(mp.Ping(stroke), seq)
                seq += 1
            got = _msgs(dev, 40_000)
            assert any(isinstance(m, mp.Stroke) and m.flags & mp.StrokeFlags.ARRIVED for m in got), got
        dev.run(200_000)  # idle: only the alarm wakes it
        stats = sim.stats()
    finally:
        sim.close()
    assert _stat(stats, "resets") == ["0"]
    kicks, longest_cycles, _ = (int(x) for x in _stat(stats, "wdr"))
    longest_us = longest_cycles * 1e6 / F_CPU
    print(f"{kicks} kicks, longest main-loop pass {longest_us:.0f} us (watchdog {WDT_PERIOD_US} us)")
    assert kicks > 100 and longest_us < WDT_PERIOD_US / 2


@pytest.mark.realtime
def test_the_serial_driver_reports_the_watchdog_reset(avrsim: Path, hang_elf: Path, tmp_path: Path) -> None:
    link = tmp_path / "usmswitch"
    sim = subprocess.Popen(
        [str(avrsim), "--elf", str(hang_elf), "--link", str(link), "--python", sys.executable, "--seed", "3"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1,
    )  # fmt: skip
    assert sim.stdin is not None and sim.stdout is not None
    daq = None
    try:
        assert sim.stdout.readline().startswith("avrsim on")
        daq = SerialMcuDaq.from_spec(f"serial:{link}?reset_wait_ms=0", **FAST)
        daq.stroke_timeout_ns = 2_000_000_000  # on the device too: only its watchdog can stop this one
        daq.open()
        sim.stdin.write("stall\n")
        sim.stdin.flush()
        daq.arm(Direction.ON, 1_000_000)
        daq.command(daq.now_ns() + 2_000_000)
        events = []
        t0 = time.monotonic()
        while not any(e.kind is EventKind.FAULT for e in events):
            ev = daq.recv(1_000_000_000)
            assert ev is not None, events
            events.append(ev)
        took_s = time.monotonic() - t0
        (start,) = [e for e in events if e.kind is EventKind.START]
        (fault,) = [e for e in events if e.kind is EventKind.FAULT]
        assert fault.fault is FaultCode.DRIVE and "hardware watchdog (MCUSR 0x08)" in fault.detail, fault
        # reported from the BOOT as the board restarts: ~32 ms after the start, not a heartbeat later
        assert 0 < fault.t_ns - start.t_ns < 100_000_000 and took_s < 1.0, (fault, start)
        stop = daq.recv(1_000_000_000)
        assert stop is not None and stop.kind is EventKind.STOP and stop.direction is Direction.ON, stop
        assert wait_for(lambda: daq.connected and daq.link_stats()["resyncs"] == 1, 5.0)
        st = daq.link_stats()
        assert (st["watchdog_resets"], st["device_resets"], st["reset_cause"]) == (1, 1, 8), st
        assert daq.device is not None and daq.device.reset_cause == mp.ResetCause.WATCHDOG
        assert daq.recv(300_000_000) is None  # reported once: the handshake after it says nothing
    finally:
        if daq is not None:
            daq.close()
        sim.terminate()
        _, err = sim.communicate(timeout=10)
        print(err[-1500:])


@pytest.mark.realtime
def test_the_daemon_latches_the_watchdog_reset(avrsim: Path, hang_elf: Path, tmp_path: Path) -> None:
    """usmswitchd --driver serial on the hang image: the first stroke's firmware hangs, the board's
    watchdog resets it, and the daemon latches that as its FAULT, shown by `status`."""
    link = tmp_path / "usmswitch"
    sim = subprocess.Popen(
        [str(avrsim), "--elf", str(hang_elf), "--link", str(link), "--python", sys.executable, "--seed", "3"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1,
    )  # fmt: skip
    daemon = None
    try:
        assert sim.stdout is not None and sim.stdout.readline().startswith("avrsim on")
        sock = tmp_path / "d.sock"
        args = ["--driver", "serial", "--port", str(link), "--target", "12ms"]
        daemon = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args, sim=False))
        daemonproc.wait_serving(sock, daemon)
        with Client(str(sock), timeout=10) as c:
            assert c.status()["state"] == "idle"
            try:
                c.switch()
            except Exception as exc:  # the stroke fails; how it says so is the daemon's business
                print(f"switch: {exc!r}")
            assert wait_for(lambda: c.status()["state"] == "fault", 5.0)
            st = c.status()
            assert "watchdog" in st["fault"] and "MCUSR 0x08" in st["fault"], st["fault"]
            assert st["driver_counters"]["watchdog_resets"] == 1, st["driver_counters"]
            print(f"status fault: {st['fault']}")
    finally:
        try:
            if daemon is not None:
                daemonproc.stop(daemon)
        finally:
            sim.terminate()
            sim.communicate(timeout=10)
