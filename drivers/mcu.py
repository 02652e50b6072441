"""The host side of the MCU protocol, shared by the serial and USB drivers.

`McuDaq` is a hardware-timed `Daq` over any byte `Transport`. A link thread owns the reading: it
decodes frames off the timing path, answers nothing itself, sends heartbeats, keeps the clock
mapping, detects lost frames by sequence number, rebuilds a stroke from the device's STROKE report
when frames went missing, and on a dead link treats the drive as stopped, reports FAULT DISCONNECT
and reconnects with backoff and a fresh handshake. Callers' arm/command/stop write directly.

A device that restarts (it says BOOT as it starts; or its PONG no longer says SYNCED, or a new
handshake finds its clock started again) ends the stroke in progress and is handshaken again; a
restart by its hardware watchdog (the firmware hung) or a brown-out is reported as FAULT DRIVE, any
other restart (power, the reset pin) as FAULT DISCONNECT, each with the cause in its detail.

This module is the link and the session (handshake, requests and their ACKs, heartbeats,
reconnects); the device's clock is `mcu_clock.DeviceTimeline`, the stroke in progress and its
checks `mcu_stroke.StrokeAssembler`.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field

from .daq import DEFAULT_DEBOUNCE_NS, Daq, DaqDisconnected, DaqError, check_ns
from .events import Direction, Event, EventKind, FaultCode, StrokeReport
from .mcu_clock import STAMP_AHEAD_NS, DeviceTimeline, fmt_ns
from .mcu_handshake import HandshakeMixin, reset_text
from .mcu_link import DeviceClock, LinkStats, Transport, TransportLost
from .mcu_protocol import (
    U16_MOD,
    U32_MOD,
    Ack,
    Arm,
    Boot,
    Command,
    Edge,
    Fault,
    FrameDecoder,
    HelloAck,
    Message,
    MsgType,
    Ping,
    Pong,
    SeqTracker,
    Start,
    StateFlags,
    Status,
    Stop,
    Stopped,
    StopReason,
    Stroke,
    encode_frame,
)
from .mcu_stroke import REPORT_WAIT_NS, StrokeAssembler

log = logging.getLogger(__name__)

DEFAULT_HEARTBEAT_NS = 100_000_000
DEFAULT_LINK_TIMEOUT_NS = 400_000_000
DEFAULT_WATCHDOG_MS = 500
DEFAULT_REPLY_TIMEOUT_NS = 25_000_000
DEFAULT_RETRIES = 3
DEFAULT_STROKE_TIMEOUT_NS = 100_000_000
DEFAULT_RECONNECT_MIN_NS = 50_000_000
DEFAULT_RECONNECT_MAX_NS = 2_000_000_000
_READ_SLICE_NS = 10_000_000
#: Events queued between the link thread and the loop: beyond it the oldest are dropped, counted
#: (`events_dropped`), and a stroke in progress ends with a FAULT SEQUENCE saying so.
MAX_QUEUED_EVENTS = 8192
#: The device's own stall limit (ARM timeout_us) spans 1 ms to 10 s (docs/mcu-protocol.md).
MIN_STROKE_TIMEOUT_NS = 1_000_000
MAX_STROKE_TIMEOUT_NS = 10_000_000_000

__all__ = ["MAX_QUEUED_EVENTS", "MAX_STROKE_TIMEOUT_NS", "REPORT_WAIT_NS", "STAMP_AHEAD_NS", "McuDaq"]


@dataclass
class _Waiter:
    """A request waiting for its ACK; any of its retransmissions' ACKs completes it."""

    mtype: MsgType
    seqs: list[int] = field(default_factory=list)
    done: threading.Event = field(default_factory=threading.Event)
    ack: Ack | None = None
    lost: str = ""


class McuDaq(HandshakeMixin, Daq):
    """A hardware-timed DAQ: the rig's microcontroller over a byte transport (docs/mcu-protocol.md)."""

    hardware_timed = True
    name = "mcu"
    # A serial/USB frame reaches the host ~0.3-1 ms after the device stamped it (measured in
    # bench_serial); chatter frames must be in before the debouncer decides.
    delivery_latency_ns = 2_000_000
    # COMMAND goes out this long before its tick; the device waits for t_cmd + delay itself.
    command_lead_ns = 4_000_000

    def __init__(
        self,
        transport: Transport,
        *,
        debounce_ns: int = DEFAULT_DEBOUNCE_NS,
        stroke_timeout_ns: int = DEFAULT_STROKE_TIMEOUT_NS,
        heartbeat_ns: int = DEFAULT_HEARTBEAT_NS,
        link_timeout_ns: int = DEFAULT_LINK_TIMEOUT_NS,
        watchdog_ms: int = DEFAULT_WATCHDOG_MS,
        reply_timeout_ns: int = DEFAULT_REPLY_TIMEOUT_NS,
        retries: int = DEFAULT_RETRIES,
        reconnect_min_ns: int = DEFAULT_RECONNECT_MIN_NS,
        reconnect_max_ns: int = DEFAULT_RECONNECT_MAX_NS,
        max_delay_ns: int = 0,
        max_queued_events: int = MAX_QUEUED_EVENTS,
    ) -> None:
        """`max_delay_ns`: the longest start delay the host may ask for (its longest target); a
        device whose longest (HELLO_ACK max_delay_us) is shorter is refused at the handshake."""
        super().__init__(clock=DeviceClock(), debounce_ns=debounce_ns)
        self.clock: DeviceClock
        self.transport = transport
        self.stroke_timeout_ns = check_ns(
            "stroke_timeout_ns", stroke_timeout_ns, minimum=MIN_STROKE_TIMEOUT_NS
        )
        if self.stroke_timeout_ns > MAX_STROKE_TIMEOUT_NS:
            raise ValueError(
                f"stroke_timeout_ns {fmt_ns(stroke_timeout_ns)} is longer than the device's longest stall"
                f" limit, {fmt_ns(MAX_STROKE_TIMEOUT_NS)} (ARM timeout_us, docs/mcu-protocol.md)"
            )
        self.heartbeat_ns = check_ns("heartbeat_ns", heartbeat_ns, minimum=1_000_000)
        self.link_timeout_ns = check_ns("link_timeout_ns", link_timeout_ns, minimum=2 * self.heartbeat_ns)
        if (
            isinstance(watchdog_ms, bool)
            or not isinstance(watchdog_ms, int)
            or not 10 <= watchdog_ms < U16_MOD
        ):
            raise ValueError(f"watchdog_ms must be an integer in 10..65535, got {watchdog_ms!r}")
        if watchdog_ms * 1_000_000 <= self.heartbeat_ns:
            raise ValueError(
                f"watchdog_ms={watchdog_ms} must exceed the heartbeat period ({heartbeat_ns} ns)"
            )
        self.watchdog_ms = watchdog_ms
        self.reply_timeout_ns = check_ns("reply_timeout_ns", reply_timeout_ns, minimum=100_000)
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 1:
            raise ValueError(f"retries must be an integer >= 1, got {retries!r}")
        self.retries = retries
        self.reconnect_min_ns = check_ns("reconnect_min_ns", reconnect_min_ns, minimum=1_000_000)
        self.reconnect_max_ns = check_ns("reconnect_max_ns", reconnect_max_ns, minimum=self.reconnect_min_ns)

        self.max_delay_ns = check_ns("max_delay_ns", max_delay_ns)
        if (
            isinstance(max_queued_events, bool)
            or not isinstance(max_queued_events, int)
            or max_queued_events < 16
        ):
            raise ValueError(f"max_queued_events must be an integer >= 16, got {max_queued_events!r}")
        self.max_queued_events = max_queued_events
        self.stats = LinkStats()
        #: What the device announced at the last handshake.
        self.device: HelloAck | None = None
        self.timeline = DeviceTimeline(
            self.clock,
            self.stats,
            name=self.name,
            heartbeat_ns=self.heartbeat_ns,
            link_timeout_ns=self.link_timeout_ns,
        )
        self.strokes = StrokeAssembler(
            self.timeline,
            self.stats,
            self._deliver,
            self._host_stamp,
            lambda: self._last_stamp_ns,
            self._check_clock_then_report,
            name=self.name,
            stroke_timeout_ns=self.stroke_timeout_ns,
            link_timeout_ns=self.link_timeout_ns,
        )

        self._wlock = threading.Lock()  # frames go out whole, in sequence order
        self._state = threading.Condition()  # guards everything below; link thread <-> callers
        self._events: deque[Event] = deque()
        self._waiters: dict[int, _Waiter] = {}
        self._connected = False
        self._closing = False
        self._thread: threading.Thread | None = None
        self._tx_seq = 0
        self._rx_seq = SeqTracker()
        self._decoder = FrameDecoder()
        self._refuse_why = ""  # set by the link thread: drop the link, saying why
        self._overflow_said = False
        self._last_stamp_ns = 0
        self._stroke_id = 0
        self._armed_msg: Arm | None = None
        self._arm_waiter: _Waiter | None = None
        self._pings: dict[int, int] = {}
        self._ping_token = 0
        # A stroke's report waiting for the PONG that checks the clock at its end: (token, report, sent).
        self._report_check: tuple[int, StrokeReport, int] | None = None
        self._report_ping: int | None = None  # its PING, to send once the frames in hand are handled
        self._last_rx_ns = 0
        self._next_ping_ns = 0
        self._dev_errors_base = (0, 0)
        # Counters of past sessions (each handshake starts a fresh decoder, tracker and unwrapper).
        self._decoder_totals = (0, 0, 0)
        self._lost_total = 0
        self._resets_total = 0
        self._boot_reported = False  # a BOOT reported the restart the next handshake will meet
        self._resync_why = ""

    # -- lifecycle ---------------------------------------------------------------------------
    def _open(self) -> None:
        self._closing = False
        try:
            self.transport.open()
            self._handshake()
        except DaqError:
            self.transport.close()
            raise
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-link", daemon=True)
        self._thread.start()

    def _close(self) -> None:
        with self._state:
            self._closing = True
            self._state.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        self._thread = None
        self._mark_lost("driver closed", report=False)
        self.transport.close()

    def stamp_ahead_ns(self) -> int:
        # The link took each stamp within the clock's uncertainty (half the round trip of the
        # sample it stands on, which a busy host makes long, all on the way back: the clock then
        # runs that far behind the device); `recv` must not drop what the link believed.
        return STAMP_AHEAD_NS + self.timeline.err_ns(time.monotonic_ns())

    def ping(self) -> bool:
        """True when the link is up and the device spoke within the link timeout."""
        with self._state:
            return (
                self.is_open
                and self._connected
                and time.monotonic_ns() - self._last_rx_ns < self.link_timeout_ns
            )

    def levels(self) -> tuple[int, int] | None:
        """Sensor levels (A, B) from the device's last PONG and the edges since; None when offline."""
        with self._state:
            levels = self.strokes.levels
            if not self._connected or levels is None:
                return None
            return levels[0], levels[1]

    #: Every stroke ends with a REPORT: the device's STROKE report held against the stroke's frames
    #: (a device without reports is refused at the handshake: REQUIRED_CAPS).
    reports_strokes = True

    @property
    def report_wait_ns(self) -> int:  # type: ignore[override]
        """How long past a stroke's end (its arrival, or its timeout) the device's account of it
        may still be on its way: a report held for lost frames waits REPORT_WAIT_NS, and frames
        take the link's delivery latency besides."""
        return REPORT_WAIT_NS + 2 * self.delivery_latency_ns + self.reply_timeout_ns

    def limits(self) -> dict[str, int]:
        """What this device can do, for the daemon to refuse what it cannot before a stroke:
        the longest start delay (HELLO_ACK max_delay_us) and the stall limit's range."""
        dev = self.device
        out = {"min_stroke_timeout_ns": MIN_STROKE_TIMEOUT_NS, "max_stroke_timeout_ns": MAX_STROKE_TIMEOUT_NS}
        if dev is not None:
            out["max_delay_ns"] = dev.max_delay_us * 1000
        return out

    @property
    def last_start_late_ns(self) -> int | None:
        """How late the device fired the last start against its commanded instant."""
        return self.strokes.last_start_late_ns

    @property
    def connected(self) -> bool:
        """True between a good handshake and the next loss of the link."""
        return self._connected

    def counters(self) -> dict[str, int]:
        return {**super().counters(), **self.link_stats()}

    def link_stats(self) -> dict[str, int]:
        """The link's counters (errors, losses, recoveries, round trip)."""
        with self._state:
            s = self.stats
            s.framing_errors = self._decoder_totals[0] + self._decoder.framing_errors
            s.crc_errors = self._decoder_totals[1] + self._decoder.crc_errors
            s.format_errors = self._decoder_totals[2] + self._decoder.format_errors
            s.lost_frames = self._lost_total + self._rx_seq.lost
            s.seq_resets = self._resets_total + self._rx_seq.resets
            s.wraps = self.timeline.session_wraps + self.timeline.wraps_total
            s.halts_cleared = getattr(self.transport, "halts_cleared", 0)
            return s.as_dict()

    # -- sending -----------------------------------------------------------------------------
    def _send(self, msg: Message, waiter: _Waiter | None = None) -> int:
        with self._wlock:
            seq = self._tx_seq
            self._tx_seq = (seq + 1) % U16_MOD
            if waiter is not None:
                with self._state:
                    waiter.seqs.append(seq)
                    self._waiters[seq] = waiter
            self.transport.write(encode_frame(msg, seq))
        return seq

    def _request(self, msg: Message, what: str) -> Ack:
        """Send `msg` and wait for its ACK, retransmitting on silence; DaqError if none comes."""
        waiter = _Waiter(msg.TYPE)
        try:
            for attempt in range(self.retries):
                if not self._connected:
                    raise DaqDisconnected(f"{self.name}: {what}: link down ({self.transport.describe()})")
                if attempt:
                    self.stats.retransmits += 1
                try:
                    self._send(msg, waiter)
                except TransportLost as exc:
                    raise self._write_lost(exc) from exc
                if waiter.done.wait(self.reply_timeout_ns / 1e9):
                    break
                self.stats.reply_timeouts += 1
            else:
                raise DaqError(
                    f"{self.name}: no ACK to {what} after {self.retries} tries of "
                    f"{self.reply_timeout_ns // 1_000_000} ms ({self.transport.describe()})"
                )
        finally:
            with self._state:
                for s in waiter.seqs:
                    self._waiters.pop(s, None)
        if waiter.ack is None:
            raise DaqDisconnected(f"{self.name}: {what}: {waiter.lost}")
        return waiter.ack

    # -- the mechanism -----------------------------------------------------------------------
    def _arm(self, direction: Direction, delay_ns: int) -> None:
        if not self._connected:
            raise DaqDisconnected(f"{self.name}: arm: link down ({self.transport.describe()})")
        delay_us = (delay_ns + 500) // 1000
        dev = self.device
        if dev is not None and delay_us > dev.max_delay_us:
            # The device would refuse it (BAD_ARG): a driver error the loop handles, never a crash.
            raise DaqError(
                f"{self.name}: a delay of {fmt_ns(delay_ns)} is longer than the device's longest,"
                f" {fmt_ns(dev.max_delay_us * 1000)}"
            )
        self._stroke_id = (self._stroke_id + 1) % U16_MOD
        msg = Arm(self._stroke_id, int(direction), delay_us, self.stroke_timeout_ns // 1000)
        self._armed_msg = msg
        self._forget_arm()
        # No wait here: arming costs the loop one write. The ACK is checked by the COMMAND.
        waiter = _Waiter(MsgType.ARM)
        self._arm_waiter = waiter
        try:
            self._send(msg, waiter)
        except TransportLost as exc:
            raise self._write_lost(exc) from exc

    def _forget_arm(self) -> None:
        waiter, self._arm_waiter = self._arm_waiter, None
        if waiter is not None:
            with self._state:
                for s in waiter.seqs:
                    self._waiters.pop(s, None)

    def _rearm(self, arm: Arm) -> None:
        """The COMMAND found nothing armed: the ARM's own ACK (the device answers in order, so it
        is in by now if it was sent) says why. A refusal names the device's limits; a lost ARM or
        ACK, or BUSY (armed while the device was still in the last stroke, its arrival on the wire
        not its own), is armed again and must be taken."""
        waiter = self._arm_waiter
        ack = waiter.ack if waiter is not None else None
        self._forget_arm()
        if ack is None or ack.status in (Status.OK, Status.BUSY):
            if ack is None:
                self.stats.reply_timeouts += 1
            self.stats.retransmits += 1
            ack = self._request(arm, f"ARM stroke {arm.stroke}")
        if ack.status != Status.OK:
            self._armed_msg = None
            raise DaqError(
                f"{self.name}: device refused ARM stroke {arm.stroke}: {_status_name(ack.status)}"
                f" (delay {fmt_ns(arm.delay_us * 1000)}, its longest"
                f" {fmt_ns(self.device.max_delay_us * 1000) if self.device else 'unknown'};"
                f" stall limit {fmt_ns(arm.timeout_us * 1000)}, its range"
                f" {fmt_ns(MIN_STROKE_TIMEOUT_NS)} to {fmt_ns(MAX_STROKE_TIMEOUT_NS)})"
            )

    def _command(self, t_cmd_ns: int | None) -> int:
        arm = self._armed_msg
        if arm is None:
            raise DaqError(f"{self.name}: command without an armed stroke")
        if t_cmd_ns is None:
            cmd = Command(arm.stroke, 0, 0)
        else:
            check_ns("t_cmd_ns", t_cmd_ns)
            cmd = Command(arm.stroke, self.timeline.to_raw_us(t_cmd_ns), 1)
        with self._state:
            self.strokes.begin(arm.stroke, Direction(arm.direction))
            ctx = self.strokes.ctx
            assert ctx is not None
            if t_cmd_ns is not None:
                ctx.due_ns = t_cmd_ns + arm.delay_us * 1000
        t_sent = self._host_stamp()
        try:
            ack = self._request(cmd, f"COMMAND stroke {arm.stroke}")
        except DaqDisconnected:
            raise
        except DaqError as exc:
            # Every ACK lost: the device may well have the command. Its own frames say whether it
            # started (the loop follows them to the stroke's end, and past it names the link).
            self.stats.unacked_commands += 1
            self._armed_msg = None
            log.warning("%s: %s: following the stroke's own frames", self.name, exc)
            return t_sent if t_cmd_ns is None else t_cmd_ns
        if ack.status == Status.NOT_ARMED:
            self._rearm(arm)
            ack = self._request(cmd, f"COMMAND stroke {arm.stroke}")
        waiter = self._arm_waiter
        arm_ack = waiter.ack if waiter is not None else None
        self._forget_arm()  # a COMMAND taken proves its ARM was
        if ack.status == Status.OK and arm_ack is not None and arm_ack.status != Status.OK:
            with self._state:  # the device contradicts itself: its account of this stroke is in doubt
                ctx = self.strokes.ctx
                if ctx is not None and ctx.stroke == arm.stroke:
                    ctx.doubts.append(
                        f"its ARM was answered {_status_name(arm_ack.status)}, its COMMAND taken"
                    )
        if ack.status != Status.OK:
            with self._state:
                self.strokes.ctx = None
            raise DaqError(
                f"{self.name}: device refused COMMAND stroke {arm.stroke}: {_status_name(ack.status)}"
            )
        self._armed_msg = None
        with self._state:
            if t_cmd_ns is not None:
                if ack.t_us != cmd.t_cmd_us:  # the device must keep the instant it was given
                    self.stats.bad_stamps += 1
                    log.warning(
                        "%s: ACK of COMMAND says instant %d us, it was %d us",
                        self.name,
                        ack.t_us,
                        cmd.t_cmd_us,
                    )
                return t_cmd_ns
            t = self.timeline.stamp(ack.t_us, "ACK of COMMAND")
            t = self._host_stamp() if t is None else t
            ctx = self.strokes.ctx
            if ctx is not None and ctx.stroke == arm.stroke:
                ctx.due_ns = t + arm.delay_us * 1000
            return t

    def _stop(self) -> None:
        self._armed_msg = None
        self._forget_arm()
        if not self._connected:
            return  # no link: the device's watchdog has stopped or will stop the drive
        try:
            ack = self._request(Stop(int(StopReason.HOST)), "STOP")
        except DaqError as exc:
            log.warning("%s: stop not acknowledged: %s", self.name, exc)
            return
        if ack.status != Status.OK:
            log.warning("%s: device refused STOP: %s", self.name, _status_name(ack.status))

    def _recv_internal(self, deadline_ns: int | None) -> Event | None:
        with self._state:
            while not self._events:
                if self._closing or not self.is_open:
                    return None
                if deadline_ns is None:
                    self._state.wait(0.1)
                    continue
                left = deadline_ns - self.clock.now_ns()
                if left <= 0:
                    return None
                self._state.wait(left / 1e9)
            return self._events.popleft()

    # -- the link thread ---------------------------------------------------------------------
    def _run(self) -> None:
        backoff = self.reconnect_min_ns
        while not self._closing:
            if not self._connected:
                if self._reconnect_once():
                    backoff = self.reconnect_min_ns
                    continue
                self._sleep(backoff)
                backoff = min(2 * backoff, self.reconnect_max_ns)
                continue
            try:
                self._service()
            except TransportLost as exc:
                self._link_failed(str(exc))
            except Exception as exc:  # a bug must not kill the link silently: log, drop the link, reconnect
                log.exception("%s: link thread error", self.name)
                self._link_failed(f"link thread error: {exc!r}")

    def _sleep(self, dt_ns: int) -> None:
        with self._state:
            if not self._closing:
                self._state.wait(dt_ns / 1e9)

    def _service(self) -> None:
        now = time.monotonic_ns()
        timeout = max(0, min(self._next_ping_ns - now, _READ_SLICE_NS))
        data = self.transport.read(timeout)
        now = time.monotonic_ns()
        if data:
            frames = self._decoder.feed(data)
            if frames:
                self._last_rx_ns = now
            with self._state:
                for seq, msg in frames:
                    self._handle(seq, msg, now)
            self._send_report_ping()
            if self._refuse_why:
                why, self._refuse_why = self._refuse_why, ""
                self._link_failed(why)
                return
            if self._resync_why:
                why, self._resync_why = self._resync_why, ""
                self._resync(why)
                return
        if now >= self._next_ping_ns:
            self._next_ping_ns = now + self.heartbeat_ns
            self._ping_token = (self._ping_token + 1) % U32_MOD
            with self._state:
                self._pings[self._ping_token] = now
                if len(self._pings) > 16:
                    self._pings.pop(next(iter(self._pings)))
            self._send(Ping(self._ping_token))
        with self._state:
            self.strokes.poll(now)
            check = self._report_check
            if check is not None and now - check[2] > self.reply_timeout_ns:
                self._report_check = None
                self._finish_report(check[1], "no PONG came to check the device clock at the stroke's end")
        if now - self._last_rx_ns > self.link_timeout_ns:
            self.stats.silences += 1
            self._link_failed(f"device silent for {(now - self._last_rx_ns) // 1_000_000} ms")

    def _resync(self, why: str) -> None:
        """The device left the session (it restarted, or tripped its watchdog): the stroke in
        progress is over; handshake again on the open link (TransportLost: the link is dropped)."""
        with self._state:
            self._connected = False
            for w in self._waiters.values():
                w.lost = f"device lost the session: {why}"
                w.done.set()
            self._waiters.clear()
            self.strokes.close(why)
            self._state.notify_all()
        log.warning("%s: %s: handshaking again", self.name, why)
        self.stats.resyncs += 1  # before: the handshake delivers the reset's FAULT, a reader sees it
        self._handshake()
        arm = self._armed_msg
        if arm is not None:
            self._send(arm)  # the device forgot it

    def _reconnect_once(self) -> bool:
        try:
            self.transport.close()
            self.transport.open()
            self._handshake(reconnect=True)  # counts the reconnect
        except DaqError as exc:
            self.transport.close()
            log.debug("%s: reconnect to %s failed: %s", self.name, self.transport.describe(), exc)
            return False
        log.warning("%s: reconnected to %s", self.name, self.transport.describe())
        arm = self._armed_msg
        if arm is not None:
            try:
                self._send(arm)  # the device forgot it at the HELLO
            except TransportLost as exc:
                self._link_failed(f"write failed: {exc}")
        return True

    def _write_lost(self, exc: TransportLost) -> DaqDisconnected:
        """Drop the link after a write failed; the error for the caller to raise says the link was
        lost (the bare OS error, such as EBADF from a port closed under the write, does not)."""
        self._link_failed(f"write failed: {exc}")
        return DaqDisconnected(f"{self.name}: link lost: write failed: {exc}")

    def _link_failed(self, why: str) -> None:
        if self._mark_lost(why, report=True):
            self.stats.disconnects += 1
            log.warning("%s: link to %s lost: %s", self.name, self.transport.describe(), why)

    def _mark_lost(self, why: str, *, report: bool) -> bool:
        """Drop the link: wake waiters, close the stroke as stopped, report DISCONNECT once."""
        with self._state:
            was = self._connected
            self._connected = False
            for w in self._waiters.values():
                w.lost = f"link lost: {why}"
                w.done.set()
            self._waiters.clear()
            if was and report:
                ctx = self.strokes.ctx
                if ctx is not None:
                    self.strokes.flush(ctx)
                    if not ctx.stopped:
                        self._deliver(Event.stop(self._host_stamp(), ctx.direction, detail="disconnect"))
                self.strokes.ctx = None
                self._deliver(
                    Event.fault_event(
                        self._host_stamp(), FaultCode.DISCONNECT, _with_where(self.transport.describe(), why)
                    )
                )
            self._state.notify_all()
        if was:
            self.transport.close()
        return was

    # -- incoming frames (link thread, under self._state) --------------------------------------
    def _handle(self, seq: int, msg: Message, now: int) -> None:
        gap = self._rx_seq.check(seq)
        if gap:
            ctx = self.strokes.ctx
            if ctx is not None:
                self.strokes.hold(ctx, now)
            log.info("%s: %d frame(s) lost before seq %d", self.name, gap, seq)
        if isinstance(msg, Ack):
            w = self._waiters.get(msg.acked_seq)
            if w is not None and w.mtype == msg.acked_type and w.ack is None:
                w.ack = msg
                w.done.set()
        elif isinstance(msg, Pong):
            t_send = self._pings.pop(msg.token, None)
            check = self._report_check
            if t_send is not None and check is not None and check[0] == msg.token:
                self._report_check = None
                doubt = self.timeline.check(msg.t_us, t_send, now)
                self._finish_report(check[1], doubt)
            if t_send is not None:
                action, why = self.timeline.sample(msg.t_us, t_send, now)
                if action == "refuse" and not self._refuse_why:
                    self._refuse_why = why
                elif action == "resync" and not self._resync_why:
                    self._resync_why = why
            # The device counts since the HELLO: add the sessions before this one.
            st = StateFlags(msg.state)
            self.strokes.on_pong_levels(
                int(StateFlags.SENSOR_A in st), int(StateFlags.SENSOR_B in st), msg.t_us
            )
            if StateFlags.SYNCED in st:
                self.timeline.heard = (msg.t_us, now)  # this session's device clock, for the next handshake
            elif not self._resync_why:
                self._resync_why = "the device says it is not in a session (PONG)"
            self.stats.device_rx_errors = self._dev_errors_base[0] + msg.rx_errors
            self.stats.device_rx_lost = self._dev_errors_base[1] + msg.rx_lost
        elif isinstance(msg, Edge):
            self.strokes.on_edge(msg)
        elif isinstance(msg, Start):
            self.strokes.on_start(msg)
        elif isinstance(msg, Stopped):
            self.strokes.on_stopped(msg)
        elif isinstance(msg, Stroke):
            self.strokes.on_stroke(msg)
        elif isinstance(msg, Fault):
            self.strokes.on_fault(msg)
        elif isinstance(msg, Boot):
            self._on_boot(msg)
        # HELLO_ACK outside a handshake and host-bound types from a confused peer are ignored.

    def _check_clock_then_report(self, report: StrokeReport) -> None:
        """A stroke's report (link thread, under the state lock): a PING as soon as the frames in
        hand are handled, and the report goes to the loop with its PONG, which checks the device
        clock at the stroke's end. (Not sent here: a write takes the write lock, which a caller's
        request holds while it takes the state lock; the other order deadlocked.)"""
        old = self._report_check
        if old is not None:
            self._finish_report(old[1], "")  # a report overtaken: its stroke's clock was checked before
        self._ping_token = (self._ping_token + 1) % U32_MOD
        self._report_check = (self._ping_token, report, time.monotonic_ns())
        self._report_ping = self._ping_token

    def _send_report_ping(self) -> None:
        """The PING a stroke's report waits for (link thread, outside the state lock)."""
        with self._state:
            token, self._report_ping = self._report_ping, None
            if token is None:
                return
            self._pings[token] = time.monotonic_ns()
        try:
            self._send(Ping(token))
        except TransportLost:
            with self._state:
                check, self._report_check = self._report_check, None
                if check is not None:
                    self._finish_report(check[1], "")  # the link's loss ends the stroke its own way

    def _finish_report(self, report: StrokeReport, doubt: str) -> None:
        if doubt:
            self.stats.clock_doubts += 1
            detail = f"{report.detail}; {doubt}" if report.detail else doubt
            report = dataclasses.replace(report, detail=detail)
        self.strokes.deliver_report(report)

    def _on_boot(self, msg: Boot) -> None:
        """The device has just started (1.1): whatever it was doing is gone. Reported at once
        (a hung firmware's stroke is then closed with its cause, not as a stall)."""
        self.stats.device_resets += 1
        self.stats.reset_cause = msg.reset_cause
        self._report_reset(msg.reset_cause, in_session=True)
        self._boot_reported = True
        self._resync_why = f"it restarted ({reset_text(msg.reset_cause)})"

    def _host_stamp(self) -> int:
        return max(self.clock.now_ns(), self._last_stamp_ns)

    def _drop_oldest(self, events: deque[Event]) -> Event:
        """Drop the oldest edge (what floods are made of), else the oldest event: a fault, a start
        or a stop near the head outlives the chatter behind it. Returns the one dropped."""
        self.stats.events_dropped += 1
        for i in range(min(len(events), 64)):
            if events[i].kind is EventKind.EDGE:
                ev = events[i]
                del events[i]
                return ev
        return events.popleft()

    def _deliver(self, ev: Event) -> None:
        self._last_stamp_ns = max(self._last_stamp_ns, ev.t_ns)
        events = self._events
        if len(events) >= self.max_queued_events:
            # Nobody reads as fast as the device talks: the oldest go, counted. A stroke in progress
            # that lost one of its own has lost its account: a SEQUENCE fault (at the queue's end)
            # ends it, once per spell. One stamped before the stroke's due start is not its own:
            # a flood between two strokes, still decoded as the next is commanded, faulted that one.
            lost = self._drop_oldest(events)
            ctx = self.strokes.ctx
            if (
                ctx is not None
                and not ctx.stopped
                and not self._overflow_said
                and (ctx.due_ns is None or lost.t_ns >= ctx.due_ns)
            ):
                self._overflow_said = True
                self._drop_oldest(events)
                events.append(
                    Event.fault_event(
                        max(self.clock.now_ns(), self._last_stamp_ns),
                        FaultCode.SEQUENCE,
                        f"events lost: the driver's queue of {self.max_queued_events} was full"
                        f" during stroke {ctx.stroke}",
                    )
                )
            if self.stats.events_dropped % 10_000 == 1:
                log.warning(
                    "%s: event queue full: the oldest dropped (%d so far)",
                    self.name,
                    self.stats.events_dropped,
                )
        elif not events:
            self._overflow_said = False
        events.append(ev)
        self._state.notify_all()


def _status_name(status: int) -> str:
    return Status(status).name if status in Status._value2member_map_ else f"status {status}"


def _with_where(where: str, why: str) -> str:
    return why if where in why else f"{where}: {why}"
