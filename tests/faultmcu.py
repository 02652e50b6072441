"""A fault-injecting fake MCU: the firmware emulator with a hand on its transmit side.

It speaks docs/mcu-protocol.md as `McuEmulator` does, over a pty (`PtyLink`), and every frame it
sends is valid (COBS, CRC, the firmware's own sequence numbers): what it injects is what a confused
device or a noisy line that happens to pass the CRC would say. `tamper` rewrites each frame the
firmware sends into any list of frames; `say` sends one more now; `flood` sends EDGE frames as fast
as the line takes them. Importable from any test (tests/conftest.py puts this folder on sys.path).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

from usmswitch.drivers.mcu_protocol import Edge, Message, Start, Stroke
from usmswitch.sim.mcu_emulator import McuEmulator, PtyLink

Tamper = Callable[[Message], list[Message]]


class FaultyMcu(McuEmulator):
    """`McuEmulator` whose outgoing frames pass through `tamper` (None: sent as the firmware says)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.tamper: Tamper | None = None
        #: Frames `tamper` replaced, and frames sent by say/flood.
        self.tampered = 0
        self.said = 0

    def _send(self, msg: Message) -> None:
        tamper = self.tamper
        if tamper is None:
            super()._send(msg)
            return
        out = tamper(msg)
        if out != [msg]:
            self.tampered += 1
        for m in out:
            super()._send(m)

    def say(self, msg: Message) -> None:
        """Send `msg` now, numbered in the firmware's sequence."""
        with self._lock:
            self.said += 1
            super()._send(msg)

    def flood(self, duration_s: float, channel: int = 0) -> int:
        """EDGE frames of `channel`, each repeating its present level (a chattering report), stamped
        now, as fast as the line takes them for `duration_s`; returns how many were sent."""
        n = 0
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            with self._lock:
                level = self.rig.sensors()[channel]
                for _ in range(200):
                    super()._send(Edge(channel, int(level), self.device_us()))
                n += 200
        self.said += n
        return n


def start_of_stroke(k: int, make: Callable[[Start], list[Message]]) -> Tamper:
    """A tamper that rewrites the k-th START the firmware sends (1-based) with `make`."""
    seen = [0]
    lock = threading.Lock()

    def tamper(msg: Message) -> list[Message]:
        if isinstance(msg, Start):
            with lock:
                seen[0] += 1
                if seen[0] == k:
                    return make(msg)
        return [msg]

    return tamper


def drop_report_of(stroke_ids: set[int], inner: Tamper | None = None) -> Tamper:
    """A tamper that drops the STROKE report of the given stroke ids (after `inner`)."""

    def tamper(msg: Message) -> list[Message]:
        out = inner(msg) if inner is not None else [msg]
        return [m for m in out if not (isinstance(m, Stroke) and m.stroke in stroke_ids)]

    return tamper


def plug(tmp_path: Path, **kwargs: object) -> tuple[FaultyMcu, PtyLink, Path]:
    """A started FaultyMcu behind a pty whose stable path is tmp_path/usmswitch."""
    emu = FaultyMcu(**kwargs).start()
    path = tmp_path / "usmswitch"
    link = PtyLink(emu, path).plug()
    return emu, link, path
