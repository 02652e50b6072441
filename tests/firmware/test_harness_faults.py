"""The harness's clock error and cable faults, seen through the firmware and the serial driver.

`--ppm N` makes the emulated crystal run N ppm fast: the firmware's microsecond clock then counts
a physical interval (the rig model's, in ns) as N ppm longer, and the firmware's stamps must show
exactly that. `unplug` and `replug` act on the real pty in real time: the serial driver must take
the unplug as a lost link (the stroke stopped, a DISCONNECT fault, DaqDisconnected on use), the
firmware's watchdog must stop the drive, and after the replug (a power-on reset, as a
bus-powered board does) the driver must handshake a new session on its own.
"""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest
from avrsim import FirmwareDevice, Lockstep, since_us

from usmswitch.drivers import DaqDisconnected, Direction, EventKind, FaultCode
from usmswitch.drivers.events import Channel
from usmswitch.drivers.mcu_protocol import Arm, Boot, Command, Hello, HelloAck, Start, Stroke
from usmswitch.drivers.serial_mcu import SerialMcuDaq
from usmswitch.sim.mcu_rig import Mover
from usmswitch.sim.model import UsmSwitchModel

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "drivers"))
from mcu_rig import FAST, run_stroke, wait_for  # the driver tests' stroke runner

U32 = 1 << 32
F_CPU = 16_000_000
SEED = 5


@pytest.mark.parametrize("ppm", [0, 1000, -500])
def test_clock_error_in_ppm_is_on_the_firmware_timebase(avrsim: Path, firmware_elf: Path, ppm: int) -> None:
    dev = FirmwareDevice(Lockstep(avrsim, firmware_elf, "--ppm", str(ppm), "--seed", str(SEED)))
    try:
        dev.write(b"\x00")
        dev.send(Hello(1, 0, 5000), 0)
        ((_, ack),) = [(s, m) for s, m in dev.run(5000) if not isinstance(m, Boot)]
        assert isinstance(ack, HelloAck)
        dev.send(Arm(1, int(Direction.ON), 1000, 100_000), 1)
        dev.send(Command(1, 0, 0), 2)
        got = [m for _, m in dev.run(40_000)]
        drive = dev.sim.drive
    finally:
        dev.sim.close()
    (start,) = [m for m in got if isinstance(m, Start)]
    (stroke,) = [m for m in got if isinstance(m, Stroke)]
    (on_level, on_cycle, on_fw_us), (off_level, _, _) = drive
    assert (on_level, off_level) == (1, 0)
    # The physical timeline: emulated cycles at the crystal's real rate, as the harness tells the
    # rig helper; the same model and seed give the stroke the rig had.
    t_on_ns = int(on_cycle * 1e9 / (F_CPU * (1 + ppm * 1e-6)))
    plan = Mover(UsmSwitchModel(seed=SEED), Channel.A).start(Direction.ON, t_on_ns)
    assert plan.depart_ns is not None and plan.arrive_ns is not None
    scale = 1 + ppm * 1e-6  # the firmware's microseconds per physical microsecond
    for fw_us, phys_ns in ((stroke.t_depart_us, plan.depart_ns), (stroke.t_arrive_us, plan.arrive_ns)):
        on_firmware = since_us(fw_us, on_fw_us)
        assert abs(on_firmware - (phys_ns - t_on_ns) * scale / 1000) <= 1, (ppm, on_firmware, phys_ns)
    assert abs(since_us(start.t_us, on_fw_us)) <= 1  # START is stamped at the drive's instant


def _truth(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_unplug_mid_stroke_then_replug_over_the_pty(avrsim: Path, firmware_elf: Path, tmp_path: Path) -> None:
    link = tmp_path / "usmswitch"
    truth_csv = tmp_path / "truth.csv"
    sim = subprocess.Popen(
        [str(avrsim), "--elf", str(firmware_elf), "--link", str(link), "--truth", str(truth_csv),
         "--python", sys.executable, "--seed", "3"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1,
    )  # fmt: skip
    assert sim.stdin is not None and sim.stdout is not None

    def harness(command: str, answer: str) -> None:
        assert sim.stdin is not None and sim.stdout is not None
        sim.stdin.write(command + "\n")
        sim.stdin.flush()
        if answer:
            line = sim.stdout.readline()
            assert line.startswith(answer), line

    daq = None
    try:
        assert sim.stdout.readline().startswith("avrsim on")
        # The harness's board does not reset when its port opens: no bootloader to wait out.
        daq = SerialMcuDaq.from_spec(f"serial:{link}?reset_wait_ms=0", **FAST)
        daq.open()
        first = run_stroke(daq, Direction.ON)
        assert first.events[-1].detail == "arrived"

        daq.stroke_timeout_ns = 2_000_000_000  # on the device too: only its watchdog can stop this one
        harness("stall", "")  # the mover jams half way: the drive stays on
        daq.arm(Direction.OFF, 1_000_000)
        daq.command(daq.now_ns() + 2_000_000)
        ev = daq.recv(1_000_000_000)
        assert ev is not None and ev.kind is EventKind.START, ev
        harness("unplug", "unplugged")
        events = [ev]
        while events[-1].kind is not EventKind.FAULT:
            nxt = daq.recv(2_000_000_000)
            assert nxt is not None, events
            events.append(nxt)
        stops = [e for e in events if e.kind is EventKind.STOP]
        assert stops and stops[-1].detail == "disconnect" and stops[-1].direction is Direction.OFF, events
        assert events[-1].fault is FaultCode.DISCONNECT
        with pytest.raises(DaqDisconnected):
            daq.arm(Direction.OFF, 1_000_000)
        # The motor is safe: the firmware's watchdog cut the drive (its row is written when the
        # drive goes off), long before the stroke's own 2 s limit, without an arrival.
        assert wait_for(lambda: len(_truth(truth_csv)) == 2, 5.0)
        jammed = _truth(truth_csv)[1]
        assert jammed["arrive_us"] == "" and jammed["depart_us"] != ""
        assert (int(jammed["off_us"]) - int(jammed["start_us"])) % U32 < 2_000_000

        harness("replug", "avrsim on")  # a new pty behind the same path; the MCU was power-cycled
        assert wait_for(lambda: daq.connected, 5.0)
        assert daq.link_stats()["reconnects"] == 1
        assert daq.device is not None and daq.device.t_us < 1_000_000  # a new session, a new clock
        daq.stroke_timeout_ns = 100_000_000
        again = run_stroke(daq, Direction.OFF)  # from where the jam left the mover, to A
        assert again.events[-1].detail == "arrived"
        assert again.start.t_ns > events[-1].t_ns > first.events[-1].t_ns  # one timeline across the reboot

        # Sensors keep their levels through a power cycle: the mover is at A.
        harness("unplug", "unplugged")
        lost = daq.recv(2_000_000_000)
        assert lost is not None and lost.fault is FaultCode.DISCONNECT, lost
        harness("replug", "avrsim on")
        assert wait_for(lambda: daq.connected and daq.levels() is not None, 5.0)
        assert daq.levels() == (1, 0)
        assert run_stroke(daq, Direction.ON).events[-1].detail == "arrived"
        st = daq.link_stats()
        assert st["reconnects"] == 2 and st["lost_frames"] == 0 and st["crc_errors"] == 0
        assert len(_truth(truth_csv)) == 4  # one drive-on per stroke the host commanded
    finally:
        if daq is not None:
            daq.close()
        sim.terminate()
        _, err = sim.communicate(timeout=10)
        print(err[-2000:])
