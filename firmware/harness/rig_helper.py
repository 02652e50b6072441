"""The rig model for the simavr harness: the project's UsmSwitchModel behind a line protocol.

firmware/build/usmswitch-avrsim starts this as a child and asks it, on stdin, what the limit
sensors do when the drive pin changes; times are emulated nanoseconds since power-on (the
physical timeline, before any crystal error). The rig is sim/mcu_rig.py's Mover, the one the
Python emulator uses (positions, the start dead time, a jammed stroke, a bounce after arrival), so
the firmware meets the same physics as the emulator.

    init                 -> sensors A B            (1 = active)
    on T_NS DIR          -> edge T_NS CH LEVEL ... end
    off T_NS             -> edge T_NS CH LEVEL ... end   (bounce edges after an arrival)
    stall | bounce       -> end                     (the next stroke jams / bounces)
"""

from __future__ import annotations

import argparse
import sys

from usmswitch.drivers.events import Channel, Direction
from usmswitch.sim.mcu_rig import Mover
from usmswitch.sim.model import UsmSwitchModel


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start-at", choices=("A", "B"), default="A")
    args = ap.parse_args(argv)
    rig = Mover(UsmSwitchModel(seed=args.seed), Channel.B if args.start_at == "B" else Channel.A)
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
            edges: list[tuple[int, Channel, int]] = []
            if cmd == "on":
                d = Direction(int(words[2]))
                edges = rig.start(d, int(words[1])).edges(d)
            elif cmd == "off":
                edges = rig.stop(int(words[1]))
            elif cmd == "stall":
                rig.jam_next()
            elif cmd == "bounce":
                rig.bounce_next()
            for t, ch, level in edges:
                out.write(f"edge {t} {int(ch)} {level}\n")
            out.write("end\n")
        out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
