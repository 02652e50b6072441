"""Polling the server's event loop without sleeping for a moment after each request, while a core is spare.

A process asleep in epoll is woken by the kernel when a request arrives: on a round trip of a
lab script's `call`, the server's wake-up is a third of the time (docs/protocol.md, "Busy
polling"). A script that calls again within `window_ns` of its last request finds the server
awake and polling, as Linux's own `net.core.busy_poll` does for network cards.

Polling takes a core. It is done only while fewer clients are active than there are cores
beside the server's: with more, the clients need every core to build their next request, and a
polling server would slow them (8 clients on 2 cores: 0.89-0.93x the throughput, p99 2.2 ms). The loop of the
rig runs at SCHED_FIFO and preempts the polling at once; after the window the server sleeps as
before, so an idle daemon costs nothing.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable

# A connection with a request in this long counts as an active client.
ACTIVE_NS = 2_000_000
# Long enough for a Python script to use a reply and send its next request (the bench's client
# takes 40-80 us between calls); at 50 us the window mostly closed before it came.
DEFAULT_WINDOW_NS = 200_000


def usable_cpus() -> int:
    """The cores this process may run on (its affinity, not the machine's count)."""
    return len(os.sched_getaffinity(0))


class BusyPoll:
    """Keeps `loop` polling (a callback that reschedules itself: the loop then waits with a zero
    timeout) until `window_ns` after the last request, while at most `cpus - 1` clients are active."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        window_ns: int,
        cpus: int,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if isinstance(window_ns, bool) or not isinstance(window_ns, int) or window_ns <= 0:
            raise ValueError(f"window_ns must be a positive integer, got {window_ns!r}")
        self.loop = loop
        self.window_ns = window_ns
        self.spare = cpus - 1  # the server's own core is not spare
        self.clock = clock
        self.active: dict[object, int] = {}  # client -> its last request's time
        self.pruned_ns = -ACTIVE_NS  # when the silent clients were last dropped from `active`
        self.until_ns = 0
        self.polling = False
        #: Windows opened, and requests that found too many clients active to open one.
        self.windows = 0
        self.declined = 0

    def request(self, client: object, now_ns: int) -> None:
        """A request from `client` at `now_ns`: poll until a window after it, if a core is spare."""
        active = self.active
        active[client] = now_ns
        if len(active) > self.spare:
            # Pruned at most four times an ACTIVE_NS: with many clients calling, not at each request.
            if now_ns - self.pruned_ns >= ACTIVE_NS // 4:
                self.pruned_ns = now_ns
                cutoff = now_ns - ACTIVE_NS
                for old in [c for c, t in active.items() if t < cutoff]:
                    del active[old]
            if len(active) > self.spare:
                self.until_ns = 0  # the clients need the cores: the poll under way stops at once
                self.declined += 1
                return
        self.until_ns = now_ns + self.window_ns
        if not self.polling:
            self.polling = True
            self.windows += 1
            self.loop.call_soon(self._poll)

    def forget(self, client: object) -> None:
        """`client` closed: it is no longer active."""
        self.active.pop(client, None)

    def _poll(self) -> None:
        if self.clock() < self.until_ns:
            self.loop.call_soon(self._poll)
        else:
            self.polling = False
