"""The reference firmware in simavr: emulator speed, capture-to-drive-off latency, start and stamp error.

1. Lockstep (firmware/build/usmswitch-avrsim --lockstep, as fast as the CPU goes): STROKES strokes,
   each an ARM and a COMMAND for a compare-timed start, the firmware's frames decoded. Emulated time
   over wall time is the speed; the harness's truth (drive pin and sensor pins, from emulator cycles)
   gives the arrival-edge-to-drive-off latency, the start error (the drive pin against the commanded
   instant) and the stamp error (the firmware's START/EDGE stamps against the pins).
2. Real time: the serial driver (SerialMcuDaq) runs RT_STROKES strokes over a pty against the
   harness (--link) and, as the peer in the same run, against sim/mcu_emulator.py in a process of
   its own; the device side's CPU use (the harness with its rig helper; the emulator's process) per
   second of wall time is what the device costs the machine the daemon runs on.
"""

from __future__ import annotations

import contextlib
import csv
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.table import print_table
from usmswitch.drivers import Direction, EventKind
from usmswitch.drivers.mcu_protocol import (
    Arm,
    Command,
    Edge,
    FrameDecoder,
    Hello,
    HelloAck,
    Start,
    encode_frame,
)

ROOT = Path(__file__).resolve().parents[1]
BUILD = ROOT / "firmware" / "build"
STROKES = 200
RT_STROKES = 100
PERIOD_US = 24_000
DELAY_US = 1_500
U32 = 1 << 32
# The limits: the drive off within 5 us of the arrival edge, stamps within 1 us of the pins.
CUT_LIMIT_NS = 5_000
STAMP_LIMIT_US = 1


class _Lockstep:
    """usmswitch-avrsim --lockstep: `send` bytes, `run(us)` returns what the firmware sent."""

    def __init__(self, *args: str) -> None:
        cmd = [str(BUILD / "usmswitch-avrsim"), "--elf", str(BUILD / "usmswitch.elf"), "--lockstep"]
        cmd += ["--python", sys.executable, *args]
        self.proc = subprocess.Popen(
            cmd,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            bufsize=1,
        )
        assert self.proc.stdout and self.proc.stdin
        line = self.proc.stdout.readline()
        if not line.startswith("avrsim lockstep"):
            raise RuntimeError(f"usmswitch-avrsim did not start: {line!r}")

    def send(self, data: bytes) -> None:
        assert self.proc.stdin
        self.proc.stdin.write(f"send {data.hex()}\n")

    def run(self, us: int) -> bytes:
        assert self.proc.stdin and self.proc.stdout
        self.proc.stdin.write(f"run {us}\n")
        self.proc.stdin.flush()
        out = b""
        while True:
            word, _, rest = self.proc.stdout.readline().strip().partition(" ")
            if word == "uart":
                out += bytes.fromhex(rest)
            elif word == "ran":
                return out
            elif not word:
                raise RuntimeError("usmswitch-avrsim exited")

    def close(self) -> None:
        assert self.proc.stdin
        self.proc.stdin.write("quit\n")
        self.proc.stdin.flush()
        self.proc.wait(10)


def _lockstep(truth: Path) -> dict[str, list[int] | float]:
    sim = _Lockstep("--truth", str(truth), "--seed", "5")
    dec = FrameDecoder()
    t0 = time.perf_counter()
    sim.send(b"\x00" + encode_frame(Hello(1, 0, 60_000), 0))
    now = next(m for _, m in dec.feed(sim.run(2000)) if isinstance(m, HelloAck)).t_us  # after its BOOT
    seq = 1
    starts: list[tuple[int, int]] = []  # (commanded instant + delay, START stamp)
    edges: list[Edge] = []
    for k in range(STROKES):
        t_cmd = (now + 3000) % U32
        sim.send(encode_frame(Arm(k + 1, k % 2, DELAY_US, 100_000), seq))
        sim.send(encode_frame(Command(k + 1, t_cmd, 1), seq + 1))
        seq += 2
        for _, m in dec.feed(sim.run(PERIOD_US)):
            if isinstance(m, Start):
                starts.append(((t_cmd + DELAY_US) % U32, m.t_us))
            elif isinstance(m, Edge):
                edges.append(m)
        now = (now + PERIOD_US) % U32
    wall = time.perf_counter() - t0
    sim.close()
    with truth.open() as f:
        rows = list(csv.DictReader(f))
    if len(rows) != STROKES or len(starts) != STROKES:
        raise RuntimeError(
            f"lockstep: {len(rows)} strokes in the truth, {len(starts)} STARTs, want {STROKES}"
        )
    start_err = [(int(r["start_us"]) - due) % U32 for r, (due, _) in zip(rows, starts, strict=True)]
    start_err = [e - U32 if e >= U32 // 2 else e for e in start_err]
    stamp_err = [abs(int(r["start_us"]) - st) for r, (_, st) in zip(rows, starts, strict=True)]
    pins = sorted(int(r[k]) for r in rows for k in ("depart_us", "arrive_us"))
    stamps = sorted(e.t_us for e in edges)
    if len(pins) != len(stamps):
        raise RuntimeError(f"lockstep: {len(stamps)} EDGE frames for {len(pins)} sensor edges")
    stamp_err += [abs(a - b) for a, b in zip(pins, stamps, strict=True)]
    emulated = (STROKES * PERIOD_US + 2000) / 1e6
    return {
        "speed": emulated / wall,
        "cut": [int(r["cut_ns"]) for r in rows],
        "start_err": start_err,
        "stamp_err": stamp_err,
    }


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process and its live children."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    pids = [pid]
    with contextlib.suppress(OSError):
        pids += [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    for p in pids:
        try:
            f = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(f[11]) + int(f[12])) / tick
    return total


_PY_DEVICE = """
import sys, time
from usmswitch.sim.mcu_emulator import McuEmulator, PtyLink
PtyLink(McuEmulator(seed=5).start(), sys.argv[1]).plug()
print("ready", flush=True)
time.sleep(3600)
"""


def _real_time(kind: str) -> tuple[float, list[int]]:
    """Device CPU per wall second while the serial driver runs RT_STROKES strokes; start lateness."""
    from usmswitch.drivers.serial_mcu import SerialMcuDaq

    tmp = Path(tempfile.mkdtemp(prefix="bench-fw-"))
    link = tmp / "link"
    if kind == "firmware":
        cmd = [str(BUILD / "usmswitch-avrsim"), "--elf", str(BUILD / "usmswitch.elf"), "--link", str(link)]
        cmd += ["--python", sys.executable, "--seed", "5"]
    else:
        cmd = [sys.executable, "-c", _PY_DEVICE, str(link)]
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    late: list[int] = []
    try:
        assert proc.stdout
        proc.stdout.readline()
        daq = SerialMcuDaq(str(link), reset_wait_ms=0)
        daq.open()
        try:
            cpu0, wall0 = _cpu_s(proc.pid), time.monotonic()
            d = Direction.ON
            tick = daq.now_ns() + 10_000_000
            for _ in range(RT_STROKES):
                daq.arm(d, DELAY_US * 1000)
                while daq.now_ns() < tick - daq.command_lead_ns:
                    time.sleep(0.0005)
                daq.command(tick)
                while True:
                    ev = daq.recv(200_000_000)
                    if ev is None:
                        raise RuntimeError(f"{kind}: no event within 200 ms")
                    if ev.kind is EventKind.START:
                        late.append(ev.lateness_ns or 0)
                    if ev.kind is EventKind.EDGE and ev.channel is d.dest and ev.level == 1:
                        break
                d = d.opposite
                tick += PERIOD_US * 1000
            cpu = (_cpu_s(proc.pid) - cpu0) / (time.monotonic() - wall0)
        finally:
            daq.close()
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
        shutil.rmtree(tmp, ignore_errors=True)
    return cpu, late


def _build() -> str:
    """Build the image and harness; the reason on failure (a missing toolchain)."""
    try:
        proc = subprocess.run(
            ["make", "-j1", "-C", str(ROOT / "firmware"), "firmware"],
            capture_output=True,
            text=True,
            check=False,
        )
    except FileNotFoundError:
        return "make not found"
    if proc.returncode != 0:
        return (proc.stderr.strip().splitlines() or ["make failed"])[-1]
    return ""


def main() -> int:
    """Print the tables; 1 if the firmware misses its drive-off or stamp limit or is slower than real time."""
    why = _build()
    if why:
        print(
            f"firmware bench not run: {why}\n"
            "(apt-get install gcc-avr avr-libc binutils-avr simavr libsimavr-dev libelf-dev)"
        )
        return 0
    with tempfile.TemporaryDirectory(prefix="bench-fw-") as tmp:
        lock = _lockstep(Path(tmp) / "truth.csv")
    speed = float(lock["speed"])  # type: ignore[arg-type]
    cut = lock["cut"]
    start_err = lock["start_err"]
    stamp_err = lock["stamp_err"]
    assert isinstance(cut, list) and isinstance(start_err, list) and isinstance(stamp_err, list)
    # The lockstep figures first: emulator cycles, whatever the machine's load.
    print_table(
        ["firmware timing (emulator cycles)", "p50", "max", "limit"],
        [
            ("arrival edge -> drive off, ns", statistics.median(cut), max(cut), CUT_LIMIT_NS),
            (
                "start: drive pin - commanded instant, us",
                statistics.median(start_err),
                max(start_err, key=abs),
                "+-1 tick",
            ),
            (
                "stamp: |START/EDGE stamp - pin|, us",
                statistics.median(stamp_err),
                max(stamp_err),
                STAMP_LIMIT_US,
            ),
        ],
        title=f"firmware timing, {STROKES} compare-timed strokes in lockstep",
    )
    print()
    ok = max(cut) <= CUT_LIMIT_NS and max(stamp_err) <= STAMP_LIMIT_US and speed > 1
    try:
        fw_cpu, fw_late = _real_time("firmware")
        py_cpu, py_late = _real_time("python")
    except RuntimeError as exc:
        # A machine too busy to keep the emulated device in real time: said, and counted a miss.
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        print(f"emulator cost in real time not measured: {exc} (load average {load}); lockstep x{speed:.0f}")
        return 1
    print_table(
        ["device", "lockstep x real time", "real-time CPU % of a core", "START late p50 / max us"],
        [
            (
                "firmware in simavr (usmswitch-avrsim)",
                f"{speed:.0f}",
                f"{100 * fw_cpu:.1f}",
                f"{statistics.median(fw_late) / 1e3:.0f} / {max(fw_late) / 1e3:.0f}",
            ),
            (
                "peer: sim/mcu_emulator.py",
                "1 (real time only)",
                f"{100 * py_cpu:.1f}",
                f"{statistics.median(py_late) / 1e3:.0f} / {max(py_late) / 1e3:.0f}",
            ),
        ],
        title=f"emulator cost: {STROKES} strokes lockstep, {RT_STROKES} strokes in real time over a pty "
        f"(one every {PERIOD_US / 1000:.0f} ms)",
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
