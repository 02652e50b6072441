"""The two clocks a driver can run on: the host's monotonic clock and a virtual clock.

A loop written against `Clock` runs unchanged in real time and in virtual time, where sleeping
jumps the clock forward so 100,000 strokes take seconds.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod

# Below this much time left, sleep() wakes too late on a stock kernel (~80 us at p50):
# spin on the clock for the rest.
DEFAULT_SPIN_MARGIN_NS = 300_000


class Clock(ABC):
    """Integer nanoseconds on one monotonic timeline."""

    virtual: bool = False

    @abstractmethod
    def now_ns(self) -> int:
        """The current instant."""

    @abstractmethod
    def sleep_until(self, t_ns: int, cancel: threading.Event | None = None) -> int:
        """Return at or after `t_ns` as precisely as the clock allows; returns the instant woken.

        When `cancel` is set (an emergency stop from another thread) it returns at once, early.
        """

    def approach(self, t_ns: int, cancel: threading.Event | None = None) -> int:
        """Sleep until shortly before `t_ns` (this clock's own margin), giving up when `cancel` is set.

        The caller then does what it must do ahead (take locks, check state), and `sleep_until(t_ns)`
        ends the wait precisely. A clock without a margin just sleeps until `t_ns`.
        """
        return self.sleep_until(t_ns, cancel)

    def wait_until(self, t_ns: int) -> int:
        """Return at or after `t_ns` without spinning: for waiting on events, not for starting motors."""
        return self.sleep_until(t_ns)


class MonotonicClock(Clock):
    """`time.monotonic_ns()`, with sleep-then-spin for starts that must be on time."""

    virtual = False

    def __init__(self, spin_margin_ns: int = DEFAULT_SPIN_MARGIN_NS) -> None:
        if spin_margin_ns < 0:
            raise ValueError(f"spin_margin_ns must be >= 0, got {spin_margin_ns!r}")
        self.spin_margin_ns = spin_margin_ns

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def approach(self, t_ns: int, cancel: threading.Event | None = None) -> int:
        ahead = t_ns - self.now_ns() - self.spin_margin_ns
        if ahead > 0:
            if cancel is None:
                time.sleep(ahead / 1e9)
            else:
                cancel.wait(ahead / 1e9)
        return self.now_ns()

    def sleep_until(self, t_ns: int, cancel: threading.Event | None = None) -> int:
        now = self.approach(t_ns, cancel)
        # The spin reads the clock in a bare loop: every call less is less overshoot.
        now_ns = time.monotonic_ns if type(self).now_ns is MonotonicClock.now_ns else self.now_ns
        if cancel is None:
            while now < t_ns:
                now = now_ns()
        else:
            is_set = cancel.is_set
            while now < t_ns and not is_set():
                now = now_ns()
        return now

    def wait_until(self, t_ns: int) -> int:
        now = self.now_ns()
        while now < t_ns:
            time.sleep((t_ns - now) / 1e9)
            now = self.now_ns()
        return now


class VirtualClock(Clock):
    """A clock that only moves when told: sleeping jumps to the wake instant at once."""

    virtual = True

    def __init__(self, start_ns: int = 0) -> None:
        self._t = int(start_ns)

    def now_ns(self) -> int:
        return self._t

    def sleep_until(self, t_ns: int, cancel: threading.Event | None = None) -> int:
        if cancel is not None and cancel.is_set():
            return self._t
        if t_ns > self._t:
            self._t = t_ns
        return self._t

    def advance(self, dt_ns: int) -> int:
        """Move the clock forward by `dt_ns` (>= 0)."""
        if dt_ns < 0:
            raise ValueError(f"a virtual clock never goes back: dt_ns={dt_ns}")
        self._t += dt_ns
        return self._t
