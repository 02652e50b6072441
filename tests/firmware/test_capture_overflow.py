"""Edge stamps at every cycle around a timer overflow, in lockstep against the harness's truth.

Timer 4/5 overflow every 524,288 cycles (32.768 ms); the clock's high part is counted by an
overflow interrupt. An edge captured in the last cycles before an overflow whose capture
interrupt runs only after it (the CPU waking, a UART handler before its `sei`, the main loop in a
`cli` section) was stamped one period late on sensor B when the overflow handler outranked its
capture vector (issue 23). Each trial here puts one edge on one sensor at one cycle offset of the
last 64 before an overflow and the first 64 after it:

* alone (the CPU asleep);
* with a UART byte arriving 12 cycles before the edge (its handler holds interrupts off across it);
* with the main loop inside each of its `cli` sections, each section found by tracing what the main
  loop does for a PING, a COMMAND, a STOP and an edge of the other sensor, then centred on the
  overflow;

and every stamp must equal the harness's truth (the firmware's clock at the edge's cycle). The
trials must also show that they reached the race: in each group some edge came before the overflow
and its capture interrupt only after it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from avrsim import FirmwareDevice, Lockstep
from conftest import BUILD, make

from usmswitch.drivers import mcu_protocol as mp

PERIOD = 65536 * 8  # cycles of one timer period (0.5 us ticks at clk/8)
WINDOW = 64
OFFSETS = range(-WINDOW, WINDOW)
CAPTURE_VECTOR = {0: 41, 1: 46}  # TIMER4_CAPT (sensor A), TIMER5_CAPT (sensor B)
UART_LEAD = 12  # the UART byte's handler starts this many cycles before the edge


@dataclass
class Trial:
    group: str
    channel: int
    offset: int
    truth_us: int
    stamps: list[int]
    held_across: bool  # captured before the overflow, its interrupt entered after it
    span: int  # where the interrupts-off stretch in progress at the edge began (-1: none)


class Bench:
    """The firmware in lockstep with a session open, tracing edges and interrupts."""

    def __init__(self, avrsim: Path, elf: Path) -> None:
        self.sim = Lockstep(avrsim, elf)
        self.dev = FirmwareDevice(self.sim)
        self.seq = 0
        self.dev.write(b"\x00")
        self.send(mp.Hello(1, 0, 60_000))
        self.dev.run(3000)
        self.origin = self.sim.origin()
        self.levels = [1, 0]  # the rig rests at A
        self.stroke = 0
        self.got: list[mp.Message] = []
        self.sim.trace(1)
        self.rx_delay = self._rx_delay()

    def close(self) -> None:
        self.sim.close()

    def send(self, msg: mp.Message) -> None:
        self.dev.send(msg, self.seq)
        self.seq = (self.seq + 1) % 65536

    def frames(self, until: int) -> list[mp.Message]:
        """Run to `until`; every message the firmware sent since the last call."""
        self.got += [m for _, m in self.dev.decoder.feed(self.sim.run_to(until))]
        got, self.got = self.got, []
        return got

    def next_overflow(self, lead: int = 40_000) -> int:
        k = (self.sim.cycle + lead - self.origin) // PERIOD + 1
        return self.origin + k * PERIOD

    def _rx_delay(self) -> int:
        """Cycles from handing the harness a byte to its receive interrupt (vector 25)."""
        self.sim.irqs.clear()
        sent = self.sim.cycle
        self.dev.write(b"\x00")
        self.sim.run(1000)
        return next(c for v, c in self.sim.irqs if v == 25) - sent

    def toggle(self, ch: int, cycle: int) -> int:
        self.levels[ch] ^= 1
        self.sim.edge(ch, self.levels[ch], cycle)
        return self.levels[ch]

    def trial(self, group: str, ch: int, offset: int, stimulus: Callable[[int], None] | None = None) -> Trial:
        ovf = self.next_overflow()
        n_sensors, n_irqs = len(self.sim.sensors), len(self.sim.irqs)
        self.frames(self.sim.cycle)  # forget what came before
        level = self.toggle(ch, ovf + offset)
        if stimulus is not None:
            stimulus(ovf)
        got = self.frames(ovf + 40_000)
        if self.stroke_open:
            self.send(mp.Stop(1))
            self.stroke_open = False
            got += self.frames(self.sim.cycle + 16_000)
        (edge,) = [s for s in self.sim.sensors[n_sensors:] if s[0] == ch]
        _, _, cycle, truth_us, span = edge
        entry = min(c for v, c in self.sim.irqs[n_irqs:] if v == CAPTURE_VECTOR[ch] and c >= cycle)
        stamps = [m.t_us for m in got if isinstance(m, mp.Edge) and m.channel == ch and m.level == level]
        return Trial(group, ch, offset, truth_us, stamps, cycle < ovf <= entry, span)

    stroke_open = False

    def at(self, cycle: int, msg: mp.Message) -> None:
        """Send `msg` so that its bytes start arriving at `cycle`."""
        self.got += [m for _, m in self.dev.decoder.feed(self.sim.run_to(cycle))]
        self.send(msg)

    # -- stimuli: what the main loop is given to do, the trigger at cycle b ---------------------
    def ping(self, b: int) -> None:
        self.at(b, mp.Ping(b & 0xFFFF))

    def command(self, b: int) -> None:
        self.stroke += 1
        self.at(b - 8000, mp.Arm(self.stroke, 0, 1_000_000, 100_000))  # starts in 1 s: stopped first
        self.at(b, mp.Command(self.stroke, 0, 0))
        self.stroke_open = True

    def stop(self, b: int) -> None:
        self.stroke += 1
        self.at(b - 16_000, mp.Arm(self.stroke, 0, 1_000_000, 100_000))
        self.at(b - 8000, mp.Command(self.stroke, 0, 0))
        self.at(b, mp.Stop(1))  # the scheduled stroke ends: hal_drive_off

    def other_edge(self, ch: int) -> Callable[[int], None]:
        def stimulus(b: int) -> None:
            self.toggle(ch ^ 1, b)

        return stimulus


def _main_sections(bench: Bench, stimulus: Callable[[int], None]) -> list[tuple[int, int, int]]:
    """(pc, start after the trigger, cycles) of the main loop's interrupts-off sections that the
    stimulus makes it run, traced far from an overflow."""
    bench.sim.trace(2)
    b = bench.next_overflow(lead=PERIOD // 2 + 40_000) - PERIOD // 2
    n = len(bench.sim.clis)
    stimulus(b)
    bench.frames(b + 16_000)
    if bench.stroke_open:
        bench.send(mp.Stop(1))
        bench.stroke_open = False
        bench.frames(bench.sim.cycle + 16_000)
    bench.sim.trace(1)
    out = []
    for name, pc, start, length in bench.sim.clis[n:]:
        if b <= start < b + 16_000 and not name.startswith(("vector", "__vector", "reset")):
            out.append((pc, start - b, length))
    return out


#: How long each swept main-loop section ran when traced (cycles with interrupts off).
lengths: dict[str, int] = {}


def _sweep(bench: Bench) -> list[Trial]:
    trials = []
    for ch in (0, 1):
        for off in OFFSETS:
            trials.append(bench.trial("alone", ch, off))
    for ch in (0, 1):
        for off in OFFSETS:
            lead = UART_LEAD + bench.rx_delay

            def byte(ovf: int, off: int = off, lead: int = lead) -> None:
                bench.got += [m for _, m in bench.dev.decoder.feed(bench.sim.run_to(ovf + off - lead))]
                bench.dev.write(b"\x00")  # an idle-line byte: the handler runs, the core ignores it

            trials.append(bench.trial("uart", ch, off, byte))
    for ch in (0, 1):
        scenarios = {
            "ping": bench.ping,
            "command": bench.command,
            "stop": bench.stop,
            "other-edge": bench.other_edge(ch),
        }
        seen: set[int] = set()
        for name, stimulus in scenarios.items():
            for pc, start, length in _main_sections(bench, stimulus):
                if pc in seen:
                    continue
                seen.add(pc)
                lengths[f"cli:{name}:{pc:#x}"] = length
                for off in OFFSETS:
                    # the section centred on the overflow: the trigger that far before it
                    def centred(
                        ovf: int, s: Callable[[int], None] = stimulus, d: int = start + length // 2
                    ) -> None:
                        s(ovf - d)

                    trials.append(bench.trial(f"cli:{name}:{pc:#x}", ch, off, centred))
    return trials


def _run_sweep(avrsim: Path, elf: Path) -> list[Trial]:
    bench = Bench(avrsim, elf)
    try:
        return _sweep(bench)
    finally:
        bench.close()


def _report(trials: list[Trial]) -> tuple[list[Trial], dict[str, int]]:
    wrong = [t for t in trials if t.stamps != [t.truth_us]]
    races: dict[str, int] = {}
    for t in trials:
        key = f"{t.group} ch{t.channel}"
        races[key] = races.get(key, 0) + (t.held_across and (not t.group.startswith("cli") or t.span != -1))
    return wrong, races


def test_every_stamp_is_right_at_every_cycle_around_an_overflow(avrsim: Path, firmware_elf: Path) -> None:
    trials = _run_sweep(avrsim, firmware_elf)
    wrong, races = _report(trials)
    assert not wrong, (
        "\n".join(
            f"{t.group} sensor {'AB'[t.channel]} offset {t.offset:+d}: stamps {t.stamps} truth {t.truth_us}"
            for t in wrong[:20]
        )
        + f"\n({len(wrong)} of {len(trials)} wrong)"
    )
    # the trials reached the race they are about, in every group and on both sensors
    assert all(n > 0 for key, n in races.items() if key.startswith("uart")), races
    groups = {t.group for t in trials if t.group.startswith("cli")}
    assert len(groups) >= 4, groups  # the main loop's sections were found and swept
    # Each section long enough to hold a capture back was met by an edge that came inside it
    # before the overflow, its interrupt entered after it. (The compiler's 2-cycle sections around
    # a stack-pointer update hold it back by one instruction: swept, not necessarily met.)
    for g in groups:
        if lengths[g] >= 8:
            assert any(t.held_across and t.span != -1 for t in trials if t.group == g), (g, lengths[g])


@pytest.fixture(scope="module")
def planted_elf(avrsim: Path) -> Path:
    """The firmware with the stamp computation of before issue 23 (test image, never flashed)."""
    make("build/usmswitch-plant.elf")
    return BUILD / "usmswitch-plant.elf"


def test_the_sweep_finds_the_old_one_period_error(avrsim: Path, planted_elf: Path) -> None:
    wrong, _ = _report(_run_sweep(avrsim, planted_elf))
    assert any(t.channel == 1 for t in wrong), "the sweep passed the firmware with the old stamp computation"
    # one period late, each (sensor A's too here: its handler now lets the overflow's run first)
    assert all(s - t.truth_us == 32768 for t in wrong for s in t.stamps), [
        (t.stamps, t.truth_us) for t in wrong
    ]
