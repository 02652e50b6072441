"""usmswitchd put together: config -> logs -> records -> driver -> predictors -> loop -> socket.

The loop runs in the main thread (signals arrive there; the stop-signal thread acts on them:
stop_signals.py); the record writer and the socket bridge are threads off the timing path, the
socket server a process of its own.

Nothing is lost silently: one daemon per state directory (a lock held for its life), a records
file that cannot be written latches FAULT and stops cycling, and the exit status says when a
record was left unwritten (EXIT_RECORDS_LOST). Exit statuses: docs/service.md.
"""

from __future__ import annotations

import fcntl
import logging
import os
import stat
import statistics
import sys
import time
from collections.abc import Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any, TextIO

import structlog

from usmswitch.drivers import Daq, DaqError, Direction
from usmswitch.fleet.hooks import Fleet
from usmswitch.predictor import AR_MODELS, Predictor, make_predictors
from usmswitch.protocol.record import CycleRecord, Flag, RunRecord
from usmswitch.protocol.units import format_ns
from usmswitch.runtime.logsetup import configure_logging
from usmswitch.runtime.realtime import apply_realtime, lift_helpers, resolve_priority, scheduling_text
from usmswitch.server.rpc import URGENT_THREADS

from .board import BoardPoller
from .config import Config, ConfigError
from .daqfactory import make_daq
from .loop import (
    AUTOSTART_OWNER,
    MIN_STROKE_FRACTION,
    ControlLoop,
    State,
    direction_from_levels,
)
from .methods import start_rpc
from .reach import TargetUnreachableError, without_allow_late
from .records import RecordStore, RecordStoreError
from .retention import Retention, RetentionPolicy
from .rig_memory import RigMemory
from .sdnotify import Notifier
from .sensitivity_memory import Sensitivities, SensitivityMemory
from .shipper_process import ShipperProcess
from .sockdir import ensure_private_dir, prepare_socket_dir
from .stop_signals import STOP_THREAD, StopSignals

RECORDS_FILE = "records.sqlite"
LOCK_FILE = "usmswitchd.lock"
#: Exit status when the daemon stopped with records unwritten, dropped or rejected (cli.py's too).
EXIT_RECORDS_LOST = 4
# How long stop() waits for the record writer: a healthy one is done in milliseconds; a failing
# one gets a few retries (space may come back) before the loss is counted and reported.
CLOSE_TIMEOUT_NS = 10_000_000_000
CLOSE_TIMEOUT_FAILING_NS = 3_000_000_000
SWITCH_INTERVAL_S = 0.0002
#: The socket's server process's nice above the daemon's when the loop runs at SCHED_OTHER.
SERVER_NICE_UNDER_OTHER = 5
#: When the loop has SCHED_FIFO: the threads an estop passes through run one below it, the socket's
#: server process's event loop this far below (its HTTP doors' one further), and the daemon's
#: other helper threads (record writer, bridge) below those, so no helper's burst holds an estop
#: back in the daemon or in the server (docs/daemon.md, "Real time").
SERVER_FIFO_BELOW = 2
HELPERS_FIFO_BELOW = 4
#: From the stop signal to the end of stop(): what is left of it after the drive is off, the
#: server process gone and the records committed is what PostgreSQL shipping may still take;
#: the rest ships at the next start. Keeps SIGTERM-to-exit within 100 ms with a database (the
#: exit itself takes ~5 ms after stop()).
STOP_BUDGET_NS = 50_000_000
#: A stop signal to the exit (docs/daemon.md); a stop that took longer says so as a warning.
EXIT_BUDGET_NS = 100_000_000
# The live line in a terminal is redrawn at most this often.
LIVE_LINE_NS = 250_000_000


def direction_predictors(
    config: Config, learned: Sensitivities | None = None, nominals: Sequence[int] | None = None
) -> list[Predictor]:
    """The two directions' predictors as [control] configures them (each its own nominal; a model that
    learns the motor as a whole learns it from both). `learned`: the sensitivities a predictor of this
    configuration learned before (`sensitivities.json`), taken instead of the configured ones.
    `nominals`: each direction's first t_hat, when known better than the config's (`first_guesses`)."""
    c = config.control
    options: dict[str, Any] = {}
    sensitivities = c.sensitivities if learned is None else learned
    if c.model in AR_MODELS:
        options = {"order": c.order, "window": c.window, "max_order": c.max_order}
    elif sensitivities is not None:  # the config refuses them for a model that does not take them
        options = {"sensitivities": sensitivities}
    if nominals is None:
        nominals = [c.nominal_for(d) for d in (Direction.ON, Direction.OFF)]
    return make_predictors(c.model, nominals, **options)


def first_guesses(config: Config, daq: Daq) -> tuple[list[int], list[str]]:
    """Each direction's t_hat before its first stroke, and where it came from: the config when it
    gives a nominal, else the driver's model of the rig (the simulated rig knows its own), else the
    config's default as a guess ("guess": that direction's first stroke is a commissioning stroke).
    Records, when there are any, replace all of these at the warm start."""
    c = config.control
    nominals, sources = [], []
    for d in (Direction.ON, Direction.OFF):
        if c.nominal_given[d]:
            nominals.append(c.nominal_for(d))
            sources.append("config")
        elif (known := daq.expected_stroke_ns(d)) is not None:
            nominals.append(known)
            sources.append("rig model")
        else:
            nominals.append(c.nominal_for(d))
            sources.append("guess")
    return nominals, sources


class _Laps:
    """The steps of a stop and each one's time, from the stop signal (or the first step)."""

    def __init__(self, since_ns: int | None) -> None:
        self.start = self.last = since_ns if since_ns is not None else time.monotonic_ns()
        self.steps: list[str] = []

    def __call__(self, step: str) -> None:
        now = time.monotonic_ns()
        self.steps.append(f"{step} {(now - self.last) / 1e6:.1f} ms")
        self.last = now

    def total_ns(self) -> int:
        return time.monotonic_ns() - self.start

    def text(self) -> str:
        """`drive off 0.4 ms, socket closed 9.8 ms, ...; 12.0 ms in all`."""
        return f"{', '.join(self.steps)}; {self.total_ns() / 1e6:.1f} ms in all"


class StateDirBusyError(RuntimeError):
    """Another daemon holds the state directory's lock; the message names the directory and its pid."""


def prepare_state_dir(state_dir: Path, group: str | None) -> Path:
    """The state directory, created 0700 (0750 with a group) if missing; an existing one we own
    loses any permission for others (records are nobody else's business)."""
    ensure_private_dir(state_dir, group)
    st = os.stat(state_dir)
    if st.st_uid == os.geteuid() and stat.S_IMODE(st.st_mode) & 0o007:
        os.chmod(state_dir, stat.S_IMODE(st.st_mode) & ~0o007)
    return state_dir


def lock_state_dir(state_dir: Path) -> int:
    """Take the state directory's lock (flock, held while the fd is open); returns the fd.

    Raises StateDirBusyError naming the directory and the holder's pid when another daemon has it.
    The lock goes with the process: kill -9 releases it, no stale lock file to clean.
    """
    path = state_dir / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise StateDirBusyError(
            f"state directory {state_dir} is in use by another usmswitchd (pid {holder}, lock"
            f" {path}); stop it first, or give this one a state directory and a socket of its own:"
            " --state-dir DIR --socket PATH (make run STATE_DIR=DIR SOCKET=PATH WEB=PORT)"
        ) from None
    except BaseException:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def first_direction(daq: Daq, last: CycleRecord | None) -> Direction:
    """Where the next stroke goes: away from the sensor the mover rests on, else after the last record."""
    after_last = Direction(last.direction).opposite if last is not None and last.t_arrive_ns else Direction.ON
    return direction_from_levels(daq.levels(), after_last)


class Daemon:
    """The service: owns every part and their order of start and stop."""

    def __init__(self, config: Config, *, stream: TextIO | None = None) -> None:
        self.config = config
        self.stream = sys.stderr if stream is None else stream
        self.log_format = configure_logging(config.daemon.log_format, config.daemon.log_level, self.stream)
        self.log = structlog.get_logger("usmswitch.daemon").bind()
        self.notifier = Notifier()
        self.started_ns = time.monotonic_ns()
        self.store: RecordStore | None = None
        self.daq: Daq | None = None
        self.rig_memory: RigMemory | None = None
        self.sensitivity_memory: SensitivityMemory | None = None
        self.loop: ControlLoop | None = None
        self.rpc: Any = None
        self.board: BoardPoller | None = None
        self.fleet: Fleet | None = None
        # From the first instant of start(): a SIGTERM while starting ends the daemon as cleanly
        # as one while running (the socket answers before run() begins).
        self.stop_signals = StopSignals(self._on_stop_signal)
        #: True once every part runs (READY=1 sent): the socket answers a moment before.
        self.ready = False
        self._next_summary_ns = 0
        self._last_summary: tuple[Any, ...] | None = None  # what the last summary line said
        self._next_live_ns = 0
        self._live = self.log_format == "console" and self.stream.isatty()
        self._lock_fd: int | None = None
        self._records_fault: str | None = None

    # -- start-up --------------------------------------------------------------------------------
    def start(self) -> None:
        """Open everything in dependency order; raises with a clear message if a part cannot start."""
        cfg = self.config
        self.stop_signals.catch()
        group = cfg.socket.group or None
        state_dir = prepare_state_dir(Path(cfg.daemon.state_dir), group)
        self._lock_fd = lock_state_dir(state_dir)
        daq = make_daq(cfg)  # built, not opened: its name stamps the records
        self.store = RecordStore(
            state_dir / RECORDS_FILE,
            driver=daq.name,
            rig=cfg.daemon.rig,
            file_mode=0o640 if group else 0o600,
            # In virtual time the loop outruns SQLite: it waits for the writer instead of piling
            # records in memory (a 2x10^6 run had 871k waiting and the daemon at 764 MB).
            wait_when_behind=20_000 if cfg.driver.kind == "sim" and cfg.sim.clock == "virtual" else 0,
        )
        # What the predictors learned of the drive before, if it is this driver's, rig's and config's.
        self.sensitivity_memory = memory = SensitivityMemory(
            state_dir,
            driver=daq.name,
            rig=cfg.daemon.rig,
            model=cfg.control.model,
            configured=cfg.control.sensitivities,
        )
        nominals, sources = first_guesses(cfg, daq)
        predictors = direction_predictors(cfg, memory.load(), nominals)
        commissioning = []
        min_stroke: list[int] = []
        memory.watch(predictors[0])
        for d in (Direction.ON, Direction.OFF):
            # Only this driver's strokes on this rig: never a real rig from simulated strokes.
            samples = self.store.last_strokes(
                int(d), cfg.control.warm_start, driver=daq.name, rig=cfg.daemon.rig
            )
            predictors[d].extend(samples)
            first = "records" if samples else sources[d]
            # The plausible floor from what is known; from a guess none (the first stroke sets it).
            known = statistics.median(samples) if samples else nominals[d] if first != "guess" else 0
            min_stroke.append(cfg.control.min_stroke_ns or round(MIN_STROKE_FRACTION * known))
            if first == "guess":
                commissioning.append(d)
            self.log.info(
                "warm start",
                direction=d.name.lower(),
                strokes=len(samples),
                ready=predictors[d].ready,
                driver=daq.name,
                rig=cfg.daemon.rig,
                first_prediction=first,
                nominal_ns=nominals[d],
            )
        if commissioning:
            self.log.warning(
                "commissioning strokes",
                directions=[d.name.lower() for d in commissioning],
                why="no records, no configured nominal and no model of this rig: the first stroke of "
                "each is predicted from the default nominal, flagged COMMISSIONING and shown apart in stats",
            )
        daq.open()
        self.daq = daq
        self.rig_memory = RigMemory(state_dir, daq)  # the sim's friction and warmth, across restarts
        self.rig_memory.restore()
        conditions = None
        if cfg.modbus.enabled:
            store = self.store
            self.board = BoardPoller(
                cfg.modbus,
                on_event=lambda kind, fields: store.record_event(kind, **fields),
                on_fault=self._board_fault,
            )
            self.board.start()
            board = self.board
            conditions = lambda: board.latest  # noqa: E731  (an attribute read on the loop thread)
        last = self.store.history(1)
        last_rec = last[-1] if last else None
        self.loop = ControlLoop(
            self.daq,
            predictors,
            target_ns=[cfg.control.target_on_ns, cfg.control.target_off_ns],
            mode=cfg.control.mode,
            open_delay_ns=cfg.control.open_delay_ns,
            stroke_timeout_ns=cfg.control.stroke_timeout_ns,
            late_margin_ns=cfg.control.late_margin_ns,
            sink=self.store.submit,
            first_cycle=self.store.last_cycle() + 1,
            first_run_id=self.store.last_run_id() + 1,
            run_sink=self._on_run,
            next_direction=first_direction(self.daq, last_rec),
            conditions=conditions,
            commissioning=commissioning,
            min_stroke_ns=min_stroke,
        )
        if self.stop_signals.first_ns is not None:  # a stop signal came while starting
            self.loop.shutdown()
        known = [d for d in (Direction.ON, Direction.OFF) if d not in commissioning]
        if cfg.control.mode == "closed" and known:
            # The same refusal as set_target's: every stroke would start at once and arrive late.
            try:
                self.loop.check_reach(self.loop.targets)
            except TargetUnreachableError as exc:
                raise ConfigError("control.target", without_allow_late(str(exc))) from None
        self.store.gate = self.loop.wait_turn
        self.loop.slack_hooks.append(self._watch_records)
        self.loop.slack_hooks.append(self._housekeeping)
        self.loop.listeners.append(self._on_record)
        self._start_socket()
        # PostgreSQL shipping and the metrics feed, chained after the socket's commit hooks.
        shipper = None
        if cfg.records.postgres_url:
            shipper = ShipperProcess(
                self.store.path,
                cfg.records.postgres_url,
                cfg.daemon.rig,
                log_format=cfg.daemon.log_format,
                log_level=cfg.daemon.log_level,
                gate=self.loop.wait_turn,
            )
        policy = RetentionPolicy(cfg.records.keep_strokes, cfg.records.keep_days, cfg.records.keep_bytes)
        if policy.active:
            # Never a stroke the PostgreSQL copy lacks: the shipper's last cycle bounds what moves.
            shipped = (
                (lambda: shipper.status().get("shipped_cycle") or 0)
                if shipper is not None
                else (lambda: None)
            )
            self.store.retention = Retention(policy, self.store.path, shipped=shipped)
        rpc = self.rpc if self.rpc is not None and self.rpc.metrics is not None else None
        self.fleet = Fleet(
            self.store, self.loop, rig=cfg.daemon.rig, driver=self.daq.name, feeds=rpc, shipper=shipper
        )
        self.fleet.start()
        self.refresh_snapshot()
        self.store.record_event(
            "start",
            driver=self.daq.name,
            rig=cfg.daemon.rig,
            pid=os.getpid(),
            seed=getattr(self.daq, "seed", None),  # the sim's: any run replays from its records
            config=cfg.to_dict(redact=True),
        )
        self.log.info(
            "started",
            driver=self.daq.name,
            seed=getattr(self.daq, "seed", None),
            state_dir=str(state_dir),
            socket=str(cfg.socket.path),
            target_on_ns=cfg.control.target_on_ns,
            target_off_ns=cfg.control.target_off_ns,
            mode=cfg.control.mode,
            model=cfg.control.model,
            order=cfg.control.order,
            first_cycle=self.loop.cycle,
        )

    def _start_socket(self) -> None:
        """The msgpack-RPC front, wired in methods.py."""
        assert self.loop is not None and self.store is not None
        # A private directory, checked: whoever can write it could swap the socket (sockdir.py).
        prepare_socket_dir(self.config.socket.path, self.config.socket.group or None)
        self.rpc = start_rpc(self)
        self.rpc.gate = self.loop.wait_turn

    # -- running -----------------------------------------------------------------------------------
    def run(self) -> int:
        """Serve until SIGTERM, SIGINT or SIGHUP; returns the exit status: 0 on a clean stop,
        EXIT_RECORDS_LOST when any record was left unwritten, dropped or rejected."""
        assert self.loop is not None
        cfg = self.config
        rt = cfg.realtime
        priority, not_permitted = resolve_priority(rt.sched_fifo_priority)
        got = apply_realtime(priority, rt.cpu_affinity, rt.mlockall)
        self.loop.scheduling = scheduling_text(got, priority, not_permitted)
        if "sched_fifo_priority" not in got.applied and self.rpc is not None and self.rpc.server_pid:
            # A loop at SCHED_OTHER shares the CPU with the socket's server process by nice: the
            # server steps back. At SCHED_FIFO the loop preempts it whatever its nice, and at the
            # daemon's nice the server keeps up with bare asyncio at 8 clients (docs/protocol.md).
            self.rpc.lower_priority(SERVER_NICE_UNDER_OTHER)
        if "sched_fifo_priority" in got.applied and priority > 1:
            helpers = max(1, priority - HELPERS_FIFO_BELOW)
            lifted = lift_helpers(helpers, dict.fromkeys((*URGENT_THREADS, STOP_THREAD), priority - 1))
            if self.rpc is not None:
                self.rpc.urgent_priority = priority - 1
            self.log.info(
                "helper threads below the loop", priority=helpers, estop=priority - 1, threads=lifted
            )
            if priority > SERVER_FIFO_BELOW and self.rpc is not None:
                # The socket's server process reads, forwards and answers an estop the moment it
                # arrives, above the machine's ordinary work and below the daemon's own threads.
                self.rpc.raise_priority(priority - SERVER_FIFO_BELOW)
        elif not_permitted:
            self.log.warning(
                "loop at SCHED_OTHER",
                reason=not_permitted,
                cost="strokes start late when the machine is busy (measured on 2 cores: 2-4 % late "
                "idle, 19 % with /metrics scraped hard; 0.5 % at SCHED_FIFO); `stats` shows the late "
                "rate; run as the shipped unit (LimitRTPRIO) or grant CAP_SYS_NICE",
            )
        self.stop_signals.catch()
        # Other threads (record writer, socket bridge) give the GIL back within this bound when
        # the loop wants it; at the default 5 ms a busy thread would land in the start lateness.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        if cfg.autostart:
            # Queued, so the first tick is laid after run() has set up the collector.
            loop = self.loop

            def autostart() -> None:
                if loop.state is State.CYCLING:  # a client's run came first: it stays
                    self.log.info("start-up run not started: a client's run was first")
                    return
                loop.start_cycling(cfg.cycle.period_ns, cfg.cycle.count, settings={"owner": AUTOSTART_OWNER})

            loop.call(autostart)
            self.log.info(
                "cycling",
                period_ns=cfg.cycle.period_ns,
                count=cfg.cycle.count or "forever",
                note="a client's run takes this start-up run over",
            )
        self._next_summary_ns = time.monotonic_ns() + cfg.daemon.summary_interval_ns
        self.ready = True
        self.notifier.ready(status=self._status_line())
        status = 0
        try:
            self.loop.run()
        finally:
            status = self.stop()
        return status

    def _on_stop_signal(self) -> None:
        # Drive off at once (the stop-signal thread); the loop returns at its next check and stop()
        # flushes the records. During start() there may be no loop yet: start() shuts it down as
        # soon as it exists.
        if self.loop is not None:
            self.loop.shutdown()

    def _board_fault(self, why: str) -> None:
        """The drive board set a fault bit (poller thread): drive off now and FAULT, as an estop."""
        if self.loop is not None:
            self.loop.estop(f"drive board fault: {why}")

    def stop(self) -> int:
        """Drive off, socket closed, every record flushed, the driver released. Safe to call twice.

        Returns the exit status: EXIT_RECORDS_LOST if any record could not be written (still
        unwritten at close, dropped, or rejected by the database), else 0.
        """
        status = 0
        closed_store = None  # the store, once closed with its writer finished
        lap = _Laps(self.stop_signals.first_ns)
        self.notifier.stopping(status="stopping: drive off, flushing records")
        if self.daq is not None:
            try:
                self.daq.stop(detail="shutdown")
            except DaqError as exc:
                self.log.warning("drive stop at shutdown failed", error=str(exc))
        lap("drive off")
        if self.rpc is not None:
            self.rpc.stop()
            self.rpc = None
            lap("socket closed")
        if self.sensitivity_memory is not None:
            self.sensitivity_memory.save()  # only if they changed since the last save
        if self.daq is not None:
            if self.rig_memory is not None:
                self.rig_memory.save()
            self.daq.close()
        if self.board is not None:
            self.board.stop()
            self.board = None
        lap("driver released")
        if self.store is not None:
            store = self.store
            if self.loop is not None:
                store.record_event("stop", cycle=self.loop.cycle - 1)
            failing = store.writer_error is not None
            flushed = store.close(CLOSE_TIMEOUT_FAILING_NS if failing else CLOSE_TIMEOUT_NS)
            lap("records flushed")
            closed_store = store if flushed else None  # a writer still stuck is not waited for twice
            try:
                records: int | None = store.count()
            except RecordStoreError:
                records = None  # the file is gone: what it held cannot be counted
            lost = {"unwritten": store.backlog, "dropped": store.dropped, "rejected": store.rejected}
            if not flushed or any(lost.values()):
                status = EXIT_RECORDS_LOST
                self.log.error(
                    "records lost",
                    **lost,
                    submitted=store.submitted,
                    written=store.written,
                    flushed=flushed,  # False: events (or records) were still waiting at exit
                    writer_error=store.writer_error or store.last_error,
                    path=str(store.path),
                    exit_status=status,
                )
            self.log.info(
                "stopped",
                records=records,
                flushed=flushed,
                writer_error=store.last_error,
                **lost,
            )
            self.store = None
        if self.fleet is not None:
            # After the store closed: what it committed ships within what is left of the budget.
            asked = self.stop_signals.first_ns or time.monotonic_ns()
            self.fleet.stop(asked + STOP_BUDGET_NS)
            self.fleet = None
            lap("shipper and metrics stopped")
        if closed_store is not None:
            # Again, last, when nothing else reads the file (the shipper, the count above): its
            # readers closed and no -wal or -shm left beside it (daemon/wal.py).
            closed_store.close()
            lap("file settled")
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # the lock goes with it
            self._lock_fd = None
        self._summary(final=True)
        # Where a stop's time went; a warning past its budget (docs/daemon.md: within 100 ms).
        if lap.total_ns() > EXIT_BUDGET_NS:
            self.log.warning("exiting", took=lap.text(), budget="100 ms")
        else:
            self.log.info("exiting", took=lap.text())
        self.stop_signals.restore()
        return status

    def records_status(self) -> dict[str, Any]:
        """The record writer's counters for the status reply (any thread; plain values)."""
        store = self.store
        if store is None:
            return {"writer_error": None, "backlog": 0, "dropped": 0, "rejected": 0, "written": 0}
        return {
            "path": str(store.path),
            "driver": store.driver,
            "rig": store.rig,
            "writer_error": store.writer_error,
            "backlog": store.backlog,
            "dropped": store.dropped,
            "rejected": store.rejected,
            "written": store.written,
            "error_count": store.error_count,
            "postgres": None if self.fleet is None else self.fleet.status(),
        }

    def _on_run(self, run: RunRecord) -> None:
        """A run opened or ended (loop thread): the stats snapshot first, then the record, so a
        client told of the run's end by its notification already finds it ended in `stats`."""
        self.refresh_snapshot()
        assert self.store is not None
        self.store.submit_run(run)

    def refresh_snapshot(self) -> None:
        """Hand the server process the statistics as of now (answered without waking the loop)."""
        if self.rpc is not None and self.loop is not None:
            self.rpc.snapshot("stats", self.loop.snapshot(raw=True))

    def set_drive(self, settings: dict[str, Any]) -> Future[dict[str, Any]]:
        """Excitation frequency / voltage / enable: on the Modbus board, else on the sim's drive."""
        if self.board is not None:
            return self.board.set_drive(**settings)
        daq, loop = self.daq, self.loop
        setter = getattr(daq, "set_drive", None)
        if setter is None or loop is None or daq is None:
            fut: Future[dict[str, Any]] = Future()
            fut.set_exception(DaqError(f"{daq.name if daq else 'driver'}: no drive board to set"))
            return fut
        if "enabled" in settings:
            fut = Future()
            fut.set_exception(DaqError(f"{daq.name}: the drive enable is the driver's own (stop/estop)"))
            return fut

        def apply() -> dict[str, Any]:
            setter(**settings)
            loop.refresh_conditions()  # the armed stroke is re-planned for the new drive
            cond = daq.conditions()
            return {"frequency_hz": cond.frequency_hz, "voltage_vpp": cond.voltage_vpp}

        return loop.call(apply)

    # -- slack work (on the loop thread, never mid-stroke) --------------------------------------------
    def _on_record(self, rec: CycleRecord) -> None:
        if rec.flags & (Flag.STALL | Flag.FAULT | Flag.ESTOP):
            self.log.warning(
                "stroke fault", cycle=rec.cycle, flags=str(Flag(rec.flags)), fault=self.loop.fault_reason
            )
        elif self.log.is_enabled_for(logging.DEBUG):  # not a dict of every stroke to drop
            self.log.debug("stroke", **rec.to_dict())

    def _watch_records(self) -> None:
        """A records file that cannot be written is a fault: stop cycling before strokes pile up
        unrecorded (those already made wait in memory, retried, until the writer recovers)."""
        store, loop = self.store, self.loop
        if store is None or loop is None:
            return
        error = store.writer_error
        if error is None:
            if self._records_fault is not None:
                self.log.info("records writable again", after=self._records_fault, backlog=store.backlog)
                self._records_fault = None
            return
        if loop.state is State.FAULT:
            return  # latched already (this or another fault); after a reset it latches again
        reason = f"records: {error}"
        loop.latch_fault(reason)
        self._records_fault = error
        self.log.error(
            "records cannot be written: cycling stopped, FAULT latched",
            error=error,
            backlog=store.backlog,
            path=str(store.path),
        )
        store.record_event("fault", reason=reason)

    def _housekeeping(self) -> None:
        now = time.monotonic_ns()
        self.notifier.maybe_watchdog(now)
        if self.rig_memory is not None:
            self.rig_memory.maybe_save(now)
        if self.sensitivity_memory is not None:
            self.sensitivity_memory.maybe_save(now)
        if now >= self._next_summary_ns:
            self._next_summary_ns = now + self.config.daemon.summary_interval_ns
            self._summary(only_if_changed=True)
        if self._live and now >= self._next_live_ns:
            self._next_live_ns = now + LIVE_LINE_NS
            self.stream.write("\r\x1b[K" + self._status_line())
            self.stream.flush()

    def _status_line(self) -> str:
        loop = self.loop
        if loop is None:
            return "starting"
        both = loop.snapshot(raw=True)["all"]  # the summary's figures: one definition of each
        if not both["count"]:
            return f"{loop.state} | no strokes yet"
        return (
            f"{loop.state} | strokes {both['count']} | error mean {format_ns(round(both['error_mean_ns']))}"
            f" std {format_ns(round(both['error_std_ns']))} | late {both['late']} stall {both['stalls']}"
        )

    def _summary(self, final: bool = False, only_if_changed: bool = False) -> None:
        """The summary line: count, error mean and std (pooled over both directions, integer ns),
        late and stall counts. `only_if_changed`: an idle daemon does not repeat the same line."""
        loop = self.loop
        if loop is None:
            return
        snap = loop.snapshot(raw=True)["all"]  # no percentiles here: not worth a sort on the loop
        fields = {
            "state": str(loop.state),
            "count": snap["count"],
            "error_mean_ns": round(snap["error_mean_ns"]),
            "error_std_ns": round(snap["error_std_ns"]),
            "max_abs_error_pct": snap["max_abs_error_pct"],
            "late": snap["late"],
            "stalls": snap["stalls"],
            "fault": loop.fault_reason or None,
        }
        said = tuple(fields.values())
        if only_if_changed and said == self._last_summary:
            return
        self._last_summary = said
        if self._live:
            self.stream.write("\n" if final else "\r\x1b[K")
        self.log.info("summary" if not final else "final summary", **fields)
        if loop.state is State.FAULT:
            self.notifier.status(f"FAULT: {loop.fault_reason}")
        else:
            self.notifier.status(self._status_line())
