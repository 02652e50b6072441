"""What the driver reports while no stroke is going: read so nothing piles up, counted, and said."""

from __future__ import annotations

import contextlib
import time
from typing import Any

import structlog

from usmswitch.drivers import Daq, DaqError, EventKind, FaultCode

log = structlog.get_logger("usmswitch.loop")

#: At most this many events read per idle pass (a flood waits for the next pass, requests first).
IDLE_READ_MAX = 10_000
IDLE_EDGES_LOG_EVERY_NS = 10_000_000_000


class IdleEvents:
    """Counts of what came between strokes: sensor edges (said at most every 10 s) and the rest."""

    def __init__(self) -> None:
        #: Sensor edges reported while no stroke was going (the mover moved by hand, a sensor chatters).
        self.edges = 0
        #: Driver events read and dropped outside a stroke (idle, a fault reset).
        self.stale = 0
        self._said_ns = -IDLE_EDGES_LOG_EVERY_NS

    def read(self, daq: Daq, latch_drive: bool) -> str:
        """Read what `daq` has queued (at most IDLE_READ_MAX). With `latch_drive` (the loop idle),
        returns the reason of the first DRIVE fault among it ("" when none): the device restarted
        (its watchdog, a brown-out) or the drive failed between strokes, which a person looks at
        before the next stroke, as after one mid-stroke. Other events are counted stale."""
        edges: list[Any] = []
        drive_fault = ""
        try:
            for _ in range(IDLE_READ_MAX):
                ev = daq.recv(0)
                if ev is None:
                    break
                if ev.kind is EventKind.EDGE:
                    edges.append(ev)
                elif (
                    latch_drive
                    and not drive_fault
                    and ev.kind is EventKind.FAULT
                    and ev.fault is FaultCode.DRIVE
                ):
                    drive_fault = f"drive: {ev.detail}" if ev.detail else "drive"
                else:  # a link's own faults reach status through the driver (driver_ok, counters)
                    self.stale += 1
        except DaqError:
            return drive_fault
        if edges:
            self._count(edges)
        return drive_fault

    def drain(self, daq: Daq) -> None:
        """Drop what the driver queued while faulted (the disconnect itself, late edges)."""
        with contextlib.suppress(DaqError):
            while daq.recv(0) is not None:
                self.stale += 1

    def _count(self, edges: list[Any]) -> None:
        self.edges += len(edges)
        now = time.monotonic_ns()
        if now - self._said_ns >= IDLE_EDGES_LOG_EVERY_NS:
            self._said_ns = now
            last = edges[-1]
            log.warning(
                "sensor edges while idle: the mover was moved by hand, or a sensor chatters",
                edges=len(edges),
                total=self.edges,
                last=f"sensor {last.channel.name} {'active' if last.level else 'released'}",
            )


def _is_drive_fault(ev: Any) -> bool:
    return ev.kind is EventKind.FAULT and ev.fault is FaultCode.DRIVE
