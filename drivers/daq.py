"""The DAQ driver interface every driver implements (sim, serial MCU, USB).

Like python-can's BusABC, the base class owns the policy (argument checks, software timing of
starts, debouncing, event-order checks, counters) and a driver supplies only the mechanism:
how to switch the drive, how to arm a hardware delay, and how events arrive (`_recv_internal`).
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections import deque

from .clock import Clock
from .events import Channel, Commanded, Conditions, Direction, Event, EventKind, FaultCode

DEFAULT_DEBOUNCE_NS = 100_000


class DaqError(Exception):
    """The driver cannot do what was asked; the message says why."""


class DaqDisconnected(DaqError):
    """The device went away (unplugged, port closed); the drive must be taken as stopped."""


def check_ns(name: str, value: object, *, minimum: int = 0) -> int:
    """Validate an integer nanosecond argument (bools and floats are refused)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an integer of nanoseconds, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum} ns, got {value!r}")
    return value


class Daq(ABC):
    """A limit-sensor timestamper and motor-start trigger.

    Hardware-timed drivers arm the device with the delay and the device starts the motor and stamps
    the edges on its own clock. Software-timed drivers leave the start to `command`, which sleeps
    then spins on `clock` until command + delay and switches the drive, stamping on the host.
    """

    #: True when the device delays the start and stamps edges itself.
    hardware_timed: bool = False
    #: Short driver name for logs and status ("sim", "serial", "usb").
    name: str = "daq"

    def __init__(self, *, clock: Clock, debounce_ns: int = DEFAULT_DEBOUNCE_NS) -> None:
        self.clock = clock
        self.debounce_ns = check_ns("debounce_ns", debounce_ns)
        self._armed: tuple[Direction, int] | None = None
        self._pending: deque[Event] = deque()
        self._last_edge_ns: list[int | None] = [None, None]
        self._last_t_ns: int | None = None
        self._lock = threading.RLock()  # stop() may come from another thread
        self.is_open = False
        #: Edges dropped by the debouncer.
        self.bounces = 0
        #: Events whose stamp went backwards (dropped, reported as a SEQUENCE fault).
        self.out_of_order = 0

    # -- lifecycle ---------------------------------------------------------------------------
    def open(self) -> None:
        """Connect to the device; raises DaqError with the reason if it cannot."""
        with self._lock:
            if not self.is_open:
                self._open()
                self.is_open = True

    def close(self) -> None:
        """Switch the drive off and release the device. Safe to call twice."""
        with self._lock:
            if not self.is_open:
                return
            try:
                self._stop()
            finally:
                self.is_open = False
                self._close()

    def __enter__(self) -> Daq:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def ping(self) -> bool:
        """True when the device answers (the default: it is open)."""
        return self.is_open

    # -- timing ------------------------------------------------------------------------------
    def now_ns(self) -> int:
        """The driver's clock: the one every event stamp is on."""
        return self.clock.now_ns()

    def conditions(self) -> Conditions | None:
        """Drive conditions now (temperature, frequency), when this driver knows them."""
        return None

    def arm(self, direction: Direction, delay_ns: int) -> None:
        """Set the next stroke: its direction and the start delay after its command."""
        direction = Direction(direction)
        check_ns("delay_ns", delay_ns)
        with self._lock:
            self._armed = (direction, delay_ns)
            if self.hardware_timed:
                self._arm(direction, delay_ns)

    @property
    def armed(self) -> tuple[Direction, int] | None:
        return self._armed

    def command(self, t_cmd_ns: int | None = None) -> Commanded:
        """Command the armed stroke; the motor starts `delay_ns` after the command instant.

        `t_cmd_ns` is a scheduled command instant on this clock (a cycler's tick); None means now.
        A software-timed driver blocks until the start. A start past its instant is not an error:
        it is reported as `lateness_ns`, for the caller to count.
        """
        with self._lock:
            if self._armed is None:
                raise DaqError("command without an armed stroke: call arm(direction, delay_ns) first")
            if not self.is_open:
                raise DaqError(f"{self.name}: command on a closed driver")
            direction, delay_ns = self._armed
            self._armed = None
        if self.hardware_timed:
            t_cmd = self._command(t_cmd_ns)
            return Commanded(direction, t_cmd, delay_ns)
        t_cmd = self.clock.now_ns() if t_cmd_ns is None else check_ns("t_cmd_ns", t_cmd_ns)
        target = t_cmd + delay_ns
        self.clock.sleep_until(target)
        with self._lock:
            t_start = self._drive(direction)
            self._pending.append(Event.start(t_start, direction))
        return Commanded(direction, t_cmd, delay_ns, t_start, t_start - target)

    def stop(self, detail: str = "stop") -> None:
        """Switch the drive off now (end of stroke, stall, emergency stop). Any thread may call it."""
        with self._lock:
            self._armed = None
            if self.is_open:
                self._stop()
                self._pending.append(Event.stop(self.clock.now_ns(), detail=detail))

    # -- events ------------------------------------------------------------------------------
    def recv(self, timeout_ns: int | None = None) -> Event | None:
        """The next event, debounced and in order, or None if none came within `timeout_ns`.

        None as the timeout waits for as long as events may still come (a virtual clock with
        nothing scheduled answers None at once rather than wait forever).
        """
        deadline = None if timeout_ns is None else self.clock.now_ns() + check_ns("timeout_ns", timeout_ns)
        while True:
            with self._lock:
                ev = self._pending.popleft() if self._pending else None
            if ev is None:
                ev = self._recv_internal(deadline)
                if ev is None:
                    return None
            if self._last_t_ns is not None and ev.t_ns < self._last_t_ns:
                self.out_of_order += 1
                return Event.fault_event(
                    self._last_t_ns,
                    FaultCode.SEQUENCE,
                    f"{ev.kind.name} stamped {ev.t_ns} ns, before the previous event at {self._last_t_ns} ns",
                )
            if ev.kind is EventKind.EDGE and self._is_bounce(ev):
                self.bounces += 1
                continue
            self._last_t_ns = ev.t_ns
            return ev

    def _is_bounce(self, ev: Event) -> bool:
        ch = Channel(ev.channel)
        last = self._last_edge_ns[ch]
        if last is not None and ev.t_ns - last < self.debounce_ns:
            return True
        self._last_edge_ns[ch] = ev.t_ns
        return False

    def _push(self, ev: Event) -> None:
        """Queue an event the driver produced outside `_recv_internal` (e.g. a fault on write)."""
        with self._lock:
            self._pending.append(ev)

    # -- the mechanism a driver supplies ------------------------------------------------------
    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def _stop(self) -> None:
        """Drive off, now."""

    @abstractmethod
    def _recv_internal(self, deadline_ns: int | None) -> Event | None:
        """The next raw event, waiting until `deadline_ns` on `clock` at most (None: no limit)."""

    def _drive(self, direction: Direction) -> int:
        """Software-timed: drive on in `direction` now; return the start stamp."""
        raise DaqError(f"{self.name} is hardware-timed: it does not start the drive from the host")

    def _arm(self, direction: Direction, delay_ns: int) -> None:
        """Hardware-timed: send the next stroke's direction and delay to the device."""
        raise DaqError(f"{self.name} is software-timed: there is nothing to arm on the device")

    def _command(self, t_cmd_ns: int | None) -> int:
        """Hardware-timed: trigger the armed stroke; return the device's command stamp."""
        raise DaqError(f"{self.name} is software-timed: command() times the start on the host")
