"""A stroke as the device tells it, assembled on the host and checked against the host's own account.

The link thread hands each stroke's frames (START, EDGE, STOPPED, STROKE, FAULT) to `StrokeAssembler`,
which delivers them as events in order. Two accounts of every stroke reach the host: the frames as
they happen, and the device's STROKE report at its end. The assembler

- holds a stroke's events when frames went missing (a sequence gap, a START it had to reject) and
  rebuilds the missing ones from the report, or gives the stroke up with a FAULT WIRE that says so;
- checks the START against the instant the host commanded (`start_check`): a device that fired off
  its instant, or says it was late by other than it was, is named;
- ends each stroke with a REPORT event carrying the device's stamps and what the checks found, so
  the loop can hold its own stamps against them (`drivers.stroke_checks`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from .events import Channel, Direction, Event, EventKind, FaultCode, StrokeReport
from .mcu_clock import DeviceTimeline, fmt_ns
from .mcu_link import LinkStats
from .mcu_protocol import DeviceFault, Edge, Fault, Start, Stopped, StopReason, Stroke, StrokeFlags

log = logging.getLogger(__name__)

#: A stroke whose frames went missing waits this long for its STROKE report before it is given up.
REPORT_WAIT_NS = 150_000_000
#: How far a START may be from the instant the host commanded (command + delay), and its `late_us`
#: from the lateness the host measures, before the device's account of its start is refused. The
#: device stamps in microseconds and fires from a compare match: a few us either way is rounding.
START_TOLERANCE_NS = 50_000


@dataclass
class StrokeCtx:
    """What the host has delivered of the stroke in progress, to rebuild it if frames go missing."""

    stroke: int
    direction: Direction
    #: The instant the device should start the drive (command + delay) on the driver's clock, when
    #: the host knows it (a scheduled command, or an immediate one whose ACK carried its instant).
    due_ns: int | None = None
    started: bool = False
    departed: bool = False
    arrived: bool = False
    stopped: bool = False
    reported: bool = False
    #: Why a START for this stroke was rejected (another stroke's id, its stamp), "" if none was.
    start_rejected: str = ""
    #: That first rejected START was this stroke's own, stamped off the device clock (a clock that
    #: jumped): a stroke it leaves without a start is the link's (WIRE), not the order's (SEQUENCE).
    start_off_clock: bool = False
    #: What the host's checks found wrong with the device's account of this stroke.
    doubts: list[str] = field(default_factory=list)
    gap: bool = False
    hold_until_ns: int = 0
    held: list[Event] = field(default_factory=list)


class StrokeAssembler:
    """The stroke in progress: its frames in, its events out (under the driver's state lock)."""

    def __init__(
        self,
        timeline: DeviceTimeline,
        stats: LinkStats,
        deliver: Callable[[Event], None],
        host_stamp: Callable[[], int],
        last_stamp: Callable[[], int],
        submit: Callable[[StrokeReport], None] | None = None,
        *,
        name: str,
        stroke_timeout_ns: int,
        link_timeout_ns: int,
    ) -> None:
        self.timeline = timeline
        self.stats = stats
        self._deliver = deliver
        self._host_stamp = host_stamp
        # A REPORT is an account, not an instant: it carries the stamp of the last event delivered.
        self._report_stamp = last_stamp
        # Where a STROKE report's account goes: the driver checks the clock at its end first.
        self._submit = submit or self.deliver_report
        self.name = name
        self.stroke_timeout_ns = stroke_timeout_ns
        self.link_timeout_ns = link_timeout_ns
        self.ctx: StrokeCtx | None = None
        # Sensor levels (A, B) as the device last told them (PONG snapshot, then each EDGE newer than
        # it), and the stamp they are as of.
        self.levels: list[int] | None = None
        self.levels_t_ns = 0
        #: How late the device fired the last start against its scheduled instant.
        self.last_start_late_ns: int | None = None

    # -- strokes ------------------------------------------------------------------------------
    def begin(self, stroke: int, direction: Direction) -> None:
        """A stroke is being commanded: a stroke still waiting for its report is given up."""
        old = self.ctx
        if old is not None and old.gap and not old.reported:
            self.give_up(old, f"stroke {stroke} commanded")
        self.ctx = StrokeCtx(stroke, direction)

    def close(self, why: str) -> None:
        """The session ended (a restart, a lost link): deliver what there is and a STOP."""
        ctx = self.ctx
        if ctx is not None:
            self.flush(ctx)
            if ctx.started and not ctx.stopped:
                self._deliver(Event.stop(self._host_stamp(), ctx.direction, detail=why))
        self.ctx = None

    def poll(self, now: int) -> None:
        """The link thread's tick: a stroke whose report is overdue is given up."""
        ctx = self.ctx
        if ctx is not None and ctx.gap and not ctx.reported and now >= ctx.hold_until_ns:
            self.give_up(ctx, "no STROKE report")

    def hold(self, ctx: StrokeCtx, now: int | None = None) -> None:
        """Hold the stroke's events for its report (frames went missing, or one was not believed)."""
        if not ctx.gap and not ctx.reported:
            ctx.gap = True
            ctx.hold_until_ns = (time.monotonic_ns() if now is None else now) + REPORT_WAIT_NS

    # -- frames -------------------------------------------------------------------------------
    def on_pong_levels(self, a: int, b: int, raw_us: int) -> None:
        """The sensors as the device sampled them at its PONG's stamp (an edge it stamped later,
        though it reaches the host after the PONG, is newer)."""
        self.levels = [a, b]
        self.levels_t_ns = self.timeline.dev_ns(raw_us)

    def on_edge(self, msg: Edge) -> None:
        if msg.channel > 1 or msg.level > 1:
            log.warning("%s: EDGE with channel %d level %d ignored", self.name, msg.channel, msg.level)
            return
        ctx = self.ctx
        t = self.timeline.stamp(msg.t_us, f"EDGE of sensor {Channel(msg.channel).name}")
        if t is None:
            if ctx is not None and ctx.started and not ctx.reported:
                ctx.doubts.append(
                    f"an edge of sensor {Channel(msg.channel).name} stamped off the device clock"
                )
                self.hold(ctx)
            return
        ev = Event.edge(t, Channel(msg.channel), msg.level)
        if self.levels is not None and t >= self.levels_t_ns:
            self.levels[msg.channel] = msg.level  # an edge older than the snapshot says nothing new
            self.levels_t_ns = t
        if ctx is not None and not ctx.reported:
            if ev.channel is ctx.direction.source and ev.level == 0:
                ctx.departed = True
            elif ev.channel is ctx.direction.dest and ev.level == 1:
                ctx.arrived = True
            if ctx.gap:
                ctx.held.append(ev)
                return
        self._deliver(ev)

    def on_start(self, msg: Start) -> None:
        direction = Direction(msg.direction) if msg.direction <= 1 else None
        if direction is None:
            log.warning("%s: START with direction %d ignored", self.name, msg.direction)
            return
        ctx = self.ctx
        why = ""
        if ctx is None:
            why = f"a START of stroke {msg.stroke}, which was not commanded"
        elif ctx.stroke != msg.stroke:
            why = f"a START naming stroke {msg.stroke} during stroke {ctx.stroke}"
        elif ctx.started:
            why = f"a second START of stroke {msg.stroke}"
        elif direction is not ctx.direction:
            why = f"a START of stroke {msg.stroke} going {direction.name}, armed {ctx.direction.name}"
        t = None
        off_clock = False
        if not why:
            t = self.timeline.stamp(msg.t_us, f"START of stroke {msg.stroke}")
            if t is None:
                why = f"its START stamped {self.timeline.off_text(msg.t_us)}"
                off_clock = True
        else:
            self.stats.foreign_starts += 1
            log.warning("%s: %s rejected", self.name, why)
        if t is None:
            # Not this stroke's start. Its own may still come, or its STROKE report rebuild it: the
            # stroke's events are held till then, delivered in order; else it ends with a SEQUENCE fault.
            if ctx is not None and not ctx.started and not ctx.reported:
                if not ctx.start_rejected:
                    ctx.start_rejected = why
                    ctx.start_off_clock = off_clock
                self.hold(ctx)
            return
        assert ctx is not None
        late_ns = self.start_check(ctx, t, msg.late_us * 1000)
        self.last_start_late_ns = late_ns
        detail = f"late {fmt_ns(late_ns)}" if late_ns > 0 else ""
        ev = Event(EventKind.START, t, direction=direction, detail=detail, lateness_ns=late_ns)
        ctx.started = True
        if ctx.gap:
            ctx.held.append(ev)
        else:
            self._deliver(ev)

    def start_check(self, ctx: StrokeCtx, t_ns: int, claimed_late_ns: int) -> int:
        """The lateness of a start as the host measures it against its own commanded instant (the
        device's `late_us` when the host does not know the instant). A start off the instant, or a
        claim off the measure, by more than START_TOLERANCE_NS is a doubt on the stroke."""
        due = ctx.due_ns
        if due is None:
            return claimed_late_ns
        late = t_ns - due
        if late < -START_TOLERANCE_NS:
            ctx.doubts.append(f"it started {fmt_ns(-late)} before the commanded instant")
        elif abs(late - claimed_late_ns) > START_TOLERANCE_NS:
            ctx.doubts.append(
                f"it started {fmt_ns(late)} after the commanded instant and said {fmt_ns(claimed_late_ns)}"
            )
        if ctx.doubts:
            self.stats.start_mismatches += 1
        return max(0, late)

    def on_stopped(self, msg: Stopped) -> None:
        ctx = self.ctx
        direction = None
        if ctx is not None and ctx.stroke == msg.stroke:
            ctx.stopped = True
            direction = ctx.direction
        if msg.reason == StopReason.HOST:
            return  # Daq.stop() already reported it, stamped when it was asked
        name = (
            StopReason(msg.reason).name.lower() if msg.reason in StopReason._value2member_map_ else "unknown"
        )
        # The drive went off: that is news even with a stamp not to be believed (stamped on arrival).
        t = self.timeline.stamp(msg.t_us, "STOPPED")
        ev = Event.stop(self._host_stamp() if t is None else t, direction, detail=name)
        if ctx is not None and ctx.gap and not ctx.reported:
            ctx.held.append(ev)
            if direction is not None and ctx.start_rejected:
                # The device sends its STROKE report before STOPPED: none will come to rebuild it.
                self.give_up(ctx, "no STROKE report came before its STOPPED")
        else:
            self._deliver(ev)
        if ctx is not None and ctx.stroke == msg.stroke and not ctx.reported:
            # The device sends a stroke's STROKE report before its STOPPED: this one was lost.
            self.give_up(ctx, "its STROKE report did not come before its STOPPED")

    def on_stroke(self, msg: Stroke) -> None:
        ctx = self.ctx
        if ctx is None or ctx.stroke != msg.stroke:
            return  # a report of a stroke this host session did not command
        if ctx.reported:
            return
        ctx.reported = True
        flags = StrokeFlags(msg.flags)
        behind = self.link_timeout_ns + self.stroke_timeout_ns
        stamp = self.timeline.stamp
        what = f"STROKE {msg.stroke} report's"
        t_start = stamp(msg.t_start_us, f"{what} start", behind)
        t_depart = (
            stamp(msg.t_depart_us, f"{what} departure", behind) if StrokeFlags.DEPARTED in flags else None
        )
        t_arrive = stamp(msg.t_arrive_us, f"{what} arrival", behind) if StrokeFlags.ARRIVED in flags else None
        rebuilt: list[Event] = []
        if not ctx.started and t_start is not None:
            late = self.start_check(ctx, t_start, 0) if ctx.due_ns is not None else 0
            rebuilt.append(Event.start(t_start, ctx.direction, lateness_ns=late))
            ctx.started = True
        if t_depart is not None and not ctx.departed:
            rebuilt.append(Event.edge(t_depart, ctx.direction.source, 0))
            ctx.departed = True
        if t_arrive is not None and not ctx.arrived:
            rebuilt.append(Event.edge(t_arrive, ctx.direction.dest, 1))
            ctx.arrived = True
        if rebuilt:
            self.stats.recovered_strokes += 1
            log.info(
                "%s: stroke %d rebuilt from its report: %d event(s)", self.name, msg.stroke, len(rebuilt)
            )
        ctx.held.extend(rebuilt)
        self.flush(ctx)
        self.no_start(ctx, "nor did its STROKE report give one")
        if (StrokeFlags.ARRIVED in flags and t_arrive is None) or t_start is None:
            ctx.doubts.append("its STROKE report's stamps are off the device clock")
        if StrokeFlags.MISSED_EDGE in flags:
            ctx.doubts.append("a stamp of it is a missed edge's, read back late (a noisy line)")
        if StrokeFlags.EVENTS_LOST in flags:
            ctx.doubts.append("the device lost interrupt events during it")
        report = StrokeReport(
            t_start_ns=t_start,
            t_depart_ns=t_depart,
            t_arrive_ns=t_arrive,
            arrived=StrokeFlags.ARRIVED in flags,
            has_stamps=True,
            detail="; ".join(ctx.doubts),
        )
        self._submit(report)

    def deliver_report(self, report: StrokeReport) -> None:
        """The stroke's account, for the loop (after the driver's last checks)."""
        self._deliver(Event.report_event(self._report_stamp(), report))

    def on_fault(self, msg: Fault) -> None:
        t = self.timeline.stamp(msg.t_us, "FAULT")
        t = self._host_stamp() if t is None else t  # a fault is news whatever its stamp
        code = {
            DeviceFault.STALL: FaultCode.STALL,
            DeviceFault.HOST_SILENT: FaultCode.DISCONNECT,
            DeviceFault.SENSORS: FaultCode.SEQUENCE,
            DeviceFault.DRIVE: FaultCode.DRIVE,
            # The firmware lost interrupt events (an edge storm): the stroke's account is gone.
            DeviceFault.EVENTS_LOST: FaultCode.SEQUENCE,
        }.get(msg.code, FaultCode.DRIVE)
        what = (
            DeviceFault(msg.code).name if msg.code in DeviceFault._value2member_map_ else f"code {msg.code}"
        )
        ev = Event.fault_event(t, code, f"device: {what} (detail {msg.detail})")
        ctx = self.ctx
        if ctx is not None and ctx.gap and not ctx.reported:
            ctx.held.append(ev)
        else:
            self._deliver(ev)

    # -- endings ------------------------------------------------------------------------------
    def no_start(self, ctx: StrokeCtx, why: str) -> None:
        """A stroke whose START was rejected and never came good: a fault ends it, WIRE when its own
        START was stamped off the device clock (the clock jumped), else SEQUENCE (a foreign START)."""
        if ctx.started or not ctx.start_rejected:
            return
        ctx.started = True  # said once
        self.stats.unrecovered_strokes += 1
        self._deliver(
            Event.fault_event(
                self._host_stamp(),
                FaultCode.WIRE if ctx.start_off_clock else FaultCode.SEQUENCE,
                f"stroke {ctx.stroke} has no START of its own ({ctx.start_rejected} was rejected), {why}",
            )
        )

    def give_up(self, ctx: StrokeCtx, why: str) -> None:
        """Frames of `ctx` were lost and its report never came: deliver what there is, flag it."""
        ctx.reported = True
        self.flush(ctx)
        if not ctx.started and ctx.start_rejected:
            self.no_start(ctx, f"and {why}")
        elif not ctx.arrived:
            self.stats.unrecovered_strokes += 1
            self._deliver(
                Event.fault_event(
                    self._host_stamp(), FaultCode.WIRE, f"stroke {ctx.stroke}: frames lost and {why}"
                )
            )
        else:
            doubts = "; ".join([*ctx.doubts, f"frames were lost and {why}"])
            report = StrokeReport(arrived=True, detail=doubts)
            self._deliver(Event.report_event(self._report_stamp(), report))

    def flush(self, ctx: StrokeCtx) -> None:
        held = sorted(ctx.held, key=lambda e: e.t_ns)
        ctx.held = []
        ctx.gap = False
        for ev in held:
            self._deliver(ev)
