"""The daemon's socket methods (docs/protocol.md): each turns a request into work for the loop.

Handlers run on the RPC bridge thread and stay short: what touches the driver or the predictors is
handed to the loop thread with `ControlLoop.call` and answered when the loop has done it, in its
slack. `stats` is served by the server process from a snapshot the loop publishes after every stroke,
`history` by the server process from the records file, and `estop` by a thread of its own that no
other call can hold up (`RpcServer`'s urgent channel).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Protocol

import structlog

from usmswitch.drivers import Daq, DaqError, Direction
from usmswitch.fleet.metrics import FEEDS
from usmswitch.protocol.record import CycleRecord, RunRecord
from usmswitch.protocol.sockets import tcp_token_path, web_token_path
from usmswitch.protocol.version import PACKAGE_VERSION
from usmswitch.protocol.wire import PROTOCOL_VERSION, ErrorCode, Limits, RpcError, estop_socket_path
from usmswitch.server.after_reply import AfterReply
from usmswitch.server.estop_socket import EstopSocket
from usmswitch.server.rpc import RpcServer

from . import run_notes
from .config import Config
from .config_values import parse_host_port, parse_listen
from .loop import AUTOSTART_OWNER, ControlLoop, LoopError, Mode, State
from .reach import TargetUnreachableError
from .records import RecordStore, RecordStoreError
from .run_queue import PARAMS, Entry, RunQueue
from .web_token import TokenFile

log = structlog.get_logger("usmswitch.daemon")


class Daemon(Protocol):
    """What the socket methods use of the running daemon (`service.Daemon`), named here so that
    this module does not import the service that imports it."""

    config: Config
    loop: ControlLoop | None
    store: RecordStore | None
    daq: Daq | None
    started_ns: int

    def refresh_snapshot(self) -> None: ...

    def set_drive(self, settings: dict[str, Any]) -> Future[dict[str, Any]]: ...

    def records_status(self) -> dict[str, Any]: ...


#: The path an estop came by, when its caller did not say: the main socket's and TCP's come through
#: the server process's urgent channel alike. The estop socket's, the panel's and our clients' say.
ESTOP_UNNAMED = "main socket or TCP"
#: How often a loop cycling in virtual time (hundreds of strokes a second) rebuilds the stats snapshot.
SNAPSHOT_EVERY_VIRTUAL_NS = 20_000_000
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
        #: The queue of runs (daemon/run_queue.py): started by `start_rpc`, loaded from the file.
        self.queue = RunQueue(self.store.write, self._queue_start, self._publish_queue, self.loop.wait_turn)
        self._targets_from_cycle = self.loop.cycle
        self._last_state: tuple[Any, ...] = ()
        # set_target calls waiting for the loop: folded into one change (bridge and loop threads).
        self._target_lock = threading.Lock()
        self._target_batch: list[tuple[int, str, Future[Any]]] | None = None
        # The stats snapshot in virtual time: when it was last built, and whether a stroke since lacks it.
        self._snapshot_ns = 0
        self._snapshot_owed = False

    def table(self) -> dict[str, Callable[[list[Any]], object]]:
        """Method name -> handler(params), params already checked by the server."""
        return {
            "status": self.status,
            "get_target": self.get_target,
            "set_target": self.set_target,
            "switch": self.switch,
            "start_cycling": self.start_cycling,
            "stop_cycling": self.stop_cycling,
            "set_mode": self.set_mode,
            "reset_fault": self.reset_fault,
            "set_drive": self.set_drive,
            "annotate_run": self.annotate_run,
            "submit": self.submit,
            "queue_cancel": self.queue_cancel,
            "queue_priority": lambda params: self.queue.set_priority(*params),
            "queue_pause": lambda params: self.queue.set_paused(True, params[0]),
            "queue_resume": lambda params: self.queue.set_paused(False, params[0]),
        }

    def urgent(self) -> dict[str, Callable[[list[Any]], object]]:
        """Methods no other call may hold up: answered by a thread of their own."""
        return {"estop": self.estop}

    def urgent_estop_socket(self) -> dict[str, Callable[[list[Any]], object]]:
        """The estop socket's methods: its estop names that socket as its path, whatever it is told."""
        return {"estop": self.estop_on_estop_socket}

    # -- read-only ---------------------------------------------------------------------------
    def status(self, params: list[Any]) -> dict[str, Any]:
        loop = self.loop
        return {
            "state": str(loop.state),
            "mode": str(loop.mode),
            "fault": loop.fault_reason,
            "driver": self.daq.name,
            "driver_ok": self.daq.ping(),
            "driver_counters": self.daq.counters(),
            "records": self.daemon.records_status(),
            "protocol_version": PROTOCOL_VERSION,
            "version": PACKAGE_VERSION,
            "uptime_ns": time.monotonic_ns() - self.daemon.started_ns,
            "cycle": loop.cycle,
            "target_on_ns": loop.targets[Direction.ON],
            "target_off_ns": loop.targets[Direction.OFF],
            "open_delay_ns": loop.open_delay_ns,
            "metrics_url": self._metrics_url(),
            "web_url": self._web_url(),
            "rig": self.daemon.config.daemon.rig,
            "model": self.daemon.config.control.model,
            "order": self.daemon.config.control.order,
            "scheduling": loop.scheduling,
            "implausible_strokes": loop.implausible,
            "mismatched_strokes": loop.mismatched,
            "noise": loop.noise_by_sensor(),
            "idle_edges": loop.idle_edges,
            "ready": self.daemon.ready,
            "run": self._running_run(),
            "queue": self.queue.snapshot(),
        }

    def _running_run(self) -> dict[str, Any] | None:
        run = self.loop.latest_run
        return run.to_dict() if run is not None and run.running else None

    def _metrics_url(self) -> str | None:
        address = None if self.server is None else self.server.metrics_address
        if address is None:
            return None
        host, port = address
        return f"http://[{host}]:{port}/metrics" if ":" in host else f"http://{host}:{port}/metrics"

    def _web_url(self) -> str | None:
        address = None if self.server is None else self.server.web_address
        return None if address is None else web_url(address)

    def get_target(self, params: list[Any]) -> dict[str, int]:
        return self._targets()

    def _targets(self) -> dict[str, int]:
        t = self.loop.targets
        return {
            "target_on_ns": t[Direction.ON],
            "target_off_ns": t[Direction.OFF],
            "from_cycle": self._targets_from_cycle,
        }

    # -- on the loop thread -----------------------------------------------------------------------
    def _on_loop(self, fn: Callable[[], Any]) -> Future[Any]:
        """Run `fn` on the loop thread; loop refusals become protocol errors with their codes."""

        def guarded() -> Any:
            try:
                return fn()
            except LoopError as exc:
                code = ErrorCode.FAULT if self.loop.state is State.FAULT else ErrorCode.STATE
                raise RpcError(code, str(exc)) from None
            except TargetUnreachableError as exc:
                raise RpcError(ErrorCode.UNREACHABLE, str(exc)) from None
            except ValueError as exc:
                raise RpcError(ErrorCode.INVALID_PARAMS, str(exc)) from None
            except DaqError as exc:
                raise RpcError(ErrorCode.UNAVAILABLE, f"driver: {exc}") from None

        return self.loop.call(guarded)

    def set_target(self, params: list[Any]) -> Future[Any]:
        """Targets are folded: calls that pile up before the loop's slack are one change."""
        target_ns, which, allow_late = params
        done: Future[Any] = Future()
        with self._target_lock:
            batch = self._target_batch
            first = batch is None
            if batch is None:
                batch = self._target_batch = []
            batch.append((target_ns, which, allow_late, done))
        if first:
            applied = self._on_loop(lambda: self._apply_targets(batch))
            applied.add_done_callback(lambda fut: _resolve_all(batch, fut))
        return done

    def _apply_targets(self, batch: list[tuple[int, str, bool, Future[Any]]]) -> dict[str, Any]:
        with self._target_lock:
            self._target_batch = None  # later calls start a batch of their own
        targets = list(self.loop.targets)
        for target_ns, which, _, _ in batch:
            for d in DIRECTIONS[which]:
                targets[d] = target_ns
        # Folded calls are one change: it may be late only if every call said so.
        before = list(self.loop.targets)
        warnings = self.loop.set_targets(targets, allow_late=all(late for _, _, late, _ in batch))
        if targets != before:  # a call that changes nothing stores nothing (a flood of them, no rows)
            self._targets_from_cycle = self.loop.cycle
            self.store.record_event(
                "target",
                target_on_ns=targets[Direction.ON],
                target_off_ns=targets[Direction.OFF],
                calls=len(batch),
                from_cycle=self.loop.cycle,
            )
            self.daemon.refresh_snapshot()
        return {**self._targets(), "warnings": warnings}

    def set_mode(self, params: list[Any]) -> Future[Any]:
        mode, open_delay_ns = params

        def apply() -> dict[str, Any]:
            before = (self.loop.mode, self.loop.open_delay_ns)
            self.loop.set_mode(Mode(mode), open_delay_ns)
            if (self.loop.mode, self.loop.open_delay_ns) != before:  # a no-op stores nothing
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
        """One stroke; answered once its record is in the file (history then holds it)."""
        (which,) = params

        def run() -> dict[str, Any]:
            d = self.loop.next_direction if which == "next" else DIRECTIONS[which][0]
            return self.loop.switch(d).to_dict()  # its record queued for the file before it returns

        return self._once_committed(self._on_loop(run))

    def start_cycling(self, params: list[Any]) -> Future[Any]:
        """A new run: the target (when given) is set with it, and the run records both.

        A run going is never ended silently: the daemon's own start-up run (`[cycle] autostart`,
        what `make run` starts) gives way to a client's run with a log line; a run a client or an
        experiment started is taken over only when asked (`take_over`), else refused naming it.

        Answered once the run's row is committed (`_once_committed`).
        """
        return self._once_committed(self._on_loop(lambda: self.start_run(*params)))

    def _once_committed(self, fut: Future[Any]) -> Future[Any]:
        """`fut`'s reply once what the loop queued for the records file before it is committed (a
        stroke's record, a run's row, a fault's): a script's next `history`, `runs` or `stats` is
        read from the file by a reader process, and answered "no run 9" for a run whose start had
        been answered (CI, 62730fa)."""
        done: Future[Any] = Future()

        def settled(f: Future[Any]) -> None:
            exc = f.exception()
            if exc is not None:
                done.set_exception(exc)
                return
            reply = f.result()
            try:
                # After the loop queued its rows (their future is done): a no-op that commits with
                # them. Not while the file fails (what was queued is kept, not waited on).
                if self.store.writer_error is None:
                    self.store.write(lambda conn: None).add_done_callback(lambda _: done.set_result(reply))
                    return
            except RecordStoreError:  # closed: the daemon is stopping
                pass
            done.set_result(reply)

        fut.add_done_callback(settled)
        return done

    def start_run(
        self,
        period_ns: int,
        count: int,
        target_ns: int | None,
        allow_late: bool,
        take_over: bool,
        owner: str,
        label: str | None,
        notes: str | None,
        extra: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Open a run (loop thread): `start_cycling`'s work, and the queue's (`extra` settings: the
        queue entry it is). Returns the Cycling reply."""
        loop = self.loop
        targets = list(loop.targets) if target_ns is None else [target_ns, target_ns]
        if not allow_late:
            loop.check_reach(targets)
        loop.check_period(period_ns, targets)
        taken = self._give_way(take_over, owner) if loop.state is State.CYCLING else None
        old = list(loop.targets)
        warnings = loop.set_targets(targets) if target_ns is not None else []
        settings: dict[str, Any] = {"allow_late": allow_late, "owner": owner, **(extra or {})}
        if taken is not None:
            settings["took_over_run"] = taken.run_id
        try:
            run = loop.start_cycling(
                period_ns, count, settings=settings, label=label or None, notes=notes or None
            )
        except Exception:
            loop.set_targets(old)  # a refused run changes nothing
            raise
        if target_ns is not None and targets != old:
            self._targets_from_cycle = loop.cycle
            self.store.record_event(
                "target",
                target_on_ns=targets[0],
                target_off_ns=targets[1],
                calls=1,
                from_cycle=loop.cycle,
            )
        self.store.record_event("cycle", period_ns=period_ns, count=count, first_cycle=loop.cycle)
        self.daemon.refresh_snapshot()
        return {
            "run_id": run.run_id,
            "period_ns": period_ns,
            "count": count,
            "first_cycle": run.first_cycle,
            "target_on_ns": loop.targets[0],
            "target_off_ns": loop.targets[1],
            "warnings": warnings,
            "took_over": None if taken is None else taken.run_id,
        }

    # -- the queue of runs (daemon/run_queue.py) ---------------------------------------------------
    def submit(self, params: list[Any]) -> Future[Any]:
        """A run into the queue: checked now as `start_cycling` checks it (period, reach), kept in
        the records file, started when its turn comes; answered with its entry and place."""
        period_ns, count, target_ns, allow_late, label, notes, priority, take_over, owner = params

        def check() -> None:
            targets = list(self.loop.targets) if target_ns is None else [target_ns, target_ns]
            if not allow_late:
                self.loop.check_reach(targets)
            self.loop.check_period(period_ns, targets)

        run = dict(
            zip(PARAMS, (period_ns, count, target_ns, allow_late, take_over, label, notes), strict=True)
        )
        done: Future[Any] = Future()

        def checked(fut: Future[Any]) -> None:
            exc = fut.exception()
            if exc is not None:
                done.set_exception(exc)
                return
            self.queue.submit(run, owner, priority).add_done_callback(
                lambda kept: (
                    done.set_exception(kept.exception())  # type: ignore[arg-type]
                    if kept.exception() is not None
                    else done.set_result(kept.result())
                )
            )

        self._on_loop(check).add_done_callback(checked)
        return done

    def queue_cancel(self, params: list[Any]) -> Future[dict[str, Any]]:
        entry, owner, operator = params
        return self.queue.cancel(entry, owner, operator)

    def _queue_start(self, entry: Entry) -> Future[Any]:
        """The queue's head started in the loop's slack, unless it must wait: None while FAULT is
        latched or another's run goes (the daemon's start-up run gives way; `take_over` ends any)."""

        def run() -> dict[str, Any] | None:
            loop = self.loop
            p = entry.params
            if loop.state is State.FAULT:
                return None
            going = loop.latest_run if loop.state is State.CYCLING else None
            if going is not None and going.settings.get("owner") != AUTOSTART_OWNER and not p["take_over"]:
                return None
            extra = {"queue_entry": entry.entry, "priority": entry.priority}
            args = (p["period_ns"], p["count"], p["target_ns"], p["allow_late"], p["take_over"])
            return self.start_run(*args, entry.owner, p["label"], p["notes"], extra)

        return self._on_loop(run)

    def _publish_queue(self, payload: dict[str, Any]) -> None:
        if self.server is not None:
            self.server.publish("queue", payload)

    def _give_way(self, take_over: bool, owner: str) -> RunRecord:
        """End the run going so that a new one can start, or refuse (LoopError) naming it."""
        loop = self.loop
        going = loop.latest_run
        assert going is not None
        by = going.settings.get("owner") or "a client"
        if by != AUTOSTART_OWNER and not take_over:
            raise LoopError(
                f"already cycling: run {going.run_id} ({by}, {going.settings.get('count') or 'endless'}"
                f" strokes from cycle {going.first_cycle}) is going; stop it first (stop_cycling,"
                " `usmswitchctl stop`) or take it over deliberately (take_over=True,"
                " `usmswitchctl cycle --take-over`)"
            )
        log.info("run taken over", run=going.run_id, owner=by, by=owner or "a client", at_cycle=loop.cycle)
        loop.stop_cycling(f"taken over by {owner or 'a client'}")
        return going

    def annotate_run(self, params: list[Any]) -> Future[Any]:
        """A run's label and notes edited (daemon/run_notes.py); answered with the run once the
        edit is in the file, and told to subscribers as a `run` notification."""
        run_id, notes, label, owner, operator = params
        if notes is None and label is None:
            raise RpcError(ErrorCode.INVALID_PARAMS, "annotate_run: give notes, a label or both")
        latest = self.loop.latest_run
        run = latest if latest is not None and latest.run_id == run_id else self.store.run(run_id)
        if run is None:
            last = self.store.last_run_id()
            have = f"runs are 1..{last}" if last else "no run has been recorded yet"
            raise RpcError(ErrorCode.INVALID_PARAMS, f"annotate_run: no run {run_id} ({have})")
        refused = run_notes.may_edit(run, owner, operator)
        if refused is not None:
            raise RpcError(ErrorCode.STATE, f"annotate_run: {refused}")
        if run is latest:  # the loop's copy, which the run's end writes and tells, has them too
            if label is not None:
                latest.label = label or None
            if notes is not None:
                latest.notes = notes or None
        self.store.record_event("notes", run_id=run_id, label=label, notes=notes, by=owner)
        done: Future[Any] = Future()

        def written(fut: Future[Any]) -> None:
            exc = fut.exception()
            if exc is not None:
                done.set_exception(exc)
                return
            edited: RunRecord | None = fut.result()
            if edited is None:  # moved to the archive since (retention)
                done.set_exception(RpcError(ErrorCode.INVALID_PARAMS, f"annotate_run: no run {run_id}"))
                return
            (self.store.on_run or self.on_run)(edited)  # subscribers, and the shipper woken
            if run is not latest:
                done.set_result(edited.to_dict())
                return
            # The loop's run: `stats` answers from its snapshot, rebuilt (in the loop's slack) before
            # the reply, so a `stats` after it shows the edit.
            self.loop.call(self.daemon.refresh_snapshot).add_done_callback(
                lambda _: done.set_result(edited.to_dict())
            )

        self.store.write(run_notes.edit(run_id, label, notes)).add_done_callback(written)
        return done

    def stop_cycling(self, params: list[Any]) -> Future[Any]:
        def run() -> dict[str, Any]:
            was = self.loop.state is State.CYCLING
            self.loop.stop_cycling()
            self.daemon.refresh_snapshot()  # a stats call after this reply sees the run ended
            run = self.loop.latest_run
            return {
                "was_cycling": was,
                "cycle": self.loop.cycle,
                "run": None if run is None else run.to_dict(),
            }

        return self._once_committed(self._on_loop(run))

    def reset_fault(self, params: list[Any]) -> Future[Any]:
        def run() -> dict[str, Any]:
            if self.loop.state is not State.FAULT:
                raise LoopError("no fault is latched")
            was = self.loop.fault_reason
            self.loop.reset_fault()
            self.store.record_event("reset", fault=was)
            return {"fault": was}

        done = self._once_committed(self._on_loop(run))  # the fault's records in the file with it
        # A person reset the fault: the queue's next run may start (a fault never starts it).
        done.add_done_callback(lambda fut: fut.exception() is None and self.queue.next())
        return done

    def estop(self, params: list[Any]) -> AfterReply:
        """An estop by the urgent channel: its source as its caller names it (`panel`,
        `usmswitchctl, TCP`), else ESTOP_UNNAMED."""
        return self._estop(params[0] if params and params[0] else ESTOP_UNNAMED)

    def estop_on_estop_socket(self, params: list[Any]) -> AfterReply:
        """An estop by the estop socket: who its caller says it is, and that socket."""
        who = params[0] if params and params[0] else ""
        return self._estop(f"{who}, estop socket" if who else "estop socket")

    def _estop(self, source: str) -> AfterReply:
        # Not queued behind anything: on the urgent thread, the drive goes off and the driver is
        # halted before this returns, so the reply means "drive off, nothing scheduled". The
        # latch and the event row wake the loop and the writer: after the reply (after_reply.py).
        reason = f"estop ({source})"
        self.loop.stop_now(reason)

        def then() -> None:
            self.loop.latch_stop(reason)
            self.store.record_event("estop", source=source)

        return AfterReply({"state": str(State.FAULT), "fault": reason}, then)

    def set_drive(self, params: list[Any]) -> Future[Any]:
        (settings,) = params
        # docs/protocol.md: a command fails with FAULT while FAULT is latched; reading (`{}`) is
        # answered in any state.
        if settings and self.loop.state is State.FAULT:
            raise RpcError(
                ErrorCode.FAULT, f"set_drive: FAULT is latched ({self.loop.fault_reason}): reset_fault first"
            )
        done: Future[Any] = Future()

        def finished(fut: Future[dict[str, Any]]) -> None:
            exc = fut.exception()
            if exc is not None:
                # An out-of-range value is the caller's; anything else is the board's.
                code = ErrorCode.INVALID_PARAMS if isinstance(exc, ValueError) else ErrorCode.UNAVAILABLE
                done.set_exception(RpcError(code, f"set_drive: {exc}"))
                return
            applied = dict(fut.result())
            self.store.record_event("drive", **applied)
            applied.setdefault("enabled", self.loop.state is not State.FAULT)  # FAULT: the drive is off
            cond = self.loop.conditions()
            applied.setdefault("temperature_c", None if cond is None else cond.temperature_c)
            done.set_result(applied)

        self.daemon.set_drive(settings).add_done_callback(finished)
        return done

    # -- from the record writer, once records are committed --------------------------------------
    def on_run(self, run: RunRecord) -> None:
        """Tell subscribers a run opened or ended, once its row is in the file: the end comes
        after every stroke of the run has been published."""
        if self.server is not None:
            self.server.publish("run", run.to_dict())
        self.queue.on_run(run)

    def on_commit(self, records: list[CycleRecord]) -> None:
        """Notify subscribers of strokes now in the file, never before: a subscriber's log and the
        records agree even if the daemon is killed the next instant."""
        server = self.server
        if server is not None:
            for rec in records:
                server.publish("stroke", rec.to_dict())

    # -- from the loop, in its slack ---------------------------------------------------------------
    def on_record(self, rec: CycleRecord) -> None:
        """Refresh the stats snapshot (the stroke itself is published once committed). A loop cycling
        in virtual time refreshes it at most every SNAPSHOT_EVERY_VIRTUAL_NS of the wall clock: built
        at every stroke it took a quarter of the loop's time (six 4096-stroke windows copied); the
        skipped refresh is made up in the slack once cycling stops, and a run's end refreshes it."""
        if self.server is None:
            return
        if self.loop.clock.virtual and self.loop.state is State.CYCLING:
            now = time.monotonic_ns()
            if now - self._snapshot_ns < SNAPSHOT_EVERY_VIRTUAL_NS:
                self._snapshot_owed = True
                return
            self._snapshot_ns = now
        self._snapshot_owed = False
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
            self._snapshot_owed = False
            self.daemon.refresh_snapshot()
        elif self._snapshot_owed and (
            loop.state is not State.CYCLING
            or time.monotonic_ns() - self._snapshot_ns >= SNAPSHOT_EVERY_VIRTUAL_NS
        ):
            self._snapshot_owed = False
            self._snapshot_ns = time.monotonic_ns()
            self.daemon.refresh_snapshot()


def _resolve_all(batch: list[tuple[int, str, bool, Future[Any]]], fut: Future[Any]) -> None:
    """Every call folded into one change gets that change's outcome."""
    exc = fut.exception()
    for _, _, _, done in batch:
        if exc is not None:
            done.set_exception(exc)
        else:
            done.set_result(fut.result())


def web_url(address: tuple[str, int], token: str | None = None) -> str:
    """The panel's URL for people: a wildcard address shown as this host's loopback."""
    host, port = address
    host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
    url = f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"
    return url if token is None else f"{url}?token={token}"


def _announce_panel(url: str, token: TokenFile) -> None:
    """Say where the panel is: the URL with its token on a terminal (`make run`, as Jupyter does),
    else without it (a journal is read by more people than the socket's group)."""
    log.info("panel", url=url, token_file=str(token.path))
    if sys.stderr.isatty():
        print(f"usmswitchd: the panel: {url}?token={token.token}", file=sys.stderr, flush=True)


def start_rpc(daemon: Daemon) -> RpcServer:
    """Bind the configured sockets, start the server process and hook it to the loop."""
    cfg = daemon.config.socket
    methods = Methods(daemon)
    cfg.path.parent.mkdir(parents=True, exist_ok=True)
    # The panel's token, beside the socket and for the socket's group (daemon/web_token.py).
    token = TokenFile(web_token_path(cfg.path), cfg.group or None) if daemon.config.web.listen else None
    # TCP without a configured token: one made here, in a file beside the socket for its group.
    tcp_token = (
        TokenFile(tcp_token_path(cfg.path), cfg.group or None) if cfg.tcp and not cfg.tcp_token else None
    )
    server = RpcServer(
        methods.table(),
        unix_path=cfg.path,
        mode=cfg.mode,
        group=cfg.group or None,
        tcp=parse_host_port(cfg.tcp) if cfg.tcp else None,
        tcp_token=cfg.tcp_token or (None if tcp_token is None else tcp_token.token),
        urgent=methods.urgent(),
        urgent_path=estop_socket_path(cfg.path),
        records_path=daemon.store.path,
        records_reader="usmswitch.daemon.records:open_reader",
        topics=("stroke", "state", "run", "queue"),
        snapshot_methods=("stats",),
        snapshot_finishers={"stats": "usmswitch.protocol.stats:finish_snapshot"},
        feeds=FEEDS if daemon.config.metrics.listen else (),
        metrics=parse_listen(daemon.config.metrics.listen) if daemon.config.metrics.listen else None,
        web=parse_listen(daemon.config.web.listen) if token is not None else None,
        web_token=None if token is None else token.token,
        web_token_file=None if token is None else token.path,
        web_allowed_hosts=daemon.config.web.allowed_hosts,
        limits=Limits(max_connections=cfg.max_clients, max_tcp_connections=cfg.max_tcp_clients),
        log_format=daemon.config.daemon.log_format,
        log_level=daemon.config.daemon.log_level,
        nice=0,  # raised by the service if the loop is refused SCHED_FIFO
        busy_poll_ns=cfg.busy_poll_ns,
    )
    # Before the socket listens: `stats` answers (count 0) from the first connection on.
    server.snapshot("stats", daemon.loop.snapshot(raw=True))
    try:
        server.start()
    except BaseException:
        for made in (token, tcp_token):
            if made is not None:
                made.stop()
        raise
    if tcp_token is not None:
        server.companions.append(tcp_token)
        log.info("tcp token made", token_file=str(tcp_token.path))
    if token is not None:
        server.companions.append(token)
        assert server.web_address is not None
        _announce_panel(web_url(server.web_address), token)
    methods.server = server
    methods.queue.start()
    methods.queue.load()  # what waited before a restart: paused until an operator resumes it
    server.companions.append(methods.queue)
    assert server.urgent_listener is not None
    estop = EstopSocket(
        server.urgent_listener, methods.urgent_estop_socket(), server.limits, gate=daemon.loop.wait_turn
    )
    estop.start()
    server.companions.append(estop)
    assert daemon.loop is not None
    daemon.loop.listeners.append(methods.on_record)
    daemon.store.on_commit = methods.on_commit
    daemon.store.on_run = methods.on_run
    daemon.loop.slack_hooks.append(methods.on_slack)
    return server
