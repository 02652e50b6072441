"""Test helpers: the MCU emulator on a pty or behind the fake pyusb backend, and a stroke runner."""

from __future__ import annotations

from dataclasses import dataclass, field

from usmswitch.drivers import Direction, Event, EventKind
from usmswitch.drivers.mcu import McuDaq

# Short link timings keep fault tests quick; the ratios are those of the defaults.
FAST = {
    "heartbeat_ns": 20_000_000,
    "link_timeout_ns": 120_000_000,
    "watchdog_ms": 150,
    "reconnect_min_ns": 20_000_000,
    "reconnect_max_ns": 100_000_000,
}


@dataclass
class StrokeSeen:
    t_cmd_ns: int
    events: list[Event] = field(default_factory=list)
    report: Event | None = None
    after: list[Event] = field(default_factory=list)

    def of(self, kind: EventKind) -> list[Event]:
        return [e for e in self.events if e.kind is kind]

    @property
    def start(self) -> Event:
        (s,) = self.of(EventKind.START)
        return s

    def edge(self, channel: int, level: int) -> Event:
        (e,) = [x for x in self.of(EventKind.EDGE) if x.channel == channel and x.level == level]
        return e


def run_stroke(
    daq: McuDaq, direction: Direction, delay_ns: int = 1_000_000, lead_ns: int = 2_000_000
) -> StrokeSeen:
    """Arm, command at now + lead, and collect events until the stroke's STOP or a fault; an arrived
    stroke's REPORT (the device's account, after the PONG that checks the clock) is `seen.report`."""
    daq.arm(direction, delay_ns)
    cmd = daq.command(daq.now_ns() + lead_ns)
    seen = StrokeSeen(cmd.t_cmd_ns)
    while True:
        ev = daq.recv(300_000_000)
        assert ev is not None, f"no event; so far {seen.events}"
        if ev.kind is EventKind.REPORT:
            seen.report = ev
            continue
        seen.events.append(ev)
        if ev.kind in (EventKind.STOP, EventKind.FAULT):
            break
    while seen.report is None and ev.kind is EventKind.STOP and ev.detail == "arrived":
        nxt = daq.recv(300_000_000)
        assert nxt is not None, f"no REPORT after {seen.events}"
        if nxt.kind is EventKind.REPORT:
            seen.report = nxt
        else:
            seen.after.append(nxt)  # a bounce's edges may come before the PONG that lets it go
    return seen


def wait_for(pred, timeout_s: float = 3.0, step_s: float = 0.01) -> bool:
    import time

    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step_s)
    return pred()
