"""Arrival edge to drive off, in lockstep: under 5 us whatever the firmware is doing as it comes.

A stroke is commanded; 200 us after the drive went on (before the rig model's own departure) the
destination sensor is made active at an exact cycle, and the drive pin must go low within 5 us
(80 cycles) of it, the harness timing both from emulator cycles. The edge is placed at every cycle
offset across each interrupts-off section the main loop runs for a PING, across the receive
handler of a byte arriving, and with the CPU asleep; with the sensor wired to INT4/INT5 as well as
the capture pins, only a section already running can hold the cut back. The longest wait measured
is printed for docs/firmware.md.
"""

from __future__ import annotations

from pathlib import Path

from avrsim import FirmwareDevice, Lockstep

from usmswitch.drivers import mcu_protocol as mp

F_CPU = 16_000_000
LIMIT_CYCLES = 80  # 5 us


class Rig:
    def __init__(self, avrsim: Path, elf: Path) -> None:
        self.sim = Lockstep(avrsim, elf, "--seed", "5")
        self.dev = FirmwareDevice(self.sim)
        self.seq = 0
        self.stroke = 0
        self.dev.write(b"\x00")
        self.send(mp.Hello(1, 1, 60_000))
        self.dev.run(5000)

    def send(self, msg: mp.Message) -> None:
        self.dev.send(msg, self.seq)
        self.seq = (self.seq + 1) % 65536

    def start(self) -> int:
        """An on stroke (A to B) commanded now; returns the cycle the drive went on."""
        self.stroke += 1
        n = len(self.sim.drive)
        self.send(mp.Arm(self.stroke, 0, 1000, 100_000))
        self.send(mp.Command(self.stroke, 0, 0))
        while len(self.sim.drive) == n:
            self.dev.run(100)
        level, cycle, _ = self.sim.drive[-1]
        assert level == 1
        return cycle

    def trial(self, stimulus, offset: int) -> tuple[int, int]:
        """(edge cycle, cycles to the drive off) for an arrival `offset` cycles after the stimulus."""
        on = self.start()
        b = on + 200 * 16
        n_sensors, n_drive = len(self.sim.sensors), len(self.sim.drive)
        self.sim.edge(1, 1, b + offset)
        if stimulus is not None:
            stimulus(b)
        self.sim.run_to(b + offset + 8000)
        (_, _, edge, _, _) = next(s for s in self.sim.sensors[n_sensors:] if s[0] == 1)
        (level, off, _) = self.sim.drive[n_drive]
        assert level == 0
        self.dev.run(3000)  # the stroke's report goes out
        self.sim.edge(1, 0, self.sim.cycle + 16)  # B released again: the mover never left A
        self.dev.run(2000)
        return edge, off - edge


def test_arrival_to_drive_off_is_under_5_us_in_every_section(avrsim: Path, firmware_elf: Path) -> None:
    rig = Rig(avrsim, firmware_elf)
    try:
        rig.sim.trace(2)

        def ping(b: int) -> None:
            rig.sim.run_to(b)
            rig.send(mp.Ping(b & 0xFFFF))

        # the main loop's sections for a PING, traced once (the arrival well after them)
        n = len(rig.sim.clis)
        marks: list[int] = []
        rig.trial(lambda b: (marks.append(b), ping(b)), 7000)
        b = marks[0]
        sections = [
            (name, start - b, length) for name, _, start, length in rig.sim.clis[n:] if b <= start < b + 6000
        ]
        rig.sim.trace(1)
        worst: dict[str, int] = {}
        offsets: set[int] = set()
        seen: set[str] = set()
        for name, start, length in sections:  # each section once, where it first ran
            if name not in seen:
                seen.add(name)
                offsets.update(range(start - 4, start + length + 4))
        # the CPU asleep, and every offset across every section (the receive handler's included)
        for off in [None, *sorted(offsets)]:
            _, cut = rig.trial(None, 0) if off is None else rig.trial(ping, off)
            key = "asleep" if off is None else "ping"
            worst[key] = max(worst.get(key, 0), cut)
            assert cut < LIMIT_CYCLES, (off, cut)
    finally:
        rig.sim.close()
    print({k: f"{v} cycles, {v * 1e6 / F_CPU:.2f} us" for k, v in worst.items()})


# An arrival's cut waits for the section running as it comes, one instruction (5 cycles at most)
# and its own 19: a section of 55 cycles keeps it under 80 (5 us).
SECTION_LIMIT = 55
# The start's compare handler runs with interrupts off throughout (no handler nests in it), only
# while the drive is off or at the instant it goes on, and then it arms and makes the cut itself
# in its first 35 cycles (test_an_arrival_as_the_drive_goes_on_is_cut_at_once): no arrival waits.
COMPARE_LIMIT = 180


def test_every_interrupts_off_section_is_bounded(avrsim: Path, firmware_elf: Path) -> None:
    """Strokes started on time, late (forced) and a period or more ahead (pre-armed), heartbeats
    in bursts, a stop: every stretch the firmware runs with interrupts off, as the harness measures
    it, stays within docs/firmware.md's table (55 cycles at most, the start's compare handler 160;
    the start-up's excepted)."""
    sim = Lockstep(avrsim, firmware_elf, "--seed", "4")
    dev = FirmwareDevice(sim)
    try:
        dev.open_session()
        seq = 1
        for n in range(1, 31):
            if n % 3 == 0:
                dev.send(mp.Arm(n, (n + 1) % 2, 1000, 100_000), seq)
                dev.send(mp.Command(n, 0, 0), seq + 1)
            elif n % 3 == 1:
                dev.send(mp.Arm(n, (n + 1) % 2, 40_000, 100_000), seq)  # pre-armed compare
                dev.send(mp.Command(n, 0, 0), seq + 1)
            else:
                dev.send(mp.Arm(n, (n + 1) % 2, 0, 100_000), seq)  # due 3 ms ago: forced, late
                dev.send(mp.Command(n, (sim.fw_us - 3000) % (1 << 32), 1), seq + 1)
            seq += 2
            for _ in range(8):
                dev.send(mp.Ping(n), seq)
                seq += 1
            dev.run(80_000)
        dev.send(mp.Arm(99, 0, 1_000_000, 100_000), seq)
        dev.send(mp.Command(99, 0, 0), seq + 1)
        dev.send(mp.Stop(1), seq + 2)
        dev.run(20_000)
        stats = sim.stats()
    finally:
        sim.close()
    spans = {}
    for line in stats:
        word, *rest = line.split()
        if word == "span" and rest[0] not in ("vector0", "reset"):
            spans[rest[0]] = int(rest[3])
    print(
        "\n".join(
            f"{where:32} {cycles:4d} cycles" for where, cycles in sorted(spans.items(), key=lambda x: -x[1])
        )
    )
    compare = spans.pop("vector42")
    assert compare <= COMPARE_LIMIT, compare
    assert max(spans.values()) <= SECTION_LIMIT, spans
    assert len(spans) >= 20  # the handlers and the main loop's sections were all met


def test_an_arrival_as_the_drive_goes_on_is_cut_at_once(avrsim: Path, firmware_elf: Path) -> None:
    """The destination sensor goes active at every cycle offset from 8 before the compare match
    that turns the drive on to 48 after it, before stop_mask is set (issue 33: such an arrival
    found the external interrupt disarmed and was cut a main-loop pass later): the compare
    handler arms the cut and looks at the sensor first, so the drive is off within 5 us of the
    later of the two instants, and the stroke ends as arrived."""
    rig = Rig(avrsim, firmware_elf)
    worst = 0
    try:
        origin = rig.sim.origin()
        for k in range(-8, 49, 2):
            rig.stroke += 1
            due_us = rig.sim.fw_us + 3000
            rig.send(mp.Arm(rig.stroke, 0, 1000, 100_000))
            rig.send(mp.Command(rig.stroke, (due_us - 1000) % (1 << 32), 1))
            due_cycle = origin + due_us * 16
            # B active from the match + k for 200 us (the noise layer: not cleared as the drive goes on)
            rig.sim.command(f"square 1 {due_cycle + k} 3200 2")
            n = len(rig.sim.drive)
            got = rig.dev.run(6000)
            assert len(rig.sim.drive) >= n + 2, f"an arrival {k} cycles after the match was not cut"
            (on, off) = rig.sim.drive[n : n + 2]
            assert (on[0], off[0]) == (1, 0), rig.sim.drive[n:]
            assert abs(on[1] - due_cycle) <= 16, (on, due_cycle)  # on at the match (a tick's slack)
            cut = off[1] - max(on[1], due_cycle + k)
            worst = max(worst, cut)
            assert cut < LIMIT_CYCLES, (k, cut)
            (stroke,) = [m for _, m in got if isinstance(m, mp.Stroke)]
            assert stroke.flags & mp.StrokeFlags.ARRIVED, (k, stroke)
            rig.dev.run(2000)
    finally:
        rig.sim.close()
    print(f"arrival as the drive goes on: cut within {worst} cycles, {worst * 1e6 / F_CPU:.2f} us")
