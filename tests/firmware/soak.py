"""A soak of the firmware in simavr: strokes through the MCU protocol, every stamp against the truth.

The firmware image runs in lockstep (usmswitch-avrsim --lockstep --truth CSV) with the project's
rig model moving its sensors. Each stroke is armed and commanded like the daemon does it (ARM,
COMMAND at a device instant), aimed so that its arrival falls on a timer overflow (a multiple of
32,768 us on the firmware's clock, give or take a few microseconds: the operating time is
predicted from the truth of the last stroke the same way), with a PING arriving as it nears, so
the rare instants issue 23 was about come up by the thousand. For every stroke, the STROKE report's
start, depart and arrive stamps and the STOPPED instant are compared with the harness's truth
(computed from emulator cycles), and the truth's arrival-to-drive-off time must be under 5 us.
One stroke in two also has noise on its lines (issue 33), in turn, in both directions: a pulse
of 1-8 us on the far sensor at rest before the COMMAND (the capture unit misses its second edge
and must read it back), and chatter on the source sensor mid-stroke (a 3 us and a 12 us pulse,
40 us apart); the stamps must still equal the truth, and no edge may be lost.

    python tests/firmware/soak.py --strokes 100000 [--elf firmware/build/usmswitch.elf]

prints strokes per second, the worst difference of each stamp and the worst drive cut, and exits
1 when any stamp is off by more than a tick (1 us) or any cut takes 5 us or more.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from avrsim import FirmwareDevice, Lockstep, since_us

from usmswitch.drivers import mcu_protocol as mp

PERIOD_US = 32_768
U32 = 1 << 32
DELAY_US = 1000
CUT_LIMIT_NS = 5000
ROOT = Path(__file__).resolve().parents[2]


@dataclass
class SoakResult:
    strokes: int = 0
    seconds: float = 0.0
    #: worst |firmware - truth| in us per stamp: start, depart, arrive, stop (the STOPPED instant)
    worst_us: dict[str, int] = field(
        default_factory=lambda: {"start": 0, "depart": 0, "arrive": 0, "stop": 0}
    )
    worst_cut_ns: int = 0
    #: arrivals that came within 3 us of an overflow (before or after it)
    near_overflow: int = 0
    late_starts: int = 0
    #: strokes with noise on a line (a pulse at rest, chatter mid-stroke)
    noisy: int = 0
    #: edges the firmware lost (FAULT EVENTS_LOST) and read back flagged (EDGE flags MISSED)
    lost: int = 0
    missed: int = 0
    #: (stroke, stamp, firmware us, truth us) of every stamp off by more than 1 us
    wrong: list[tuple[int, str, int, int]] = field(default_factory=list)
    slow_cuts: list[tuple[int, int]] = field(default_factory=list)
    missing: list[int] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.wrong and not self.slow_cuts and not self.missing and not self.lost

    def summary(self) -> str:
        rate = self.strokes / self.seconds if self.seconds else 0.0
        w = self.worst_us
        return (
            f"{self.strokes} strokes in {self.seconds:.1f} s ({rate:.0f}/s), {self.near_overflow}"
            f" arrivals within 3 us of an overflow; worst |stamp - truth|: start {w['start']} us,"
            f" depart {w['depart']} us,"
            f" arrive {w['arrive']} us, drive-off {w['stop']} us; worst arrival-to-drive-off"
            f" {self.worst_cut_ns} ns; {len(self.wrong)} wrong stamps, {len(self.slow_cuts)} cuts >= 5 us,"
            f" {len(self.missing)} strokes without a report, {self.late_starts} late starts;"
            f" {self.noisy} noisy strokes, {self.missed} edges read back, {self.lost} lost"
        )


class _Truth:
    """The harness's truth CSV, read as it grows (a row per stroke, written at its drive-off)."""

    def __init__(self, path: Path) -> None:
        self.f = path.open()
        self.header: list[str] | None = None
        self.rows: dict[int, dict[str, str]] = {}

    def poll(self) -> None:
        while line := self.f.readline():
            if not line.endswith("\n"):  # a row half written: read it next time
                self.f.seek(self.f.tell() - len(line))
                return
            values = next(csv.reader([line]))
            if self.header is None:
                self.header = values
                continue
            row = dict(zip(self.header, values, strict=True))
            self.rows[int(row["stroke"])] = row

    def close(self) -> None:
        self.f.close()


def run_soak(
    avrsim: Path, elf: Path, strokes: int, workdir: Path, seed: int = 7, max_wrong: int = 50
) -> SoakResult:
    """Run `strokes` strokes; stops early once `max_wrong` stamps were wrong (a planted error)."""
    truth_csv = workdir / f"soak-truth-{elf.stem}-{seed}.csv"
    sim = Lockstep(avrsim, elf, "--seed", str(seed), "--truth", str(truth_csv))
    dev = FirmwareDevice(sim)
    truth = _Truth(truth_csv)
    res = SoakResult()
    seq = 0

    def send(msg: mp.Message) -> None:
        nonlocal seq
        dev.send(msg, seq)
        seq = (seq + 1) % 65536

    t0 = time.monotonic()
    try:
        dev.write(b"\x00")
        send(mp.Hello(1, 2, 60_000))
        got = [m for _, m in dev.run(5000)]
        assert any(isinstance(m, mp.HelloAck) for m in got), got
        predicted = {0: 8500, 1: 8500}  # operating time per direction, us
        direction = 0
        jitter = 0
        drive_ons = 0  # the harness numbers its truth rows by the drive going on
        for n in range(1, strokes + 1):
            now = sim.fw_us
            # the arrival aimed at an overflow, give or take a few microseconds (a sweep)
            jitter = (jitter + 7) % 13 - 6
            lead = DELAY_US + predicted[direction] + 1500  # the frames take ~0.3 ms to arrive
            target = ((now + lead) // PERIOD_US + 1) * PERIOD_US + jitter
            t_cmd = (target - predicted[direction] - DELAY_US) % U32
            noise = n % 8
            if noise in (3, 6):  # a pulse of 1-8 us on the far sensor, at rest (on and off strokes)
                width = 1 + (n // 8) % 8
                sim.command(f"square {direction ^ 1} {sim.cycle + 200 * 16} {width * 16} 2")
            send(mp.Arm(n % 65536, direction, DELAY_US, 100_000))
            send(mp.Command(n % 65536, t_cmd, 1))
            res.noisy += noise in (3, 4, 6, 7)
            msgs = []
            if noise in (4, 7):  # chatter on the source sensor, mid-stroke: a 3 us and a 12 us pulse
                mid = sim.cycle + (since_us(t_cmd, now) + DELAY_US + 3000) * 16
                sim.command(f"square {direction} {mid} {3 * 16} 2")
                msgs += [m for _, m in dev.run((mid - sim.cycle) // 16 + 20)]
                sim.command(f"square {direction} {mid + 40 * 16} {12 * 16} 2")
            # a PING arriving as the arrival nears: the UART and the main loop busy around it
            msgs += [m for _, m in dev.run(max(1, since_us(target, sim.fw_us) - 300))]
            send(mp.Ping(n))
            msgs += [m for _, m in dev.run(3000)]
            res.lost += sum(
                m.detail for m in msgs if isinstance(m, mp.Fault) and m.code == mp.DeviceFault.EVENTS_LOST
            )
            res.missed += sum(1 for m in msgs if isinstance(m, mp.Edge) and m.flags)
            report = next((m for m in msgs if isinstance(m, mp.Stroke) and m.stroke == n % 65536), None)
            stopped = next((m for m in msgs if isinstance(m, mp.Stopped) and m.stroke == n % 65536), None)
            drive_ons += any(isinstance(m, mp.Start) for m in msgs)
            truth.poll()
            row = truth.rows.pop(drive_ons, None)
            if report is None or stopped is None or row is None or not report.flags & mp.StrokeFlags.ARRIVED:
                res.missing.append(n)
                if len(res.missing) > 5:
                    raise AssertionError(f"strokes without a report: {res.missing}; last frames {msgs}")
                dev.run(200_000)  # let it settle (a stall ends by the device's timeout)
                truth.poll()
                truth.rows.clear()
                direction ^= 1
                continue
            res.strokes += 1
            if report.flags & mp.StrokeFlags.LATE:
                res.late_starts += 1
            stamps = {
                "start": (report.t_start_us, int(row["start_us"])),
                "depart": (report.t_depart_us, int(row["depart_us"])),
                "arrive": (report.t_arrive_us, int(row["arrive_us"])),
                "stop": (stopped.t_us, int(row["arrive_us"])),
            }
            for name, (fw, tr) in stamps.items():
                d = abs(since_us(fw, tr))
                res.worst_us[name] = max(res.worst_us[name], d)
                if d > 1:
                    res.wrong.append((n, name, fw, tr))
            cut = int(row["cut_ns"])
            res.worst_cut_ns = max(res.worst_cut_ns, cut)
            if cut >= CUT_LIMIT_NS:
                res.slow_cuts.append((n, cut))
            arrive = int(row["arrive_us"])
            off = arrive % PERIOD_US
            if min(off, PERIOD_US - off) <= 3:
                res.near_overflow += 1
            predicted[direction] = since_us(arrive, int(row["start_us"]))
            direction ^= 1
            if len(res.wrong) >= max_wrong:
                break
    finally:
        res.seconds = time.monotonic() - t0
        truth.close()
        sim.close()
        truth_csv.unlink(missing_ok=True)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--strokes", type=int, default=100_000)
    ap.add_argument("--elf", type=Path, default=ROOT / "firmware/build/usmswitch.elf")
    ap.add_argument("--avrsim", type=Path, default=ROOT / "firmware/build/usmswitch-avrsim")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp"))
    args = ap.parse_args(argv)
    res = run_soak(args.avrsim, args.elf, args.strokes, args.workdir, args.seed)
    print(res.summary())
    for n, name, fw, tr in res.wrong[:10]:
        print(f"  stroke {n} {name}: firmware {fw} us, truth {tr} us ({since_us(fw, tr):+d})")
    return 0 if res.ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
