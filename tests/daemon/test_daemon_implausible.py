"""Strokes that are not physically strokes, through the daemon process (issue 29, item 2): a lone
arrival 1 us after the start is a glitch the stroke outlives; an arrival before the departure is
kept, flagged IMPLAUSIBLE, never learned, and latches a FAULT that says so (not "stall").
The fault-injecting fake MCU (tests/faultmcu.py) on a pty; `usmswitchd --driver serial`."""

from __future__ import annotations

import threading

import faultmcu
import pytest
from test_daemon_hw_checks import FAULT, MS, daemon, rows, run

from usmswitch.drivers.mcu_protocol import U32_MOD, Edge, Message, Start, Stroke
from usmswitch.protocol.record import Flag

pytestmark = pytest.mark.realtime


def test_a_lone_arrival_is_a_glitch_and_an_arrival_before_the_departure_is_not_a_stroke(tmp_path) -> None:
    with faultmcu.plugged(tmp_path, seed=8) as (emu, port), daemon(tmp_path, port) as (c, _):
        # 1. An arrival 1 us after the 3rd start, no departure: it was recorded as a clean 1 us
        #    stroke (and learned: the next stroke of that direction 10 ms off).
        def lone_arrival(s: Start) -> list[Message]:
            return [s, Edge(1 - s.direction, 1, (s.t_us + 1) % U32_MOD)]

        emu.tamper = faultmcu.start_of_stroke(3, lone_arrival)
        st = run(c, 60 * MS, 8)
        assert st["state"] == "idle", st["fault"]
        first = rows(tmp_path)
        truth = [s.t_arrive_ns - s.t_start_ns for s in emu.log]

        # 2. The 2nd stroke of the next run: its own edges and report lost, and instead the
        #    destination active at +5 ms and the source released at +6 ms.
        lock, seen, mine = threading.Lock(), [0], set()

        def reversed_edges(msg: Message) -> list[Message]:
            with lock:
                if isinstance(msg, Start):
                    seen[0] += 1
                    if seen[0] == 2:
                        mine.add(msg.stroke)
                        src, dst = msg.direction, 1 - msg.direction
                        emu.later(5 * MS, lambda t_us: Edge(dst, 1, t_us))
                        emu.later(6 * MS, lambda t_us: Edge(src, 0, t_us))
                        return [msg]
                    mine.clear()
                if mine and isinstance(msg, Edge | Stroke):
                    return []  # the stroke's true edges and its report: lost
            return [msg]

        emu.tamper = reversed_edges
        st = run(c, 60 * MS, 4)
        emu.tamper = None
        status = c.status()
    assert len(first) == 8 and not [r for r in first if r[1] & FAULT], first
    assert abs(first[2][4] - truth[2]) < 50_000, (first[2], truth[2])  # the true stroke, not 1 us
    assert st["state"] == "fault" and st["fault"].startswith("implausible stroke: sensor "), st["fault"]
    assert "before the departure from sensor" in st["fault"] and "+5.000 ms" in st["fault"]
    bad = rows(tmp_path)[9]
    assert bad[1] & Flag.IMPLAUSIBLE and bad[1] & FAULT and not bad[1] & Flag.STALL
    assert status["implausible_strokes"] == 1
