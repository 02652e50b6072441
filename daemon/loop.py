"""The control loop of the paper's Fig. 10: predict, delay, start, stamp, record.

One thread owns the driver and the predictors. Everything else (socket, signals, summary) talks to
it through `call()` (a queue drained in the loop's slack) or `estop()` (immediate). The timing path
runs from an arrival stamp to the next stroke being armed, and from a command to its start: on it
there is no logging, no disk I/O, no socket work and no garbage collection.
"""

from __future__ import annotations

import contextlib
import gc
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from enum import StrEnum
from typing import Any

import structlog

from usmswitch.drivers import Conditions, Daq, DaqError, DaqHalted, Direction, check_ns
from usmswitch.protocol.record import CycleRecord, Flag, RunRecord
from usmswitch.protocol.stats import DirectionStats
from usmswitch.protocol.units import format_ns

from . import reach
from .idle_events import IdleEvents
from .loop_requests import RequestQueue
from .plan import Mode, Plan, direction_from_levels, drive_of, flags_for_failure, predictor_conditions
from .runs import RunBook
from .stroke_events import StrokeEvents, await_report, disagreement, implausible_reason, read_stroke

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


class LoopError(Exception):
    """A request the loop refuses in its present state; the message says why."""


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
        self.runs = RunBook(first_run_id, run_sink)
        self._first_cycle = first_cycle
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
        self.idle = IdleEvents()  # what the driver reports between strokes
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
        self._requests = RequestQueue()
        self._estop = threading.Event()
        # Cleared from the end of a slack window until the stroke has started: the daemon's other
        # threads wait on it (`wait_turn`) so that none holds the GIL when the start is due.
        self._helpers_may_run = threading.Event()
        self._helpers_may_run.set()
        self._shutdown = threading.Event()
        self._cycling_left: int | None = None  # strokes still to run; -1 forever; None not cycling
        self._period_ns = 0
        self._next_tick_ns = 0

    @property
    def latest_run(self) -> RunRecord | None:
        """The open run, else the last one (None before the first)."""
        return self.runs.latest

    @property
    def run_sink(self) -> Callable[[RunRecord], None] | None:
        """Where each opened and ended run is sent (the record store)."""
        return self.runs.sink

    @run_sink.setter
    def run_sink(self, sink: Callable[[RunRecord], None] | None) -> None:
        self.runs.sink = sink

    @property
    def idle_edges(self) -> int:
        """Sensor edges reported while no stroke was going (the mover moved by hand, a sensor chatters)."""
        return self.idle.edges

    @property
    def stale_events(self) -> int:
        """Driver events read and dropped outside a stroke (idle, a fault reset)."""
        return self.idle.stale

    # -- requests from other threads ------------------------------------------------------------
    def call(self, fn: Callable[[], Any]) -> Future[Any]:
        """Run `fn` on the loop thread in its slack; the future carries its result or exception."""
        return self._requests.put(fn)

    def estop(self, reason: str = "emergency stop") -> None:
        """Drive off now, from any thread, and final: when it returns no start can follow.

        The driver is halted (drive off, nothing armed, a waiting start abandoned) until
        `reset_fault`; the loop latches FAULT and stops cycling at its next step.
        """
        self.stop_now(reason)
        self.latch_stop(reason)

    def stop_now(self, reason: str) -> None:
        """`estop`'s part that its answer waits for: the drive off, no start after it, FAULT shown
        (a status right after the estop's reply says FAULT); `latch_stop` must follow."""
        self._estop.set()
        self._halt(reason)
        self.fault_reason = reason
        self.state = State.FAULT

    def latch_stop(self, reason: str) -> None:
        """`estop`'s rest: the loop thread latches the fault fully (cycling stopped, the run ended)
        at its next step; queued here so that an idle loop does it too."""
        self.call(lambda: self._latch_fault(reason))

    def shutdown(self) -> None:
        """Ask `run()` to return, drive off and no start after this call (signal handlers call this)."""
        self._shutdown.set()
        self._halt("shutdown")
        self._requests.wake()

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
        return reach.shortest_target_ns(self.predictors[direction], self.late_margin_ns)

    def check_reach(self, targets: Sequence[int], mode: Mode | None = None) -> None:
        """Refuse (TargetUnreachableError) a closed-loop target below what the rig reaches."""
        if (mode or self.mode) is Mode.CLOSED:
            reach.check_reach(self.predictors, targets, self.late_margin_ns)

    def reach_warnings(self) -> list[str]:
        """Per direction, a warning when T is shorter than the predicted stroke (it will be late)."""
        return reach.reach_warnings(self.predictors, self.targets)

    def reset_fault(self) -> None:
        """Clear a latched FAULT; the drive stays off until the next command."""
        if self.state is State.FAULT and not self.daq.ping():
            raise LoopError(f"{self.daq.name} is not connected: reset when the device is back")
        if self._shutdown.is_set():
            raise LoopError("shutting down")
        self._estop.clear()
        self.daq.release()
        if self.state is State.FAULT:
            self.idle.drain(self.daq)
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
        label: str | None = None,
        notes: str | None = None,
    ) -> RunRecord:
        """Command a stroke every `period_ns`, alternately on and off, `count` strokes (0: until
        stopped), as a new run; returns the run (its id, its first cycle, its settings).

        `kind`, `settings`, `label` and `notes` describe the run for its record (an experiment names
        itself and adds its own settings to the loop's).
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
        settings = {"period_ns": period_ns, "count": count, **(settings or {})}
        return self.runs.open(kind, self.cycle, {**self.run_settings(), **settings}, label, notes)

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

    def _end_run(self, reason: str) -> None:
        """End the open run (if any) with `reason`; during a stroke, once that stroke is recorded."""
        self.runs.end(reason, self.cycle - 1, self._in_stroke)

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
            per, both, first = self.runs.stats, self.runs.stats_all, run.first_cycle
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
        reach.check_period(self.predictors, period_ns, targets, mode, open_delay_ns)

    def _check_device(self, targets: Sequence[int], mode: Mode, open_delay_ns: int) -> None:
        longest = self.daq.limits().get("max_delay_ns")
        reach.check_device(self.predictors, longest, targets, mode, open_delay_ns)

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
            self.runs.after_stroke(self.cycle - 1)

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
            implausible = implausible_reason(
                direction, t_start, t_depart, t_arrive, partial, self.min_stroke_ns[direction]
            )
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
        rec = plan.record(
            self.cycle,
            t_cmd,
            t_start,
            t_depart,
            t_arrive,
            operating,
            lateness,
            flags,
            cond=self._conditions,
            run_id=self.runs.running_id,
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
            self.runs.add(rec)
        if self.sink is not None:
            self.sink(rec)
        for listener in self.listeners:
            listener(rec)
        return rec

    def _read_idle_events(self) -> None:
        drive_fault = self.idle.read(self.daq, latch_drive=self.state is State.IDLE)
        if drive_fault:
            self._latch_fault(drive_fault)

    def _serve_requests(self, block_ns: int = 0, until_ns: int | None = None) -> None:
        self._requests.serve(self.clock, block_ns, until_ns)

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
