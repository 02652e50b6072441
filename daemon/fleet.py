"""What reaches beyond this machine: the records shipped to PostgreSQL, the metrics page's figures.

Both hang off the record writer's commits (`RecordStore.on_commit`/`on_run`, chained after the
socket's publishing, never replacing it) and the loop's slack, and neither makes the loop wait:
the shipper is a process of its own (daemon/shipper_process.py), the metrics are counted on the writer's
thread and handed to the socket's server process as snapshots (O(1) appends), where the page is
rendered and served (daemon/metrics_page.py). docs/fleet.md.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import structlog

from usmswitch.protocol.record import CycleRecord, RunRecord
from usmswitch.protocol.version import PACKAGE_VERSION

from .config import Config
from .loop import ControlLoop
from .metrics import STATE_FEED, STROKES_FEED, StrokeMetrics
from .records import RecordStore
from .rpc import RpcServer
from .shipper_process import STOP_OVERHEAD_NS, ShipperProcess

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
    """The PostgreSQL shipper (with records.postgres_url) and the metrics feed (with a metrics page)."""

    def __init__(
        self, config: Config, store: RecordStore, loop: ControlLoop, rpc: RpcServer | None, driver: str
    ) -> None:
        self.store = store
        self.loop = loop
        self.rpc = rpc if rpc is not None and rpc.metrics is not None else None
        self.rig = config.daemon.rig
        self.driver = driver
        self.metrics = StrokeMetrics() if self.rpc is not None else None
        self.shipper: ShipperProcess | None = None
        if config.records.postgres_url:
            self.shipper = ShipperProcess(
                store.path,
                config.records.postgres_url,
                self.rig,
                log_format=config.daemon.log_format,
                log_level=config.daemon.log_level,
                gate=loop.wait_turn,
            )
        self._next_state_ns = 0
        self._last_key: tuple[Any, ...] = ()

    def start(self) -> None:
        """Hook onto the store's commits and the loop's slack; start shipping."""
        store = self.store
        store.on_commit = fan_out(store.on_commit, self.on_commit)
        store.on_run = fan_out(store.on_run, self.on_run)
        self.loop.slack_hooks.append(self.slack)
        if self.rpc is not None:
            self.push_strokes()
            self.push_state()
        if self.shipper is not None:
            self.shipper.start()

    def stop(self, deadline_ns: int) -> None:
        """After the record store closed: ship what it committed, the shipper gone by `deadline_ns`
        (monotonic; at least SHIP_DRAIN_MIN_NS of shipping); what is left ships at the next start."""
        if self.shipper is not None:
            drain = deadline_ns - time.monotonic_ns() - STOP_OVERHEAD_NS
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
        if self.rpc is not None and self.metrics is not None:
            self.rpc.snapshot(STROKES_FEED, self.metrics.snapshot())

    # -- the loop's slack ---------------------------------------------------------------------------
    def slack(self) -> None:
        """The state snapshot, once a second or when the state or fault changed (a few attribute reads)."""
        if self.rpc is None:
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
        if self.rpc is None:
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
        self.rpc.snapshot(STATE_FEED, state)
