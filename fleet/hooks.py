"""What reaches beyond this machine, hooked onto the daemon: the shipper's wake-ups, the metrics feed.

Both hang off the record writer's commits (`on_commit`/`on_run`, chained after the socket's
publishing, never replacing it) and the loop's slack, and neither makes the loop wait: the shipper
is a process of its own (the daemon starts it and hands its handle here: usmswitch.daemon.
shipper_process), the metrics are counted on the writer's thread and handed to the socket's server
process as snapshots (O(1) appends), where the page is rendered and served (usmswitch.web.metrics_page).
The daemon's parts are seen through the few attributes used here (the Protocols below): the fleet
never imports the loop. docs/fleet.md.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import structlog

from usmswitch.protocol.record import CycleRecord, RunRecord
from usmswitch.protocol.version import PACKAGE_VERSION

from .metrics import STATE_FEED, STROKES_FEED, StrokeMetrics


class Store(Protocol):
    """The record writer as the fleet sees it: its commit hooks and its health."""

    on_commit: Callable[[list[CycleRecord]], None] | None
    on_run: Callable[[RunRecord], None] | None

    @property
    def backlog(self) -> int: ...

    @property
    def writer_error(self) -> str | None: ...


class Loop(Protocol):
    """The control loop as the fleet sees it: its state, fault and targets, and its slack hooks."""

    @property
    def state(self) -> object: ...

    @property
    def fault_reason(self) -> str: ...

    @property
    def targets(self) -> Sequence[int]: ...

    @property
    def slack_hooks(self) -> list[Callable[[], None]]: ...


class Feeds(Protocol):
    """The socket's server, which keeps the latest snapshot of each feed for the page."""

    def snapshot(self, method: str, result: object) -> None: ...


class Shipper(Protocol):
    """The daemon's handle on the shipper process."""

    #: The most stop() takes beyond its drain.
    stop_overhead_ns: int

    def start(self) -> None: ...

    def wake(self, records: list[Any] | None = None) -> None: ...

    def stop(self, drain_timeout_ns: int = ...) -> bool: ...

    def status(self) -> dict[str, Any]: ...


#: The least a stopping shipper is given to ship what the records file committed last.
SHIP_DRAIN_MIN_NS = 5_000_000

log = structlog.get_logger("usmswitch.fleet")

#: The state snapshot (state, fault, backlog, shipper) is refreshed this often, and at once on a change.
STATE_EVERY_NS = 1_000_000_000


def fan_out(*hooks: Callable[[Any], None] | None) -> Callable[[Any], None]:
    """One hook that calls each of `hooks` in turn; one that raises is logged and the rest still run."""
    chain = [h for h in hooks if h is not None]

    def call_all(value: Any) -> None:
        for hook in chain:
            try:
                hook(value)
            except Exception:
                log.exception("record commit hook failed", hook=getattr(hook, "__qualname__", repr(hook)))

    return call_all


class Fleet:
    """The PostgreSQL shipper (when given one) and the metrics feed (with `feeds`: a metrics page)."""

    def __init__(
        self,
        store: Store,
        loop: Loop,
        *,
        rig: str,
        driver: str,
        feeds: Feeds | None = None,
        shipper: Shipper | None = None,
    ) -> None:
        self.store = store
        self.loop = loop
        self.feeds = feeds
        self.rig = rig
        self.driver = driver
        self.metrics = StrokeMetrics() if feeds is not None else None
        self.shipper = shipper
        self._next_state_ns = 0
        self._last_key: tuple[Any, ...] = ()

    def start(self) -> None:
        """Hook onto the store's commits and the loop's slack; start shipping."""
        store = self.store
        store.on_commit = fan_out(store.on_commit, self.on_commit)
        store.on_run = fan_out(store.on_run, self.on_run)
        self.loop.slack_hooks.append(self.slack)
        if self.feeds is not None:
            self.push_strokes()
            self.push_state()
        if self.shipper is not None:
            self.shipper.start()

    def stop(self, deadline_ns: int) -> None:
        """After the record store closed: ship what it committed, the shipper gone by `deadline_ns`
        (monotonic; at least SHIP_DRAIN_MIN_NS of shipping); what is left ships at the next start."""
        if self.shipper is not None:
            drain = deadline_ns - time.monotonic_ns() - self.shipper.stop_overhead_ns
            caught_up = self.shipper.stop(max(drain, SHIP_DRAIN_MIN_NS))
            status = self.shipper.status()
            if not caught_up:
                log.warning("postgres shipping stopped behind: the rest ships at the next start", **status)

    def status(self) -> dict[str, Any] | None:
        """The shipper's figures for the status reply (None when not shipping)."""
        return None if self.shipper is None else self.shipper.status()

    # -- the record writer's thread -----------------------------------------------------------------
    def on_commit(self, records: list[CycleRecord]) -> None:
        """Strokes committed: counted for the page, and the shipper woken."""
        if self.metrics is not None:
            self.metrics.add(records)
            self.push_strokes()
        if self.shipper is not None:
            self.shipper.wake(records)

    def on_run(self, run: RunRecord) -> None:
        """A run's row committed: the run's figures start afresh at its open; the shipper woken."""
        if self.metrics is not None:
            self.metrics.on_run(run)
            self.push_strokes()
        if self.shipper is not None:
            self.shipper.wake()

    def push_strokes(self) -> None:
        """The stroke counts to the server process (coalesced there to the latest)."""
        if self.feeds is not None and self.metrics is not None:
            self.feeds.snapshot(STROKES_FEED, self.metrics.snapshot())

    # -- the loop's slack ---------------------------------------------------------------------------
    def slack(self) -> None:
        """The state snapshot, once a second or when the state or fault changed (a few attribute reads)."""
        if self.feeds is None:
            return
        loop = self.loop
        now = time.monotonic_ns()
        key = (loop.state, loop.fault_reason)
        if now < self._next_state_ns and key == self._last_key:
            return
        self._next_state_ns = now + STATE_EVERY_NS
        self._last_key = key
        self.push_state()

    def push_state(self) -> None:
        """State, fault, targets, record writer and shipper figures to the server process."""
        if self.feeds is None:
            return
        loop, store = self.loop, self.store
        state: dict[str, Any] = {
            "rig": self.rig,
            "driver": self.driver,
            "version": PACKAGE_VERSION,
            "state": str(loop.state),
            "fault": loop.fault_reason or None,
            "targets_ns": list(loop.targets),
            "records": {"backlog": store.backlog, "writer_error": store.writer_error},
        }
        if self.shipper is not None:
            state["postgres"] = self.shipper.status()
        self.feeds.snapshot(STATE_FEED, state)
