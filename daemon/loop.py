"""The control loop of the paper's Fig. 10: predict, delay, start, stamp, record.

One thread owns the driver and the predictors. Everything else (socket, signals, summary) talks to
it through `call()` (a queue drained in the loop's slack) or `estop()` (immediate). The timing path
runs from an arrival stamp to the next stroke being armed, and from a command to its start: on it
there is no logging, no disk I/O, no socket work and no garbage collection.
"""

from __future__ import annotations

import contextlib
import gc
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from enum import StrEnum
from typing import Any

import structlog

from usmswitch.drivers import Conditions, Daq, DaqError, DaqHalted, Direction, EventKind, FaultCode, check_ns
from usmswitch.protocol.record import CycleRecord, Flag, RunRecord
from usmswitch.protocol.stats import DirectionStats
from usmswitch.protocol.units import format_ns

from .plan import Mode, Plan, direction_from_levels, drive_of, flags_for_failure, predictor_conditions
from .stroke_events import StrokeEvents, await_report, disagreement, read_stroke

log = structlog.get_logger("usmswitch.loop")

# Events are polled in slices so an emergency stop or shutdown is seen within this bound.
RECV_SLICE_NS = 2_000_000
# In real time the loop stops waiting on its command queue this long before a command instant and
# leaves the rest to the driver's sleep-then-spin.
COMMAND_LEAD_NS = 2_000_000
# A helper thread waits at most this long for its turn: with a long start delay (open loop, a
# long target) it proceeds rather than stall the socket for the whole delay.
HELPER_WAIT_MAX_S = 0.01


class State(StrEnum):
    IDLE = "idle"
    CYCLING = "cycling"
    FAULT = "fault"  # latched by a stall, a disconnect or an emergency stop until reset_fault
    STOPPED = "stopped"  # shut down


#: The owner of the run the daemon starts by itself (`[cycle] autostart`): a client's run takes it over.
AUTOSTART_OWNER = "autostart"


#: The plausible band's floor as a fraction of a direction's known stroke (`[control] min_stroke`).
#: A USM cannot cross 5 mm three times faster than it usually does; a sensor or a stamp can lie.
MIN_STROKE_FRACTION = 0.3
#: Idle: how long the loop waits for a request before it reads the driver's events again.
IDLE_POLL_NS = 50_000_000
#: At most this many events read per idle pass (a flood waits for the next pass, requests first).
IDLE_READ_MAX = 10_000
IDLE_EDGES_LOG_EVERY_NS = 10_000_000_000


class LoopError(Exception):
    """A request the loop refuses in its present state; the message says why."""


class TargetUnreachableError(ValueError):
    """A closed-loop target below the shortest stroke the rig makes; the message names the shortest."""


class ControlLoop:
    """Runs strokes on a `Daq` with one predictor per direction and hands each record to a sink."""

    def __init__(
        self,
        daq: Daq,
        predictors: Sequence[Any],
        *,
        target_ns: int | Sequence[int],
        mode: Mode | str = Mode.CLOSED,
        open_delay_ns: int = 0,
        stroke_timeout_ns: int = 50_000_000,
        late_margin_ns: int = 50_000,
        sink: Callable[[CycleRecord], None] | None = None,
        first_cycle: int = 1,
        next_direction: Direction = Direction.ON,
        conditions_every: int = 1,
        conditions: Callable[[], Conditions | None] | None = None,
        first_run_id: int = 1,
        run_sink: Callable[[RunRecord], None] | None = None,
        commissioning: Sequence[Direction] = (),
        min_stroke_ns: Sequence[int] = (0, 0),
    ) -> None:
        if len(predictors) != 2:
            raise ValueError(f"one predictor per direction (on, off) is needed, got {len(predictors)}")
        self.daq = daq
        self.clock = daq.clock
        self.predictors = list(predictors)
        targets = [target_ns, target_ns] if isinstance(target_ns, int) else list(target_ns)
        self.targets = [check_ns("target_ns", t, minimum=1) for t in targets]
        self.mode = Mode(mode)
        self.open_delay_ns = check_ns("open_delay_ns", open_delay_ns)
        self.stroke_timeout_ns = check_ns("stroke_timeout_ns", stroke_timeout_ns, minimum=1)
        self.late_margin_ns = check_ns("late_margin_ns", late_margin_ns)
        self.sink = sink
        #: How the loop thread is scheduled, in words (the daemon sets it once it has asked).
        self.scheduling = "not yet set (starting)"
        #: Directions whose next completed stroke commissions them (nothing known before it).
        self.commissioning = set(commissioning)
        self.cycle = first_cycle
        self.state = State.IDLE
        self.fault_reason = ""
        self.stats = [DirectionStats(), DirectionStats()]  # since the loop started
        self.stats_all = DirectionStats()  # both directions together
        # Runs: each start_cycling opens one; its strokes carry its id and have statistics of
        # their own, which `snapshot` reports (the current run, else the last one).
        self.latest_run: RunRecord | None = None  # the open run, else the last one
        self.run_sink = run_sink
        self.run_stats = [DirectionStats(), DirectionStats()]
        self.run_stats_all = DirectionStats()
        self._next_run_id = first_run_id
        self._first_cycle = first_cycle
        self._run_ending: str | None = None  # why the open run ends, once its last stroke is recorded
        self._in_stroke = False
        self.spurious_edges = 0
        #: Per direction, the shortest operating time believed (the plausible band's floor).
        self.min_stroke_ns = [check_ns("min_stroke_ns", m) for m in min_stroke_ns]
        #: Strokes the hardware side reported that were not physically strokes (flag IMPLAUSIBLE).
        self.implausible = 0
        #: Strokes whose stamps the device's own account did not bear out (flag MISMATCH).
        self.mismatched = 0
        #: Edges per sensor (A, B) that no stroke explains, seen by the loop during strokes (the
        #: driver's debouncer counts the chatter it absorbed: `Daq.noise`).
        self.noise = [0, 0]
        self.overruns = 0
        self.stale_events = 0  # driver events read and dropped outside a stroke (idle, a fault reset)
        #: Sensor edges reported while no stroke was going (the mover moved by hand, a sensor chatters).
        self.idle_edges = 0
        self._idle_edges_said_ns = -IDLE_EDGES_LOG_EVERY_NS
        self.listeners: list[Callable[[CycleRecord], None]] = []
        self.slack_hooks: list[Callable[[], None]] = []
        self._conditions_every = max(1, conditions_every)
        # Where temperature and frequency come from: the driver (sim) or a drive board's poller.
        self._conditions_source = conditions or daq.conditions
        self._set_conditions(self._conditions_source())
        self._plan_drive = drive_of(self._conditions)  # the drive setting the armed plan was made for
        self._last_command: list[int | None] = [None, None]  # per direction: the predictors' idle_ns
        self._next_dir = Direction(next_direction)
        self._plan: Plan | None = None
        self._requests: queue.SimpleQueue[tuple[Callable[[], Any], Future[Any]]] = queue.SimpleQueue()
        self._estop = threading.Event()
        # Cleared from the end of a slack window until the stroke has started: the daemon's other
        # threads wait on it (`wait_turn`) so that none holds the GIL when the start is due.
        self._helpers_may_run = threading.Event()
        self._helpers_may_run.set()
        self._shutdown = threading.Event()
        self._cycling_left: int | None = None  # strokes still to run; -1 forever; None not cycling
        self._period_ns = 0
        self._next_tick_ns = 0

    # -- requests from other threads ------------------------------------------------------------
    def call(self, fn: Callable[[], Any]) -> Future[Any]:
        """Run `fn` on the loop thread in its slack; the future carries its result or exception."""
        fut: Future[Any] = Future()
        self._requests.put((fn, fut))
        return fut

    def estop(self, reason: str = "emergency stop") -> None:
        """Drive off now, from any thread, and final: when it returns no start can follow.

        The driver is halted (drive off, nothing armed, a waiting start abandoned) until
        `reset_fault`; the loop latches FAULT and stops cycling at its next step.
        """
        self._estop.set()
        self._halt(reason)
        # Shown at once (a status right after the estop's reply says FAULT); the loop thread
        # latches it fully (cycling stopped, the run ended) at its next step.
        self.fault_reason = reason
        self.state = State.FAULT
        self.call(lambda: self._latch_fault(reason))

    def shutdown(self) -> None:
        """Ask `run()` to return, drive off and no start after this call (signal handlers call this)."""
        self._shutdown.set()
        self._halt("shutdown")
        self._requests.put((lambda: None, Future()))  # wake a blocked queue wait

    def wait_turn(self, max_s: float = HELPER_WAIT_MAX_S) -> None:
        """For helper threads: return when the loop is not about to start a stroke (or after `max_s`)."""
        self._helpers_may_run.wait(max_s)

    def latch_fault(self, reason: str) -> None:
        """Drive off, stop cycling, FAULT until reset (loop thread: a slack hook's finding)."""
        self._safe_stop(reason)
        self._latch_fault(reason)

    # -- operations (loop thread) -----------------------------------------------------------------
    def set_target(self, target_ns: int, direction: Direction | None = None) -> list[str]:
        """New target T for one direction or both, from the next armed stroke; returns warnings.

        While cycling, a target the period cannot hold is refused (commands would overlap); a
        target shorter than the predicted stroke is taken but warned about: those strokes are late.
        """
        check_ns("target_ns", target_ns, minimum=1)
        dirs = (Direction.ON, Direction.OFF) if direction is None else (Direction(direction),)
        targets = list(self.targets)
        for d in dirs:
            targets[d] = target_ns
        return self.set_targets(targets)

    def set_targets(self, targets: Sequence[int], allow_late: bool = True) -> list[str]:
        """Both targets (on, off) in one change: one check, one re-arm; returns warnings.

        With `allow_late=False` a target the rig cannot reach (closed loop) is refused instead.
        """
        targets = [check_ns("target_ns", t, minimum=1) for t in targets]
        if len(targets) != 2:
            raise ValueError(f"set_targets takes (on, off), got {len(targets)} values")
        if not allow_late:
            self.check_reach(targets)
        self._check_device(targets, self.mode, self.open_delay_ns)
        if self.state is State.CYCLING:
            self._check_period(self._period_ns, targets, self.mode, self.open_delay_ns)
        self.targets = targets
        self._rearm()
        return self.reach_warnings() if self.mode is Mode.CLOSED else []

    def set_mode(self, mode: Mode | str, open_delay_ns: int | None = None) -> None:
        """Closed loop (Eq. 7) or open loop with a fixed delay; applies from the next armed stroke."""
        mode = Mode(mode)
        delay = self.open_delay_ns if open_delay_ns is None else check_ns("open_delay_ns", open_delay_ns)
        self._check_device(self.targets, mode, delay)
        if self.state is State.CYCLING:
            self._check_period(self._period_ns, self.targets, mode, delay)
        self.mode = mode
        self.open_delay_ns = delay
        self._rearm()

    def shortest_target_ns(self, direction: Direction) -> int:
        """The shortest target `direction` reaches now: its predicted stroke plus the late margin."""
        return math.ceil(self.predictors[direction].predict()) + self.late_margin_ns

    def check_reach(self, targets: Sequence[int], mode: Mode | None = None) -> None:
        """Refuse (ValueError) a closed-loop target below what the rig reaches: every stroke would
        start at once and arrive late. The message names the shortest reachable target."""
        if (mode or self.mode) is not Mode.CLOSED:
            return
        for d in (Direction.ON, Direction.OFF):
            shortest = self.shortest_target_ns(d)
            if targets[d] < shortest:
                # Rounded up to 10 us: a target people can type that is surely reachable.
                typed = -(-shortest // 10_000) * 10_000
                hint = (
                    " (a bare number is nanoseconds: write the unit, e.g. '12ms')"
                    if targets[d] < 1_000_000
                    else ""
                )
                name = "on" if d is Direction.ON else "off"
                raise TargetUnreachableError(
                    f"target {format_ns(targets[d])}{hint} is below the shortest the rig reaches "
                    f"in direction {name}: {format_ns(typed)} (predicted stroke "
                    f"{format_ns(shortest - self.late_margin_ns)} + late margin "
                    f"{format_ns(self.late_margin_ns)}); every stroke would be late. Set a target "
                    f">= {format_ns(typed)}, or allow late strokes (allow_late)"
                )

    def reach_warnings(self) -> list[str]:
        """Per direction, a warning when T is shorter than the predicted stroke (it will be late)."""
        out = []
        for d in (Direction.ON, Direction.OFF):
            t_hat = round(self.predictors[d].predict())
            if self.targets[d] < t_hat:
                out.append(
                    f"target_{d.name.lower()}_ns {self.targets[d]} is shorter than the predicted stroke "
                    f"({t_hat} ns): those strokes start at once and arrive late"
                )
        return out

    def reset_fault(self) -> None:
        """Clear a latched FAULT; the drive stays off until the next command."""
        if self.state is State.FAULT and not self.daq.ping():
            raise LoopError(f"{self.daq.name} is not connected: reset when the device is back")
        if self._shutdown.is_set():
            raise LoopError("shutting down")
        self._estop.clear()
        self.daq.release()
        if self.state is State.FAULT:
            self._drain_stale_events()
            self.state = State.IDLE
            self.fault_reason = ""
            # After a fault the mover may be anywhere: ask the sensors where it rests.
            self._next_dir = direction_from_levels(self.daq.levels(), self._next_dir)
            self._plan = None

    def check_period(self, period_ns: int, targets: Sequence[int] | None = None) -> None:
        """Refuse (ValueError) a period that `targets` (default: the current ones) do not fit in."""
        chosen = self.targets if targets is None else targets
        self._check_period(period_ns, chosen, self.mode, self.open_delay_ns)

    def start_cycling(
        self,
        period_ns: int,
        count: int = 0,
        *,
        kind: str = "cycling",
        settings: dict[str, Any] | None = None,
    ) -> RunRecord:
        """Command a stroke every `period_ns`, alternately on and off, `count` strokes (0: until
        stopped), as a new run; returns the run (its id, its first cycle, its settings).

        `kind` and `settings` describe the run for its record (an experiment names itself and
        adds its own settings to the loop's).
        """
        check_ns("period_ns", period_ns, minimum=1)
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ValueError(f"count must be an integer >= 0, got {count!r}")
        self._require_no_fault()
        if self.state is State.CYCLING:
            raise LoopError("already cycling: stop_cycling first (or wait for the run to end)")
        self._check_device(self.targets, self.mode, self.open_delay_ns)
        self._check_period(period_ns, self.targets, self.mode, self.open_delay_ns)
        self._period_ns = period_ns
        self._cycling_left = count if count else -1
        # The first command as far ahead as every later one: a hardware-timed device is told
        # command_lead_ns before the instant (it was laid 2 ms ahead, inside the MCU's 4 ms lead).
        self._next_tick_ns = self.clock.now_ns() + self.daq.command_lead_ns + COMMAND_LEAD_NS
        self.state = State.CYCLING
        return self._open_run(kind, {"period_ns": period_ns, "count": count, **(settings or {})})

    def stop_cycling(self, reason: str = "stopped") -> None:
        """Command no more strokes (the loop thread calls it between strokes); ends the run."""
        self._cycling_left = None
        if self.state is State.CYCLING:
            self.state = State.IDLE
        self._end_run(reason)

    def run_settings(self) -> dict[str, Any]:
        """What a run records of the loop's settings at its open."""
        p = self.predictors
        return {
            "target_on_ns": self.targets[Direction.ON],
            "target_off_ns": self.targets[Direction.OFF],
            "mode": str(self.mode),
            "open_delay_ns": self.open_delay_ns,
            "model": getattr(p[0], "model", type(p[0]).__name__),
            "order": [p[0].order, p[1].order],
            "window": getattr(p[0], "window", None),
            "driver": self.daq.name,
        }

    def _open_run(self, kind: str, settings: dict[str, Any]) -> RunRecord:
        self._end_run("superseded")  # never two open runs (defensive: start_cycling refuses)
        run = RunRecord(
            run_id=self._next_run_id,
            kind=kind,
            first_cycle=self.cycle,
            started_wall_ns=time.time_ns(),
            settings={**self.run_settings(), **settings},
        )
        self._next_run_id += 1
        self.latest_run = run
        self._run_ending = None
        self.run_stats = [DirectionStats(), DirectionStats()]
        self.run_stats_all = DirectionStats()
        if self.run_sink is not None:
            self.run_sink(run)
        return run

    def _end_run(self, reason: str) -> None:
        """End the open run (if any) with `reason`; during a stroke, once that stroke is recorded."""
        run = self.latest_run
        if run is None or not run.running:
            return
        if self._in_stroke:
            self._run_ending = self._run_ending or reason
            return
        run.last_cycle = self.cycle - 1
        run.ended_wall_ns = time.time_ns()
        run.end_reason = reason
        self._run_ending = None
        if self.run_sink is not None:
            self.run_sink(run)

    def switch(self, direction: Direction) -> CycleRecord:
        """One stroke in `direction`, commanded now; returns its record."""
        if self.state is State.CYCLING:
            raise LoopError("busy: cycling; stop_cycling first")
        self._require_no_fault()
        direction = Direction(direction)
        if direction_from_levels(self.daq.levels(), direction) is not direction:
            # Driving toward the sensor the mover rests at pushes it into the end stop until the
            # stroke timeout: refuse instead.
            raise LoopError(
                f"the mover already rests at sensor {direction.dest.name} (switch is "
                f"{'on' if direction is Direction.ON else 'off'}): nothing to do"
            )
        self._next_dir = direction
        return self._stroke(None)

    def run_cycles(
        self, period_ns: int, count: int, *, kind: str = "cycling", settings: dict[str, Any] | None = None
    ) -> RunRecord:
        """Cycle `count` strokes as one run in the calling thread (tests, benchmarks, experiments);
        stops early on a fault. Returns the run, ended."""
        run = self.start_cycling(period_ns, count, kind=kind, settings=settings)
        while self._cycling_left is not None and self.state is State.CYCLING:
            self._cycle_once()
        return run

    def run(self) -> None:
        """The service's main loop: serve requests, cycle when asked, until `shutdown()`."""
        self._enter_realtime_gc()
        try:
            while not self._shutdown.is_set():
                if self.state is State.CYCLING:
                    try:
                        self._cycle_once()
                    except Exception as exc:  # a bug must not leave the drive on or the socket dark
                        self._safe_stop("internal error")
                        self._latch_fault(f"internal error: {type(exc).__name__}: {exc}")
                        log.exception("stroke failed; drive off, FAULT latched")
                else:
                    self._serve_requests(block_ns=IDLE_POLL_NS)
                    self._read_idle_events()
                    self._slack()
        finally:
            self._safe_stop("shutdown")
            self._cycling_left = None
            self.state = State.STOPPED
            self._end_run("shutdown")
            gc.enable()

    def conditions(self) -> Conditions | None:
        """Drive conditions now, from the same source the records use (any thread)."""
        return self._conditions_source()

    def _set_conditions(self, cond: Conditions | None) -> None:
        self._conditions = cond
        self._pcond = predictor_conditions(cond)  # what the predictors are told

    def refresh_conditions(self) -> None:
        """Read the conditions now (loop thread, slack); a changed drive setting re-plans the armed
        stroke, so its delay is for the drive it will run at, not the one of the previous arrival."""
        try:
            self._set_conditions(self._conditions_source())
        except DaqError:
            return
        if self._plan is not None and drive_of(self._conditions) != self._plan_drive:
            self._rearm()

    @property
    def next_direction(self) -> Direction:
        """The direction of the next stroke (away from where the mover rests)."""
        return self._next_dir

    # -- statistics ---------------------------------------------------------------------------------
    def snapshot(self, raw: bool = False) -> dict[str, Any]:
        """Statistics per direction and combined, plus the models, as plain types.

        `raw=True` (the daemon's path, on the loop thread) leaves the percentiles to
        `stats.finish_snapshot`, which the socket's server process runs.
        """
        out: dict[str, Any] = {
            "state": str(self.state),
            "mode": str(self.mode),
            "fault": self.fault_reason,
            "cycle": self.cycle,
            "target_on_ns": self.targets[Direction.ON],
            "target_off_ns": self.targets[Direction.OFF],
            "spurious_edges": self.spurious_edges,
            "implausible": self.implausible,
            "mismatched": self.mismatched,
            "noise": self.noise_by_sensor(),
            "overruns": self.overruns,
            "driver_bounces": self.daq.bounces,
            "driver": self.daq.counters(),
            "scheduling": self.scheduling,
        }
        run = self.latest_run
        if run is None:  # no run yet: every stroke since the start
            per, both, first = self.stats, self.stats_all, self._first_cycle
        else:
            per, both, first = self.run_stats, self.run_stats_all, run.first_cycle
        last = run.last_cycle if run is not None and not run.running else self.cycle - 1
        out["run"] = None if run is None else run.to_dict()
        out["first_cycle"] = first
        out["last_cycle"] = last if last >= first else None
        out["all"] = both.snapshot(raw)
        for d, name in ((Direction.ON, "on"), (Direction.OFF, "off")):
            s = per[d].snapshot(raw)
            p = self.predictors[d]
            s["order"] = p.order
            s["coefficients"] = list(p.coefficients)
            s["ready"] = p.ready
            out[name] = s
        return out

    def noise_by_sensor(self) -> dict[str, int]:
        """Edges per sensor that no stroke explains: chatter the debouncer absorbed, spurious edges
        during strokes and edges while idle are apart (`idle_edges`)."""
        return {ch: self.noise[i] + self.daq.noise[i] for i, ch in enumerate(("A", "B"))}

    # -- internals ----------------------------------------------------------------------------------
    def _check_with_device(self, got: StrokeEvents, direction: Direction) -> str:
        """Hold an arrived stroke's stamps against the device's own account ("" when they agree):
        a stroke it disagrees with is counted and logged, and never learned from."""
        daq = self.daq
        if not daq.reports_strokes:
            return ""
        await_report(daq, got, slice_ns=RECV_SLICE_NS, halted=self._estop.is_set)
        doubt = disagreement(got)
        if doubt:
            self.mismatched += 1
            log.warning("stroke not learned: the device's account disagrees", cycle=self.cycle, why=doubt)
        return doubt

    def _require_no_fault(self) -> None:
        if self.state is State.FAULT:
            raise LoopError(f"FAULT latched ({self.fault_reason}): reset_fault first")

    def _safe_stop(self, detail: str) -> None:
        """Drive off; a device that is already gone cannot be driving, so its refusal is not an error."""
        with contextlib.suppress(DaqError):
            self.daq.stop(detail=detail)

    def _halt(self, reason: str) -> None:
        """Drive off and no start until released; a device already gone cannot be driving."""
        try:
            self.daq.halt(reason)
        except DaqError:
            log.warning("halt: the device did not take the stop", reason=reason)

    def _check_period(self, period_ns: int, targets: Sequence[int], mode: Mode, open_delay_ns: int) -> None:
        """Refuse a period that a stroke from its command (T, or t_hat when late) would not fit in."""
        t_hat = max(round(p.predict()) for p in self.predictors)
        longest = max(*targets, t_hat) if mode is Mode.CLOSED else open_delay_ns + t_hat
        if period_ns <= longest:
            what = "max of T and t_hat" if mode is Mode.CLOSED else "open delay + t_hat"
            raise ValueError(
                f"period {period_ns} ns is not longer than a stroke from its command"
                f" ({longest} ns, {what}): commands would overlap"
            )

    def _check_device(self, targets: Sequence[int], mode: Mode, open_delay_ns: int) -> None:
        """Refuse (ValueError) a start delay longer than the device can time (HELLO_ACK
        max_delay_us), naming its limit: the strokes would otherwise each fault at their ARM."""
        longest = self.daq.limits().get("max_delay_ns")
        if longest is None:
            return
        if mode is Mode.OPEN:
            if open_delay_ns > longest:
                raise ValueError(
                    f"open-loop delay {format_ns(open_delay_ns)} is longer than the device's longest"
                    f" start delay, {format_ns(longest)}"
                )
            return
        for d in (Direction.ON, Direction.OFF):
            t_hat = max(0, math.floor(self.predictors[d].predict()))
            if targets[d] - t_hat > longest:
                raise TargetUnreachableError(
                    f"target {format_ns(targets[d])} needs a start delay of {format_ns(targets[d] - t_hat)}"
                    f" (T - t_hat), longer than the device's longest, {format_ns(longest)}: the"
                    f" longest target it reaches is {format_ns(longest + t_hat)}"
                )

    def _latch_fault(self, reason: str) -> None:
        self.state = State.FAULT
        self.fault_reason = reason
        self._cycling_left = None
        self._plan = None
        self._end_run(f"fault: {reason}")

    def _expected_command_ns(self) -> int:
        """When the stroke being planned will be commanded: the next tick when cycling, else now."""
        if self.state is State.CYCLING and self._in_stroke:
            return self._next_tick_ns + self._period_ns  # armed ahead, during the stroke before it
        if self.state is State.CYCLING:
            return self._next_tick_ns
        return self.clock.now_ns()

    def _told(self, direction: Direction, t_ns: int) -> dict[str, Any] | None:
        """The conditions for a stroke of `direction` commanded at `t_ns`: idle_ns since its last command."""
        last = self._last_command[direction]
        if last is None or t_ns < last:
            return self._pcond
        return {**(self._pcond or {}), "idle_ns": t_ns - last}

    def _plan_for(self, direction: Direction) -> Plan:
        """Eq. 6-7: t_hat from this direction's predictor, T_d = T - t_hat clamped at 0 (late)."""
        p = self.predictors[direction]
        target = self.targets[direction]
        t_hat = round(p.predict(self._told(direction, self._expected_command_ns())))
        self._plan_drive = drive_of(self._conditions)
        if self.mode is Mode.CLOSED:
            delay = target - t_hat
            late = delay < 0
            if late:
                delay = 0
        else:
            delay = self.open_delay_ns
            late = False
        flags = Flag.LATE | Flag.CLAMPED if late else Flag(0)
        if not p.ready:
            flags |= Flag.WARMUP
        if direction in self.commissioning:
            flags |= Flag.COMMISSIONING
        return Plan(direction, target, self.mode, t_hat, delay, late, p.order, tuple(p.coefficients), flags)

    def _arm(self, direction: Direction) -> None:
        plan = self._plan_for(direction)
        self.daq.arm(direction, plan.delay_ns)
        self._plan = plan

    def _rearm(self) -> None:
        if self._plan is not None:
            self._arm_or_defer(self._plan.direction)

    def _arm_or_defer(self, direction: Direction) -> None:
        """Arm now; a device that cannot take it (gone) is armed again at the next command."""
        try:
            self._arm(direction)
        except DaqError:
            self._plan = None

    def _cycle_once(self) -> None:
        t_cmd = self._next_tick_ns
        if self.cycle % self._conditions_every == 0:
            self.refresh_conditions()  # before the wait for the command: off the timing path
        if self._plan is None or self._plan.direction is not self._next_dir:
            # A run's first stroke (or one after a fault): armed here, in the slack, as every other
            # stroke is armed after the previous arrival; never a round trip inside the command's lead.
            self._arm_or_defer(self._next_dir)
        # A hardware-timed device is told ahead and waits for the instant itself.
        self._slack_until(t_cmd - self.daq.command_lead_ns)
        if self.state is not State.CYCLING or self._shutdown.is_set():
            return
        now = self.clock.now_ns()
        if now > t_cmd + self._period_ns // 2:
            # Behind schedule (a long stroke, a stalled machine): count it, restart the grid from now.
            self.overruns += 1
            t_cmd = now
        self._stroke(t_cmd)
        self._next_tick_ns = t_cmd + self._period_ns
        if self._cycling_left is not None and self._cycling_left > 0:
            self._cycling_left -= 1
            if self._cycling_left == 0:
                self.stop_cycling("done")

    def _stroke(self, t_cmd_ns: int | None) -> CycleRecord:
        """Command the armed stroke, stamp it, update the predictor, arm the next one, record."""
        self._in_stroke = True  # a fault latched now ends the run after this stroke's record
        try:
            return self._stroke_inner(t_cmd_ns)
        finally:
            self._in_stroke = False
            if self._run_ending is not None:
                self._end_run(self._run_ending)

    def _stroke_inner(self, t_cmd_ns: int | None) -> CycleRecord:
        direction = self._next_dir
        daq = self.daq
        bounces_before = daq.bounces
        levels = daq.levels()
        partial = levels is not None and not levels[direction.source]
        self._helpers_may_run.clear()
        try:
            if self._plan is None or self._plan.direction is not direction:
                self._arm(direction)
            plan = self._plan
            assert plan is not None
            cmd = daq.command(t_cmd_ns)
        except DaqError as exc:
            plan = self._plan if self._plan is not None else self._plan_for(direction)
            self._plan = None
            # Nothing moved; the attempt is still a cycle and gets its record.
            t_cmd = self.clock.now_ns() if t_cmd_ns is None else t_cmd_ns
            if isinstance(exc, DaqHalted) and self._shutdown.is_set():
                flags = plan.flags | Flag.ABORTED
            elif isinstance(exc, DaqHalted):
                flags = plan.flags | Flag.ESTOP | Flag.FAULT
                self._latch_fault(daq.halt_reason or "emergency stop")
            else:
                flags = flags_for_failure(plan)
                self._latch_fault(f"command failed: {exc}")
            return self._finish(plan, t_cmd, None, None, None, None, None, flags)
        finally:
            self._helpers_may_run.set()  # started (or not at all): the rest is waiting for edges
        t_start = cmd.t_start_ns
        deadline = (cmd.t_cmd_ns + cmd.delay_ns if t_start is None else t_start) + self.stroke_timeout_ns
        flags = plan.flags
        noise_before = list(daq.noise)
        got = read_stroke(
            daq,
            direction,
            cmd.t_cmd_ns,
            t_start,
            cmd.lateness_ns,
            deadline,
            self.stroke_timeout_ns,
            partial=partial,
            slice_ns=RECV_SLICE_NS,
            halted=lambda: self._estop.is_set() or self._shutdown.is_set(),
        )
        t_start, lateness, t_depart, t_arrive = got.t_start, got.lateness, got.t_depart, got.t_arrive
        if partial and t_depart is not None:
            # The mover left its source after the start: it was there, whatever the levels said (a
            # chattering line's last edge can leave them wrong until the next PONG).
            partial = False
        early_arrive, fault = got.early_arrive, got.fault
        if got.earlier_drive_fault:
            # The device restarted (its watchdog, a brown-out) between strokes: latched as it is
            # while idle; the run ends after this stroke's record.
            flags |= Flag.FAULT
            self._latch_fault(got.earlier_drive_fault)
        implausible = ""
        halted = self._estop.is_set() or self._shutdown.is_set()
        if t_arrive is None and early_arrive is not None and t_start is not None and not fault and not halted:
            t_arrive = early_arrive  # the only arrival there was: kept, and said what it was
        doubt = ""
        if t_arrive is not None and t_start is not None:
            implausible = self._implausible(direction, t_start, t_depart, t_arrive, partial)
            if implausible and not fault:
                # A device with its own account of the stroke settles it: when that account
                # disagrees, the wire lied (a line ringing) and the stroke is a MISMATCH, not a fault.
                doubt = self._check_with_device(got, direction)
                if doubt and got.report is not None and got.report.has_stamps:
                    implausible = ""
        if implausible:
            # Not a stroke: kept with its stamps, not learned from, the drive off and a FAULT that says
            # what the hardware side reported.
            operating = t_arrive - t_start if t_arrive is not None and t_start is not None else None
            self.implausible += 1
            self._plan = None
            self._safe_stop("implausible stroke")
            flags |= Flag.IMPLAUSIBLE | Flag.FAULT
            self._latch_fault(f"implausible stroke: {implausible}")
        elif t_arrive is not None and t_start is not None:
            operating = t_arrive - t_start
            told = self._told(direction, cmd.t_cmd_ns)  # idle since this direction's previous command
            self._last_command[direction] = cmd.t_cmd_ns
            # Arm ahead: the next stroke goes the other way, so its predictor is already up to date
            # and this stroke's update (an AIC re-selection may take a millisecond) comes after it.
            self._next_dir = direction.opposite
            self._arm_or_defer(self._next_dir)  # the timing path ends here
            doubt = doubt or self._check_with_device(got, direction)
            if doubt:
                flags |= Flag.MISMATCH  # the device's account disagrees: kept, never learned
            if partial:
                flags |= Flag.PARTIAL  # a part of a stroke would teach the predictor nonsense
            elif not doubt:
                try:
                    self.predictors[direction].update(operating, told)
                except ValueError as exc:  # a stamp the model cannot take: keep it out, say so
                    flags |= Flag.FAULT
                    self._latch_fault(f"stroke not fed to the predictor: {exc}")
        else:
            operating = None
            self._safe_stop(fault or "stall")
            if self._shutdown.is_set() and not fault:
                flags |= Flag.ABORTED  # cut short by shutdown: not the rig's fault
                return self._finish(plan, cmd.t_cmd_ns, t_start, t_depart, None, None, lateness, flags)
            if self._estop.is_set():
                flags |= Flag.ESTOP
                fault = fault or daq.halt_reason or "emergency stop"
            elif not fault:
                flags |= Flag.STALL
                fault = f"stall: no arrival within {format_ns(self.stroke_timeout_ns)} of the start"
            elif got.stalled:
                flags |= Flag.STALL
            flags |= Flag.FAULT
            self._latch_fault(fault)
        if daq.bounces != bounces_before:
            flags |= Flag.BOUNCE
        for ch in (0, 1):
            n = got.spurious[ch] + daq.noise[ch] - noise_before[ch]
            if n:
                self.noise[ch] += got.spurious[ch]
                self.spurious_edges += got.spurious[ch]
                flags |= Flag.NOISE
        if lateness is not None and lateness > self.late_margin_ns:
            flags |= Flag.LATE  # started past its instant: the stroke cannot meet T
        return self._finish(plan, cmd.t_cmd_ns, t_start, t_depart, t_arrive, operating, lateness, flags)

    def _implausible(
        self, direction: Direction, t_start: int, t_depart: int | None, t_arrive: int, partial: bool
    ) -> str:
        """Why a reported stroke is not physically one ("" when it is): the mover must leave the
        source after the start and reach the destination after leaving, in no less than the band's
        floor. A mover that started midway (PARTIAL) has no source to leave and a part of the way to go:
        neither check applies (the stroke is kept from the predictor as PARTIAL anyway)."""
        operating = t_arrive - t_start
        src, dst = direction.source.name, direction.dest.name
        if not partial:
            if t_depart is None:
                return (
                    f"sensor {dst} reported the arrival {format_ns(operating)} after the start, with no"
                    f" departure from sensor {src}"
                )
            if not t_start < t_depart < t_arrive:
                return (
                    f"sensor {dst} reported the arrival at +{format_ns(operating)}, before the departure"
                    f" from sensor {src} at +{format_ns(t_depart - t_start)}"
                )
        floor = self.min_stroke_ns[direction]
        if operating < floor and not partial:
            return f"operating time {format_ns(operating)} is below the plausible floor {format_ns(floor)}"
        return ""

    def _finish(
        self,
        plan: Plan,
        t_cmd: int,
        t_start: int | None,
        t_depart: int | None,
        t_arrive: int | None,
        operating: int | None,
        lateness: int | None,
        flags: Flag,
    ) -> CycleRecord:
        """Slack work after a stroke: the record, statistics, the sink and the listeners."""
        if self.cycle % self._conditions_every == 0:
            try:
                self._set_conditions(self._conditions_source())
            except DaqError:
                self._set_conditions(None)  # unknown while the device is away
        cond = self._conditions
        total = None if t_arrive is None else t_arrive - t_cmd
        error = None if total is None else total - plan.target_ns
        rec = CycleRecord(
            cycle=self.cycle,
            direction=int(plan.direction),
            mode=str(plan.mode),
            target_ns=plan.target_ns,
            order=plan.order,
            coefficients=plan.coefficients,
            t_hat_ns=plan.t_hat_ns,
            delay_ns=plan.delay_ns,
            t_cmd_ns=t_cmd,
            t_start_ns=t_start,
            t_depart_ns=t_depart,
            t_arrive_ns=t_arrive,
            operating_ns=operating,
            total_ns=total,
            error_ns=error,
            dead_ns=None if t_depart is None or t_start is None else t_depart - t_start,
            lateness_ns=lateness,
            temperature_c=None if cond is None else cond.temperature_c,
            frequency_hz=None if cond is None else cond.frequency_hz,
            flags=int(flags),
            wall_ns=time.time_ns(),
            run_id=self.latest_run.run_id
            if self.latest_run is not None and self.latest_run.running
            else None,
        )
        self.cycle += 1
        d = plan.direction
        if operating is not None and not flags & Flag.IMPLAUSIBLE and d in self.commissioning:
            self.commissioning.discard(d)
            if not self.min_stroke_ns[d]:  # no floor from a guess: the first real stroke sets it
                self.min_stroke_ns[d] = round(MIN_STROKE_FRACTION * operating)
        self.stats[plan.direction].add_record(rec)
        self.stats_all.add_record(rec)
        if rec.run_id is not None:
            self.run_stats[plan.direction].add_record(rec)
            self.run_stats_all.add_record(rec)
        if self.sink is not None:
            self.sink(rec)
        for listener in self.listeners:
            listener(rec)
        return rec

    def _read_idle_events(self) -> None:
        """While no stroke is going, read what the driver reports, so nothing piles up between a
        device and the loop; edges are counted (and said, at most every 10 s), a DRIVE fault (the
        device reset by its watchdog, say) latched as it would be during a stroke."""
        edges: list[Any] = []
        try:
            for _ in range(IDLE_READ_MAX):
                ev = self.daq.recv(0)
                if ev is None:
                    break
                if ev.kind is EventKind.EDGE:
                    edges.append(ev)
                elif ev.kind is EventKind.FAULT and ev.fault is FaultCode.DRIVE and self.state is State.IDLE:
                    # The device restarted (its watchdog, a brown-out) or the drive failed between
                    # strokes: a person looks before the next stroke, as after one mid-stroke.
                    self._latch_fault(f"drive: {ev.detail}" if ev.detail else "drive")
                else:  # a link's own faults reach status through the driver (driver_ok, counters)
                    self.stale_events += 1
        except DaqError:
            return
        if not edges:
            return
        self.idle_edges += len(edges)
        now = time.monotonic_ns()
        if now - self._idle_edges_said_ns >= IDLE_EDGES_LOG_EVERY_NS:
            self._idle_edges_said_ns = now
            last = edges[-1]
            log.warning(
                "sensor edges while idle: the mover was moved by hand, or a sensor chatters",
                edges=len(edges),
                total=self.idle_edges,
                last=f"sensor {last.channel.name} {'active' if last.level else 'released'}",
            )

    def _drain_stale_events(self) -> None:
        """Drop what the driver queued while faulted (the disconnect itself, late edges)."""
        with contextlib.suppress(DaqError):
            while self.daq.recv(0) is not None:
                self.stale_events += 1

    def _serve_requests(self, block_ns: int = 0, until_ns: int | None = None) -> None:
        """Run queued requests, first waiting up to `block_ns` of wall time for one (idle).

        `until_ns` (on the driver's clock) is the slack window's end: no request is begun after
        it, so however many are queued, the next command is not held up; the rest wait for the
        next window.
        """
        try:
            if block_ns > 0:  # idle waits on wall time, whatever the clock: nothing to simulate
                item = self._requests.get(timeout=block_ns / 1e9)
            else:
                item = self._requests.get_nowait()
        except queue.Empty:
            return
        clock = self.clock
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
                item = self._requests.get_nowait()
            except queue.Empty:
                return

    def _slack_until(self, t_ns: int) -> None:
        """Serve requests and housekeeping until shortly before `t_ns` (not in virtual time)."""
        self._slack()
        if self.clock.virtual:
            self._serve_requests()  # virtual time does not pass while requests run
            return
        end = t_ns - COMMAND_LEAD_NS
        self._serve_requests(until_ns=end)
        while not self._shutdown.is_set() and self.state is State.CYCLING:
            left = end - self.clock.now_ns()
            if left <= 0:
                return
            self._serve_requests(block_ns=left, until_ns=end)

    def _slack(self) -> None:
        # GC runs here, where the automatic collector would have run, but never mid-stroke.
        if gc.get_count()[0] > 700:
            gc.collect(0 if self.cycle % 64 else 1)
        for hook in self.slack_hooks:
            hook()

    @staticmethod
    def _enter_realtime_gc() -> None:
        gc.collect()
        gc.freeze()  # start-up objects never get scanned again
        gc.disable()
