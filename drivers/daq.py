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
from .events import Commanded, Conditions, Direction, Event, EventKind, FaultCode

#: How far past the driver's clock (plus its delivery latency) a stamp may be and still be believed.
MAX_STAMP_AHEAD_NS = 5_000_000

DEFAULT_DEBOUNCE_NS = 100_000


class DaqError(Exception):
    """The driver cannot do what was asked; the message says why."""


class DaqDisconnected(DaqError):
    """The device went away (unplugged, port closed); the drive must be taken as stopped."""


class DaqHalted(DaqError):
    """The driver is halted (emergency stop, shutdown): no stroke may start until `release()`."""


def check_ns(name: str, value: object, *, minimum: int = 0) -> int:
    """Validate an integer nanosecond argument (bools and floats are refused)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an integer of nanoseconds, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum} ns, got {value!r}")
    return value


class _Hold:
    """An edge waiting for its sensor to settle, and the events that came in behind it."""

    __slots__ = ("behind", "changes", "edge", "level", "until_ns")

    def __init__(self, edge: Event, until_ns: int) -> None:
        self.edge = edge
        self.level = edge.level
        self.changes = 0
        self.until_ns = until_ns
        self.behind: list[Event] = []


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
    #: How long after its stamp an event can reach the host (a link's transit time): the
    #: debouncer waits this much longer before deciding that a sensor has settled.
    delivery_latency_ns: int = 0
    #: Hardware-timed: how far ahead of its instant a command is sent (the device waits).
    command_lead_ns: int = 0
    #: True when the driver ends each stroke with a REPORT event (the device's own account of it).
    reports_strokes: bool = False
    #: How long past a stroke's end (its arrival or its timeout) the device's account of it may
    #: still be on its way; the loop reads that long before it declares a stall (0: the driver's
    #: events are the truth as they come, as the simulated rig's are).
    report_wait_ns: int = 0

    def __init__(self, *, clock: Clock, debounce_ns: int = DEFAULT_DEBOUNCE_NS) -> None:
        self.clock = clock
        self.debounce_ns = check_ns("debounce_ns", debounce_ns)
        self._armed: tuple[Direction, int] | None = None
        self._pending: deque[Event] = deque()
        self._hold: _Hold | None = None
        self._ready: deque[Event] = deque()
        self._last_t_ns: int | None = None
        self._lock = threading.RLock()  # stop() may come from another thread
        # Set by halt() from any thread; a start is only ever switched on under _lock after
        # checking it, so once halt() returns no start can follow.
        self._halt = threading.Event()
        #: Why the driver is halted ("" when it is not).
        self.halt_reason = ""
        self.is_open = False
        #: Edges delivered after chatter (the chatter itself is dropped).
        self.bounces = 0
        #: Pulses shorter than debounce_ns that returned to the old level (dropped).
        self.glitches = 0
        #: Events whose stamp went backwards (dropped, reported as a SEQUENCE fault).
        self.out_of_order = 0
        #: Events stamped ahead of the driver's clock by more than a link can explain (dropped).
        self.future_stamps = 0
        #: Sensor edges per channel (A, B) that the debouncer absorbed: chatter and glitches.
        self.noise = [0, 0]

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

    def counters(self) -> dict[str, int]:
        """What the driver dropped or repaired so far, for status and stats (drivers add their own)."""
        return {
            "bounces": self.bounces,
            "glitches": self.glitches,
            "out_of_order": self.out_of_order,
            "future_stamps": self.future_stamps,
        }

    # -- timing ------------------------------------------------------------------------------
    def now_ns(self) -> int:
        """The driver's clock: the one every event stamp is on."""
        return self.clock.now_ns()

    def conditions(self) -> Conditions | None:
        """Drive conditions now (temperature, frequency), when this driver knows them."""
        return None

    def expected_stroke_ns(self, direction: Direction) -> int | None:
        """A stroke's operating time as this driver knows it before any is made (a model of the
        rig), else None: on a real rig the first stroke of each direction is a commissioning one."""
        return None

    def levels(self) -> tuple[int, int] | None:
        """Limit-sensor levels (A, B) now, when this driver knows them: where the mover rests."""
        return None

    def limits(self) -> dict[str, int]:
        """What the device can do, for the daemon to refuse the rest at the call (`max_delay_ns`,
        `min_stroke_timeout_ns`, `max_stroke_timeout_ns`; a key missing: no limit known)."""
        return {}

    def arm(self, direction: Direction, delay_ns: int) -> None:
        """Set the next stroke: its direction and the start delay after its command."""
        direction = Direction(direction)
        check_ns("delay_ns", delay_ns)
        with self._lock:
            self._armed = None  # a failed arm leaves nothing armed
            self._check_not_halted("arm")
            if self.hardware_timed:
                self._arm(direction, delay_ns)
            self._armed = (direction, delay_ns)

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
            # Halted first: an estop disarms, and its command then refused as unarmed latched
            # "command failed: command without an armed stroke" as the run's end, not the estop.
            self._check_not_halted("command")
            if self._armed is None:
                raise DaqError("command without an armed stroke: call arm(direction, delay_ns) first")
            if not self.is_open:
                raise DaqError(f"{self.name}: command on a closed driver")
            direction, delay_ns = self._armed
            self._armed = None
            if self.hardware_timed:
                # Under the lock: a halt() waits for the device to have the command, then stops it.
                t_cmd = self._command(t_cmd_ns)
                return Commanded(direction, t_cmd, delay_ns)
        t_cmd = self.clock.now_ns() if t_cmd_ns is None else check_ns("t_cmd_ns", t_cmd_ns)
        target = t_cmd + delay_ns
        # Sleep coarsely, then do the lock and the checks, then spin: after a sleep the code that
        # runs first meets cold caches (measured: ~5 us from the spin's end to the drive's stamp
        # when the lock and checks came after it). A halt() waits at most the spin margin for the
        # lock, and the spin watches for it, so no start follows an acknowledged halt.
        self.clock.approach(target, self._halt)
        halt = self._halt
        with self._lock:
            self._check_not_halted("start")
            drive = self._drive
            self.clock.sleep_until(target, halt)
            if halt.is_set():
                self._check_not_halted("start")
            t_start = drive(direction)
            self._pending.append(Event.start(t_start, direction))
        return Commanded(direction, t_cmd, delay_ns, t_start, t_start - target)

    def halt(self, reason: str) -> None:
        """Emergency stop or shutdown, from any thread: drive off, nothing armed, no start until release().

        When it returns, the drive is off (a hardware-timed device has been sent STOP, which disarms
        it) and no start can follow: a software-timed start waiting for its instant gives up.
        """
        self._halt.set()
        with self._lock:
            self.halt_reason = reason
            self._armed = None
            if self.is_open:
                self._stop()
                self._pending.append(Event.stop(self.clock.now_ns(), detail=reason))

    def release(self) -> None:
        """Allow starts again after a halt (a fault reset)."""
        with self._lock:
            self._halt.clear()
            self.halt_reason = ""

    @property
    def halted(self) -> bool:
        """True from halt() until release(): no stroke can start."""
        return self._halt.is_set()

    def _check_not_halted(self, what: str) -> None:
        if self._halt.is_set():
            raise DaqHalted(f"{self.name}: {what} refused: halted ({self.halt_reason or 'stop'})")

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

        Debouncing: an edge is held until its sensor has kept the new level for `debounce_ns`
        (measured from the last change). It is then delivered with the stamp of its FIRST
        transition, so chatter costs latency of delivery, never accuracy of the stamp. Chatter that
        settles on the new level counts in `bounces`; a pulse that returns to the old level is a
        glitch, dropped and counted in `glitches`. Events that arrive while an edge is held are
        delivered after it, in stamp order.
        """
        deadline = None if timeout_ns is None else self.clock.now_ns() + check_ns("timeout_ns", timeout_ns)
        while True:
            if self._ready:
                return self._ready.popleft()
            with self._lock:
                ev = self._pending.popleft() if self._pending else None
            hold = self._hold
            if ev is None:
                wait_to = deadline
                if hold is not None:
                    settled = hold.until_ns + self.delivery_latency_ns
                    wait_to = settled if deadline is None else min(deadline, settled)
                ev = self._recv_internal(wait_to)
                if ev is None:
                    if hold is not None and self.clock.now_ns() >= hold.until_ns + self.delivery_latency_ns:
                        self._settle()
                        continue
                    return None
            if ev.kind is EventKind.REPORT:
                # An account, not an instant: after what the stroke's edges held, never ordered.
                if hold is not None:
                    hold.behind.append(ev)
                    continue
                return ev
            if ev.t_ns > self.clock.now_ns() + self.delivery_latency_ns + self.stamp_ahead_ns():
                # From the future: a corrupt or confused stamp. Held, it would hold every event
                # behind it (the debouncer waits for its sensor to settle) and set the order check
                # against all that follow: it is dropped and counted, and outlives nothing.
                self.future_stamps += 1
                continue
            if self._last_t_ns is not None and ev.t_ns < self._last_t_ns:
                self.out_of_order += 1
                return Event.fault_event(
                    self._last_t_ns,
                    FaultCode.SEQUENCE,
                    f"{ev.kind.name} stamped {ev.t_ns} ns, before the previous event at {self._last_t_ns} ns",
                )
            self._last_t_ns = ev.t_ns
            if hold is not None:
                if ev.t_ns >= hold.until_ns:
                    self._settle()
                    if ev.kind is EventKind.EDGE:
                        with self._lock:  # it may start a hold of its own: back to the input's head
                            self._pending.appendleft(ev)
                    else:
                        self._ready.append(ev)
                    continue
                if ev.kind is EventKind.EDGE and ev.channel == hold.edge.channel:
                    hold.level = ev.level
                    hold.changes += 1
                    self.noise[ev.channel] += 1
                    hold.until_ns = ev.t_ns + self.debounce_ns
                else:
                    hold.behind.append(ev)
                continue
            if ev.kind is EventKind.EDGE and self.debounce_ns > 0:
                self._hold = _Hold(ev, ev.t_ns + self.debounce_ns)
                continue
            return ev

    def _settle(self) -> None:
        """The held edge's sensor has been stable for debounce_ns: deliver it or drop a glitch."""
        hold = self._hold
        assert hold is not None
        self._hold = None
        if hold.level == hold.edge.level:
            self._ready.append(hold.edge)
            if hold.changes:
                self.bounces += 1
        else:
            self.glitches += 1
            self.noise[hold.edge.channel] += 1
        self._ready.extend(hold.behind)

    def stamp_ahead_ns(self) -> int:
        """How far past the driver's clock (and the delivery latency) `recv` believes a stamp: a
        driver whose clock is an estimate of the device's widens it by that estimate's uncertainty."""
        return MAX_STAMP_AHEAD_NS

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
