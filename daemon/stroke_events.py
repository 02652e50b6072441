"""Reading one stroke's events off the driver, and holding them against the device's own account.

`read_stroke` follows a commanded stroke from its start to its arrival, a fault, or its timeout;
`await_report` then waits for the device's REPORT (drivers that report strokes) so the loop can
check its stamps before it learns from them. A stall is declared only once what is in hand and on
the line has been read: past the stroke timeout the loop reads on for the driver's `report_wait_ns`,
an arrival stamped inside the timeout still counts, and the cause is named: the device's own STALL
(the mover), or no word from it at all (WIRE: the link).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from usmswitch.drivers import Channel, Daq, DaqError, Direction, Event, EventKind, FaultCode
from usmswitch.drivers.events import StrokeReport
from usmswitch.protocol.units import format_ns

#: Driver faults that end the stroke in progress, with the name its FAULT is latched under.
STROKE_FAULTS = {
    FaultCode.DISCONNECT: "disconnect",
    FaultCode.STALL: "stall",
    FaultCode.DRIVE: "drive",
    FaultCode.SEQUENCE: "edge order",
    FaultCode.WIRE: "wire",
}
#: Past a stroke's deadline, at most this many events already in hand are read before it ends (a
#: line ringing on keeps adding more).
MAX_READS_PAST_DEADLINE = 10_000
#: How far the host's stamps of a stroke may be from the device's report of it: both are the
#: device's stamps of the same edges, so only the microsecond rounding separates them.
REPORT_TOLERANCE_NS = 2_000


@dataclass
class StrokeEvents:
    """What one stroke's events said."""

    t_start: int | None
    lateness: int | None
    t_depart: int | None = None
    t_arrive: int | None = None
    #: An arrival before any departure: a glitch, or a sensor that lies (kept if nothing better came).
    early_arrive: int | None = None
    fault: str = ""
    #: The fault's cause was the mover (a stall), not the link or the device.
    stalled: bool = False
    report: StrokeReport | None = None
    #: Edges the stroke does not explain, per sensor (A, B).
    spurious: list[int] = field(default_factory=lambda: [0, 0])
    #: The device fault (its watchdog or a brown-out reset) stamped before this stroke's command.
    earlier_drive_fault: str = ""

    def take_edge(self, ev: Event, src: Channel, dst: Channel, timeout_ns: int, partial: bool) -> bool:
        """A sensor edge: the departure, the arrival (True: the stroke is over), or one the stroke
        does not explain."""
        ts = self.t_start
        if ts is None or ev.t_ns <= ts or ev.t_ns > ts + timeout_ns:
            self.spurious[int(ev.channel)] += 1
        elif ev.channel is dst and ev.level == 1:
            if self.t_depart is None and not partial:
                # Not yet left: a glitch, or a sensor that lies. The stroke goes on; if nothing
                # better comes, it ends IMPLAUSIBLE with this stamp.
                self.spurious[int(ev.channel)] += 1
                self.early_arrive = self.early_arrive or ev.t_ns
                return False
            self.t_arrive = ev.t_ns
            return True
        elif ev.channel is src and ev.level == 0 and self.t_depart is None:
            self.t_depart = ev.t_ns
        else:
            self.spurious[int(ev.channel)] += 1
        return False

    def take_report(self, report: StrokeReport, timeout_ns: int) -> bool:
        """The device's account of the stroke; True when it ends the reading (a stall it reports, an
        arrival it has no stamp of, or the only arrival there was confirmed)."""
        self.report = report
        if report.arrived and self.early_arrive is not None and self.t_arrive is None:
            return True  # the device's account is in: the only arrival there was is all there is
        if not report.arrived:
            self.fault = f"stall: the device reports no arrival within {format_ns(timeout_ns)} of the start"
            self.stalled = True
            return True
        if self.t_start is not None and report.has_stamps and report.t_arrive_ns is None:
            why = report.detail
            self.fault = f"wire: the device reports an arrival, but no believable stamp of it ({why})"
            return True
        return False

    def take_fault(self, ev: Event, t_cmd_ns: int) -> bool:
        """A driver fault that ends a stroke (True), or one from before this command (kept if the
        device restarted, else dropped)."""
        name = STROKE_FAULTS[ev.fault]  # type: ignore[index]
        if ev.t_ns < t_cmd_ns:
            # Left over from before this command. A device's reset between strokes is still news.
            if ev.fault is FaultCode.DRIVE:
                self.earlier_drive_fault = f"{name}: {ev.detail}" if ev.detail else name
            return False
        self.fault = f"{name}: {ev.detail}" if ev.detail else name
        self.stalled = ev.fault is FaultCode.STALL
        return True

    def name_silence(self, waited_ns: int, grace_ns: int, timeout_ns: int) -> None:
        """No arrival and no fault past the report wait: the link's (WIRE), named by what came."""
        if self.report is not None and self.report.arrived:
            self.fault = (
                "wire: the device reports an arrival whose stamps did not reach the host"
                f" ({self.report.detail or 'no detail'})"
            )
        elif self.t_start is None:
            self.fault = (
                f"wire: no START from the device within {format_ns(waited_ns)} of the command"
                " (the link, or a device that did not take the command)"
            )
        else:
            self.fault = (
                f"wire: no word from the device within {format_ns(grace_ns)} after the stroke timeout"
                f" ({format_ns(timeout_ns)}): neither an arrival nor its stall"
            )


def read_stroke(
    daq: Daq,
    direction: Direction,
    t_cmd_ns: int,
    t_start: int | None,
    lateness: int | None,
    deadline: int,
    timeout_ns: int,
    *,
    partial: bool,
    slice_ns: int,
    halted: Callable[[], bool],
) -> StrokeEvents:
    """Follow a commanded stroke until its arrival, a fault, or its timeout and the report wait."""
    out = StrokeEvents(t_start, lateness)
    src, dst = direction.source, direction.dest
    clock = daq.clock
    grace = daq.report_wait_ns
    # Past the deadline the device's own stall limit (armed with the same timeout) has cut the drive;
    # its account of the stroke is still read before a cause is named, and the loop's stop follows.
    # Past it, what is already in hand is still read (a loop thread that woke late must not call a
    # stall the arrival stamped inside the timeout): its stamps decide, not when it was read.
    late_reads = MAX_READS_PAST_DEADLINE
    while True:
        now = clock.now_ns()
        past = now >= deadline + grace
        if past:
            late_reads -= 1
            if late_reads < 0:
                break
        try:
            ev = daq.recv(0 if past else min(slice_ns, deadline + grace - now))
        except DaqError as exc:
            out.fault = f"driver: {exc}"
            break
        if ev is None:
            if past or halted():
                break
            continue
        kind = ev.kind
        if kind is EventKind.EDGE:
            if out.take_edge(ev, src, dst, timeout_ns, partial):
                break
        elif kind is EventKind.START:
            if out.t_start is None:
                out.t_start = ev.t_ns
                out.lateness = ev.lateness_ns
                deadline = ev.t_ns + timeout_ns
        elif kind is EventKind.REPORT:
            assert ev.report is not None
            if out.take_report(ev.report, timeout_ns):
                break
        elif kind is EventKind.FAULT and ev.fault in STROKE_FAULTS:
            if out.take_fault(ev, t_cmd_ns):
                break
        elif kind is EventKind.STOP and halted():
            break  # the halt's own stop: nothing will arrive
    if not out.fault and out.t_arrive is None and out.early_arrive is None and not halted() and grace:
        out.name_silence(clock.now_ns() - t_cmd_ns, grace, timeout_ns)
    return out


def await_report(daq: Daq, events: StrokeEvents, *, slice_ns: int, halted: Callable[[], bool]) -> None:
    """After an arrival: read on for the device's REPORT (drivers that report strokes), counting
    what else comes as edges the stroke does not explain."""
    if events.report is not None or not daq.reports_strokes:
        return
    clock = daq.clock
    end = clock.now_ns() + daq.report_wait_ns
    while (now := clock.now_ns()) < end and not halted():
        try:
            ev = daq.recv(min(slice_ns, end - now))
        except DaqError:
            return
        if ev is None:
            continue
        if ev.kind is EventKind.REPORT:
            events.report = ev.report
            return
        if ev.kind is EventKind.EDGE:
            events.spurious[int(ev.channel)] += 1  # chatter after the arrival, before the report


def disagreement(events: StrokeEvents) -> str:
    """Why the stroke's stamps are not the device's account of it ("" when they agree): the report
    missing or saying otherwise. (Where the sensors say the mover rests is checked as the next
    stroke starts: one that starts away from its source is PARTIAL, docs/daemon.md; read at the
    arrival it would race the bounce of the sensor's own contact.)"""
    rep = events.report
    if rep is None:
        return "no report of the stroke from the device"
    doubts = [rep.detail] if rep.detail else []
    for what, ours, theirs in (
        ("start", events.t_start, rep.t_start_ns),
        ("departure", events.t_depart, rep.t_depart_ns),
        ("arrival", events.t_arrive, rep.t_arrive_ns),
    ):
        if not rep.has_stamps:
            break
        if ours is None or theirs is None:
            if theirs is None and ours is not None and what != "departure":
                doubts.append(f"the device reports no {what}")
            continue
        if abs(ours - theirs) > REPORT_TOLERANCE_NS:
            doubts.append(f"the {what} on the wire is {format_ns(ours - theirs)} off the device's report")
    return "; ".join(doubts)


def implausible_reason(
    direction: Direction, t_start: int, t_depart: int | None, t_arrive: int, partial: bool, floor_ns: int
) -> str:
    """Why a reported stroke is not physically one ("" when it is): the mover must leave the
    source after the start and reach the destination after leaving, in no less than the plausible
    band's floor (`floor_ns`). A mover that started midway (PARTIAL) has no source to leave and a
    part of the way to go: neither check applies (it is kept from the predictor as PARTIAL anyway)."""
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
    if operating < floor_ns and not partial:
        return f"operating time {format_ns(operating)} is below the plausible floor {format_ns(floor_ns)}"
    return ""
