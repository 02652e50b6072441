"""The simavr harness in lockstep: UART over stdin/stdout, emulated time advanced on command."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from usmswitch.drivers.mcu_protocol import FrameDecoder, Hello, Message, encode_frame


class Lockstep:
    """usmswitch-avrsim --lockstep as a child; `run(us)` returns the UART bytes of that stretch."""

    def __init__(self, binary: Path, elf: Path, *args: str) -> None:
        cmd = [str(binary), "--elf", str(elf), "--lockstep", "--python", sys.executable, *args]
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1
        )
        assert self.proc.stdout
        line = self.proc.stdout.readline()
        assert line.startswith("avrsim lockstep"), line + self._stderr()
        #: (level, cycle, firmware us) of every drive pin change.
        self.drive: list[tuple[int, int, int]] = []
        #: With `trace(1)`: (channel, active, cycle, firmware us, span) of every sensor edge, span
        #: being where the interrupts-off stretch in progress as it came began (-1: none).
        self.sensors: list[tuple[int, int, int, int, int]] = []
        #: With `trace(1)`: (vector, cycle) of every interrupt entered.
        self.irqs: list[tuple[int, int]] = []
        #: With `trace(2)`: (where, pc, start cycle, cycles) of every interrupts-off stretch.
        self.clis: list[tuple[str, int, int, int]] = []
        #: (cycle, firmware us) of every watchdog reset.
        self.resets: list[tuple[int, int]] = []
        self.cycle = 0
        self.fw_us = 0

    def _stderr(self) -> str:
        if self.proc.poll() is not None and self.proc.stderr:
            return self.proc.stderr.read()
        return ""

    def command(self, line: str) -> None:
        assert self.proc.stdin
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def send_bytes(self, data: bytes) -> None:
        self.command("send " + data.hex())

    def run(self, us: int) -> bytes:
        """Run `us` microseconds of emulated time; returns what the firmware sent meanwhile."""
        self.command(f"run {us}")
        return self._ran()

    def run_to(self, cycle: int) -> bytes:
        """Run to emulator cycle `cycle` (16 a microsecond); returns what the firmware sent."""
        self.command(f"runto {cycle}")
        return self._ran()

    def edge(self, channel: int, active: int, cycle: int) -> None:
        """Set a sensor's line (0 A, 1 B; 1 active) at an exact emulator cycle."""
        self.command(f"edge {channel} {active} {cycle}")

    def trace(self, level: int) -> None:
        self.command(f"trace {level}")

    def origin(self) -> int:
        """The cycle where the firmware's clock counts from zero (timer overflows every 524,288)."""
        assert self.proc.stdout
        self.command("info")
        word, *rest = self.proc.stdout.readline().split()
        assert word == "info", word
        return int(rest[1])

    def stats(self) -> list[str]:
        """The harness's measurements: "span WHERE PC COUNT MAX_CYCLES AT", "wdr ...", "resets N"."""
        assert self.proc.stdout
        self.command("stats")
        out = []
        while (line := self.proc.stdout.readline().strip()) != "end":
            assert line, "usmswitch-avrsim exited: " + self._stderr()
            out.append(line)
        return out

    def _ran(self) -> bytes:
        assert self.proc.stdout
        out = b""
        while True:
            line = self.proc.stdout.readline()
            assert line, "usmswitch-avrsim exited: " + self._stderr()
            word, _, rest = line.strip().partition(" ")
            if word == "uart":
                out += bytes.fromhex(rest)
            elif word == "drive":
                level, cycle, fw_us = (int(x) for x in rest.split())
                self.drive.append((level, cycle, fw_us))
            elif word == "sensor":
                ch, active, cycle, fw_us, span = (int(x) for x in rest.split())
                self.sensors.append((ch, active, cycle, fw_us, span))
            elif word == "irq":
                vec, cycle = (int(x) for x in rest.split())
                self.irqs.append((vec, cycle))
            elif word == "cli":
                name, pc, start, length = rest.split()
                self.clis.append((name, int(pc), int(start), int(length)))
            elif word == "reset":
                _, cycle, fw_us = rest.split()
                self.resets.append((int(cycle), int(fw_us)))
            elif word == "ran":
                cycle, fw_us = rest.split()
                self.cycle, self.fw_us = int(cycle), int(fw_us)
                return out

    def close(self) -> None:
        if self.proc.poll() is None:
            self.command("quit")
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class FirmwareDevice:
    """The firmware under the harness as a protocol peer: frames in, frames out, time on command."""

    def __init__(self, sim: Lockstep) -> None:
        self.sim = sim
        self.decoder = FrameDecoder()

    def write(self, data: bytes) -> None:
        self.sim.send_bytes(data)

    def send(self, msg: Message, seq: int) -> None:
        self.write(encode_frame(msg, seq))

    def open_session(self, watchdog_ms: int = 60_000) -> None:
        """End any partial frame, HELLO (protocol 1.1) and run 5 ms: the firmware answers and waits."""
        self.write(b"\x00")
        self.send(Hello(1, 1, watchdog_ms), 0)
        self.run(5000)

    def run(self, us: int) -> list[tuple[int, Message]]:
        return self.decoder.feed(self.sim.run(us))


def since_us(t_us: int, t0_us: int) -> int:
    """Signed microseconds from t0_us to t_us on the protocol's 32-bit clock."""
    d = (t_us - t0_us) % (1 << 32)
    return d - (1 << 32) if d >= 1 << 31 else d
