"""The loop thread's queue of requests from other threads: run in its slack, never past a deadline."""

from __future__ import annotations

import queue
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from usmswitch.drivers import Clock


class RequestQueue:
    """Calls other threads hand to the loop thread; each gets a Future with its result or exception."""

    def __init__(self) -> None:
        self._items: queue.SimpleQueue[tuple[Callable[[], Any], Future[Any]]] = queue.SimpleQueue()

    def put(self, fn: Callable[[], Any]) -> Future[Any]:
        """Queue `fn` for the loop thread; the future carries its result or exception."""
        fut: Future[Any] = Future()
        self._items.put((fn, fut))
        return fut

    def wake(self) -> None:
        """Wake a loop thread blocked waiting for a request."""
        self._items.put((lambda: None, Future()))

    def serve(self, clock: Clock, block_ns: int = 0, until_ns: int | None = None) -> None:
        """Run queued requests, first waiting up to `block_ns` of wall time for one (idle).

        `until_ns` (on `clock`) is the slack window's end: no request is begun after it, so however
        many are queued, the next command is not held up; the rest wait for the next window.
        """
        try:
            if block_ns > 0:  # idle waits on wall time, whatever the clock: nothing to simulate
                item = self._items.get(timeout=block_ns / 1e9)
            else:
                item = self._items.get_nowait()
        except queue.Empty:
            return
        while True:
            fn, fut = item
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn())
                except BaseException as exc:  # the caller gets every failure, the loop carries on
                    fut.set_exception(exc)
            if until_ns is not None and clock.now_ns() >= until_ns:
                return
            try:
                item = self._items.get_nowait()
            except queue.Empty:
                return
