"""The daemon's socket methods (docs/protocol.md): each turns a request into work for the loop.

Handlers run on the RPC bridge thread and stay short: what touches the driver or the predictors is
handed to the loop thread with `ControlLoop.call` and answered when the loop has done it, in its
slack. `stats` is served by the server process from a snapshot the loop publishes after every stroke.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

from usmswitch.drivers import DaqError, Direction

from .config import parse_host_port
from .loop import LoopError, Mode, State
from .record import CycleRecord
from .rpc import PROTOCOL_VERSION, ErrorCode, Limits, RpcError, RpcServer

if TYPE_CHECKING:
    from .service import Daemon

try:
    PACKAGE_VERSION = version("usmswitch")
except PackageNotFoundError:  # running from a source tree that was never installed
    PACKAGE_VERSION = "0+unknown"

ESTOP_REASON = "estop (socket)"
DIRECTIONS = {"on": (Direction.ON,), "off": (Direction.OFF,), "both": (Direction.ON, Direction.OFF)}


class Methods:
    """The handler table for RpcServer, bound to one running daemon."""

    def __init__(self, daemon: Daemon) -> None:
        assert daemon.loop is not None and daemon.store is not None and daemon.daq is not None
        self.daemon = daemon
        self.loop = daemon.loop
        self.store = daemon.store
        self.daq = daemon.daq
        self.server: RpcServer | None = None
        self._targets_from_cycle = self.loop.cycle
        self._last_state: tuple[Any, ...] = ()

    def table(self) -> dict[str, Callable[[list[Any]], object]]:
        """Method name -> handler(params), params already checked by the server."""
        return {
            "status": self.status,
            "get_target": self.get_target,
            "set_target": self.set_target,
            "history": self.history,
            "switch": self.switch,
            "start_cycling": self.start_cycling,
            "stop_cycling": self.stop_cycling,
            "set_mode": self.set_mode,
            "reset_fault": self.reset_fault,
            "estop": self.estop,
            "set_drive": self.set_drive,
        }

    # -- read-only ---------------------------------------------------------------------------
    def status(self, params: list[Any]) -> dict[str, Any]:
        loop = self.loop
        return {
            "state": str(loop.state),
            "mode": str(loop.mode),
            "fault": loop.fault_reason,
            "driver": self.daq.name,
            "driver_ok": self.daq.ping(),
            "protocol_version": PROTOCOL_VERSION,
            "version": PACKAGE_VERSION,
            "uptime_ns": time.monotonic_ns() - self.daemon.started_ns,
            "cycle": loop.cycle,
            "target_on_ns": loop.targets[Direction.ON],
            "target_off_ns": loop.targets[Direction.OFF],
        }

    def get_target(self, params: list[Any]) -> dict[str, int]:
        return self._targets()

    def _targets(self) -> dict[str, int]:
        t = self.loop.targets
        return {
            "target_on_ns": t[Direction.ON],
            "target_off_ns": t[Direction.OFF],
            "from_cycle": self._targets_from_cycle,
        }

    def history(self, params: list[Any]) -> list[dict[str, Any]]:
        (n,) = params
        # Strokes finished a moment ago may still be on their way to the file: wait for them.
        if not self.store.flush(2_000_000_000):
            raise RpcError(ErrorCode.TIMEOUT, "history: the record writer is behind; try again")
        return [rec.to_dict() for rec in self.store.history(n)]

    # -- on the loop thread -----------------------------------------------------------------------
    def _on_loop(self, fn: Callable[[], Any]) -> Future[Any]:
        """Run `fn` on the loop thread; loop refusals become protocol errors with their codes."""

        def guarded() -> Any:
            try:
                return fn()
            except LoopError as exc:
                code = ErrorCode.FAULT if self.loop.state is State.FAULT else ErrorCode.STATE
                raise RpcError(code, str(exc)) from None
            except ValueError as exc:
                raise RpcError(ErrorCode.INVALID_PARAMS, str(exc)) from None
            except DaqError as exc:
                raise RpcError(ErrorCode.UNAVAILABLE, f"driver: {exc}") from None

        return self.loop.call(guarded)

    def set_target(self, params: list[Any]) -> Future[Any]:
        target_ns, which = params

        def apply() -> dict[str, int]:
            for d in DIRECTIONS[which]:
                self.loop.set_target(target_ns, d)
            self._targets_from_cycle = self.loop.cycle
            self.store.record_event(
                "target", target_ns=target_ns, direction=which, from_cycle=self.loop.cycle
            )
            self.daemon.refresh_snapshot()
            return self._targets()

        return self._on_loop(apply)

    def set_mode(self, params: list[Any]) -> Future[Any]:
        mode, open_delay_ns = params

        def apply() -> dict[str, Any]:
            self.loop.set_mode(Mode(mode), open_delay_ns)
            self.store.record_event(
                "mode", mode=mode, open_delay_ns=self.loop.open_delay_ns, from_cycle=self.loop.cycle
            )
            self.daemon.refresh_snapshot()
            return {
                "mode": str(self.loop.mode),
                "open_delay_ns": self.loop.open_delay_ns,
                "from_cycle": self.loop.cycle,
            }

        return self._on_loop(apply)

    def switch(self, params: list[Any]) -> Future[Any]:
        (which,) = params

        def run() -> dict[str, Any]:
            d = self.loop.next_direction if which == "next" else DIRECTIONS[which][0]
            rec: CycleRecord = self.loop.switch(d)
            return rec.to_dict()

        return self._on_loop(run)

    def start_cycling(self, params: list[Any]) -> Future[Any]:
        period_ns, count = params

        def run() -> dict[str, int]:
            self.loop.start_cycling(period_ns, count)
            self.store.record_event("cycle", period_ns=period_ns, count=count, first_cycle=self.loop.cycle)
            return {"period_ns": period_ns, "count": count, "first_cycle": self.loop.cycle}

        return self._on_loop(run)

    def stop_cycling(self, params: list[Any]) -> Future[Any]:
        def run() -> dict[str, Any]:
            was = self.loop.state is State.CYCLING
            self.loop.stop_cycling()
            return {"was_cycling": was, "cycle": self.loop.cycle}

        return self._on_loop(run)

    def reset_fault(self, params: list[Any]) -> Future[Any]:
        def run() -> dict[str, Any]:
            if self.loop.state is not State.FAULT:
                raise LoopError("no fault is latched")
            was = self.loop.fault_reason
            self.loop.reset_fault()
            self.store.record_event("reset", fault=was)
            return {"fault": was}

        return self._on_loop(run)

    def estop(self, params: list[Any]) -> dict[str, Any]:
        # Not queued behind anything: the drive goes off from this thread, now.
        self.loop.estop(ESTOP_REASON)
        self.store.record_event("estop", source="socket")
        return {"state": str(State.FAULT), "fault": ESTOP_REASON}

    def set_drive(self, params: list[Any]) -> Future[Any]:
        (settings,) = params
        done: Future[Any] = Future()

        def finished(fut: Future[dict[str, Any]]) -> None:
            exc = fut.exception()
            if exc is not None:
                done.set_exception(RpcError(ErrorCode.UNAVAILABLE, f"set_drive: {exc}"))
                return
            applied = dict(fut.result())
            self.store.record_event("drive", **applied)
            applied.setdefault("enabled", True)
            cond = self.loop.conditions()
            applied.setdefault("temperature_c", None if cond is None else cond.temperature_c)
            done.set_result(applied)

        self.daemon.set_drive(settings).add_done_callback(finished)
        return done

    # -- from the loop, in its slack ---------------------------------------------------------------
    def on_record(self, rec: CycleRecord) -> None:
        """Notify subscribers of the stroke and refresh the stats snapshot."""
        server = self.server
        if server is None:
            return
        server.publish("stroke", rec.to_dict())
        self.daemon.refresh_snapshot()

    def on_slack(self) -> None:
        """Tell subscribers when state, mode, fault or a target changes."""
        loop = self.loop
        key = (loop.state, loop.mode, loop.fault_reason, loop.targets[0], loop.targets[1])
        if key != self._last_state and self.server is not None:
            self._last_state = key
            self.server.publish(
                "state",
                {
                    "state": str(loop.state),
                    "mode": str(loop.mode),
                    "fault": loop.fault_reason,
                    "target_on_ns": loop.targets[Direction.ON],
                    "target_off_ns": loop.targets[Direction.OFF],
                    "cycle": loop.cycle,
                },
            )
            self.daemon.refresh_snapshot()


def start_rpc(daemon: Daemon) -> RpcServer:
    """Bind the configured sockets, start the server process and hook it to the loop."""
    cfg = daemon.config.socket
    methods = Methods(daemon)
    cfg.path.parent.mkdir(parents=True, exist_ok=True)
    server = RpcServer(
        methods.table(),
        unix_path=cfg.path,
        mode=cfg.mode,
        group=cfg.group or None,
        tcp=parse_host_port(cfg.tcp) if cfg.tcp else None,
        tcp_token=cfg.tcp_token or None,
        topics=("stroke", "state"),
        snapshot_methods=("stats",),
        limits=Limits(max_connections=cfg.max_clients),
    )
    server.start()
    methods.server = server
    assert daemon.loop is not None
    daemon.loop.listeners.append(methods.on_record)
    daemon.loop.slack_hooks.append(methods.on_slack)
    return server
