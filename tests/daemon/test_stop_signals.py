"""The stop signals are acted on by a thread of their own, never inside the code they interrupted."""

from __future__ import annotations

import os
import signal
import threading
import time

from usmswitch.daemon.stop_signals import STOP_THREAD, StopSignals


def test_a_sigterm_that_interrupts_a_lock_holder_stops_once_the_lock_is_let_go() -> None:
    """The main thread is the control loop's: a SIGTERM can land while it holds the serial driver's
    frame lock (not re-entrant) in the middle of a write. A halt run in the handler took that lock
    again and deadlocked the stop; the stop-signal thread waits for it like any other thread."""
    frame_lock = threading.Lock()
    stopped_on: list[str] = []
    done = threading.Event()

    def halt() -> None:
        if not frame_lock.acquire(timeout=2):  # the thread holding it is the one waiting here
            stopped_on.append("deadlocked")
            return
        stopped_on.append(threading.current_thread().name)
        frame_lock.release()
        done.set()

    before = signal.getsignal(signal.SIGTERM)
    signals = StopSignals(halt)
    signals.catch()
    try:
        with frame_lock:  # as the loop thread, mid-write
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the handler ran at the first bytecode after the kill, and returned
            assert signals.first_ns is not None and not stopped_on
        assert done.wait(10), "the stop never came"
        assert stopped_on == [STOP_THREAD]
        first = signals.first_ns
        os.kill(os.getpid(), signal.SIGINT)  # each signal stops again; the first one's time stays
        end = time.monotonic() + 10
        while len(stopped_on) < 2 and time.monotonic() < end:
            time.sleep(0.01)
        assert stopped_on == [STOP_THREAD] * 2 and signals.first_ns == first
    finally:
        signals.restore()
    assert signal.getsignal(signal.SIGTERM) == before
