"""The stop signals (SIGTERM, SIGINT, SIGHUP): noted on the main thread, acted on by a thread of their own.

A Python signal handler runs on the main thread between two of its bytecodes, and the main thread is
the control loop's: anywhere in it, also while it holds a lock. A halt run there takes locks the
code it interrupted may hold, none of them re-entrant: the driver's halt event (Event.set takes the
lock that Event.wait holds for a moment, and the loop waits on that event before every start) and
the serial driver's frame lock mid-write; the daemon then never exits (most likely CI's one daemon
with no exit 20 s after SIGTERM, at 66119b1). Signals sent by another process to a loop of such
waits: 375 of 44,464 landed with a lock held. So the handler only notes the time and hands the
signal over (SimpleQueue.put is safe in a handler); the `stop-signal` thread calls the stop, waiting
for the locks like any other thread (the estop's does the same).
"""

from __future__ import annotations

import queue
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

from usmswitch.runtime.realtime import name_thread

#: The signals that end the daemon: drive off, records flushed (SIGHUP: the terminal closed).
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)

#: The thread that acts on them; lifted with the estop's threads under SCHED_FIFO.
STOP_THREAD = "stop-signal"


class StopSignals:
    """Catches the stop signals and calls `on_stop` on a thread of its own, once per signal."""

    def __init__(self, on_stop: Callable[[], None]) -> None:
        #: When the first stop signal came (monotonic ns), None before any.
        self.first_ns: int | None = None
        self._on_stop = on_stop
        self._signals: queue.SimpleQueue[int | None] = queue.SimpleQueue()
        self._old: dict[int, Any] = {}
        self._thread: threading.Thread | None = None

    def catch(self) -> None:
        """From now on; only the main thread may set handlers (a no-op on any other)."""
        if threading.current_thread() is not threading.main_thread():
            return
        if self._thread is None:
            self._thread = threading.Thread(target=self._serve, name=STOP_THREAD, daemon=True)
            self._thread.start()
        for sig in STOP_SIGNALS:
            self._old.setdefault(sig, signal.signal(sig, self._note))

    def restore(self) -> None:
        """The handlers from before catch(); the thread ends."""
        for sig, handler in self._old.items():
            signal.signal(sig, handler)
        self._old.clear()
        if self._thread is not None:
            self._signals.put(None)
            self._thread = None

    def _note(self, signum: int, frame: object) -> None:
        if self.first_ns is None:
            self.first_ns = time.monotonic_ns()
        self._signals.put(signum)

    def _serve(self) -> None:
        name_thread(STOP_THREAD)  # as ps -L shows it: at the estop's priority under SCHED_FIFO
        while self._signals.get() is not None:
            self._on_stop()
