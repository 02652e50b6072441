"""The rig model for the simavr harness: the project's UsmSwitchModel behind a line protocol.

firmware/build/usmswitch-avrsim starts this as a child and asks it, on stdin, what the limit
sensors do when the drive pin changes; times are emulated nanoseconds since power-on (the
physical timeline, before any crystal error). It mirrors sim/mcu_emulator.py's use of the model
(positions, the start dead time, a jammed stroke, a bounce after arrival), so the firmware meets
the same physics as the Python emulator.

    init                 -> sensors A B            (1 = active)
    on T_NS DIR          -> edge T_NS CH LEVEL ... end
    off T_NS             -> edge T_NS CH LEVEL ... end   (bounce edges after an arrival)
    stall | bounce       -> end                     (the next stroke jams / bounces)
"""

from __future__ import annotations

import argparse
import sys

from usmswitch.drivers.events import Direction
from usmswitch.sim.mcu_emulator import BOUNCE_NS
from usmswitch.sim.model import UsmSwitchModel


class Rig:
    def __init__(self, seed: int, start_at_b: bool) -> None:
        self.model = UsmSwitchModel(seed=seed)
        p = self.model.params
        self.stroke_mm = p.stroke_mm
        self.release_mm = p.release_mm
        self.pos_mm = p.stroke_mm if start_at_b else 0.0
        self.stroke = None
        self.t_start_ns = 0
        self.arrive_ns: int | None = None
        self.direction = Direction.ON
        self.stall_next = False
        self.bounce_next = False

    def sensors(self) -> tuple[int, int]:
        a = 1 if self.pos_mm <= self.release_mm else 0
        b = 1 if self.pos_mm >= self.stroke_mm - self.release_mm else 0
        return a, b

    def on(self, t_ns: int, direction: int) -> list[tuple[int, int, int]]:
        d = Direction(direction)
        self.direction = d
        self.t_start_ns = t_ns
        self.arrive_ns = None
        self.stroke = None
        distance = (self.stroke_mm - self.pos_mm) if d is Direction.ON else self.pos_mm
        if distance <= self.release_mm:
            return []  # already there: the firmware sees the far sensor active at the start
        src_active = self.sensors()[int(d.source)] == 1
        jam = 0.5 if self.stall_next else None
        self.stall_next = False
        st = self.model.next_stroke(d, t_ns, distance_mm=distance, jam_fraction=jam)
        self.stroke = st
        edges = []
        if src_active and st.end_mm >= self.release_mm:
            edges.append((t_ns + st.time_at_ns(self.release_mm), int(d.source), 0))
        if st.operating_ns is not None:
            self.arrive_ns = t_ns + st.operating_ns
            edges.append((self.arrive_ns, int(d.dest), 1))
        return edges

    def off(self, t_ns: int) -> list[tuple[int, int, int]]:
        self.model.drive_off(t_ns)
        st, self.stroke = self.stroke, None
        if st is None:
            return []
        d = self.direction
        if self.arrive_ns is not None and t_ns >= self.arrive_ns:
            self.pos_mm = self.stroke_mm if d is Direction.ON else 0.0
            if not self.bounce_next:
                return []
            self.bounce_next = False
            ch = int(d.dest)
            a = self.arrive_ns
            return [(a + BOUNCE_NS, ch, 0), (a + 2 * BOUNCE_NS, ch, 1)]
        travelled = st.displacement_mm(t_ns - self.t_start_ns)
        if d is Direction.ON:
            self.pos_mm = min(self.stroke_mm, self.pos_mm + travelled)
        else:
            self.pos_mm = max(0.0, self.pos_mm - travelled)
        return []


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start-at", choices=("A", "B"), default="A")
    args = ap.parse_args(argv)
    rig = Rig(args.seed, args.start_at == "B")
    out = sys.stdout
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        cmd = words[0]
        if cmd == "init":
            a, b = rig.sensors()
            out.write(f"sensors {a} {b}\n")
        else:
            edges: list[tuple[int, int, int]] = []
            if cmd == "on":
                edges = rig.on(int(words[1]), int(words[2]))
            elif cmd == "off":
                edges = rig.off(int(words[1]))
            elif cmd == "stall":
                rig.stall_next = True
            elif cmd == "bounce":
                rig.bounce_next = True
            for t, ch, level in edges:
                out.write(f"edge {t} {ch} {level}\n")
            out.write("end\n")
        out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
