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

The driver's clock is the device's timeline mapped onto the host: device stamps (32-bit us,
unwrapped) become `base_ns + (us - base_us) * 1000`, where the base is fixed at each handshake so
the timeline starts near `time.monotonic_ns()` and never goes back across reconnects; `now_ns()` is
`time.monotonic_ns() + offset_ns`, the offset re-estimated from each heartbeat round trip (the
sample with the smallest round trip of the last eight), which tracks the crystals' drift.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field

from .daq import DEFAULT_DEBOUNCE_NS, Daq, DaqDisconnected, DaqError, check_ns
from .events import Channel, Direction, Event, EventKind, FaultCode
from .mcu_link import DeviceClock, LinkStats, Transport, TransportLost
from .mcu_protocol import (
    PROTOCOL_MAJOR,
    PROTOCOL_MINOR,
    REQUIRED_CAPS,
    U16_MOD,
    U32_MOD,
    Ack,
    Arm,
    Boot,
    Caps,
    Command,
    DeviceFault,
    Edge,
    Fault,
    FrameDecoder,
    Hello,
    HelloAck,
    Message,
    MsgType,
    Ping,
    Pong,
    ResetCause,
    SeqTracker,
    Start,
    StateFlags,
    Status,
    Stop,
    Stopped,
    StopReason,
    Stroke,
    StrokeFlags,
    encode_frame,
)

log = logging.getLogger(__name__)

DEFAULT_HEARTBEAT_NS = 100_000_000
DEFAULT_LINK_TIMEOUT_NS = 400_000_000
DEFAULT_WATCHDOG_MS = 500
DEFAULT_REPLY_TIMEOUT_NS = 25_000_000
DEFAULT_RETRIES = 3
DEFAULT_STROKE_TIMEOUT_NS = 100_000_000
DEFAULT_RECONNECT_MIN_NS = 50_000_000
DEFAULT_RECONNECT_MAX_NS = 2_000_000_000
# A stroke whose frames went missing waits this long for its STROKE report before it is given up.
REPORT_WAIT_NS = 150_000_000
_READ_SLICE_NS = 10_000_000
_OFFSET_WINDOW = 8
# A device whose clock at a new handshake is this far from where the last session's clock would
# be now (plus twice the worst round trip seen, and 1000 ppm of the time between) has restarted
# since: a restart less than this after the one before is told by its BOOT alone.
_CLOCK_CONTINUITY_NS = 10_000_000
#: A device stamp is believed only inside this band around the device clock as the heartbeat tracks
#: it (plus the clock's uncertainty, half the round trip of its best sample): a frame is stamped
#: before it is sent, so never much ahead; and it arrives within the link timeout, so never much
#: behind (a STROKE report's stamps may be as old as the stroke timeout besides).
STAMP_AHEAD_NS = 5_000_000
#: Events queued between the link thread and the loop: beyond it the oldest are dropped, counted
#: (`events_dropped`), and a stroke in progress ends with a FAULT SEQUENCE saying so.
MAX_QUEUED_EVENTS = 8192
#: How far the device's clock may run from 1 us per us (a crystal is within 0.01 %, a ceramic
#: resonator 0.5 %); judged over heartbeats, past their round trips.
MAX_CLOCK_RATE_ERROR_PPM = 5_000
#: A sample whose round trip is longer than this is too coarse to judge the clock rate against.
_RATE_REF_RTT_NS = 10_000_000


@dataclass
class _Waiter:
    """A request waiting for its ACK; any of its retransmissions' ACKs completes it."""

    mtype: MsgType
    seqs: list[int] = field(default_factory=list)
    done: threading.Event = field(default_factory=threading.Event)
    ack: Ack | None = None
    lost: str = ""


@dataclass
class _StrokeCtx:
    """What the host has delivered of the stroke in progress, to rebuild it if frames go missing."""

    stroke: int
    direction: Direction
    started: bool = False
    departed: bool = False
    arrived: bool = False
    stopped: bool = False
    reported: bool = False
    #: Why a START for this stroke was rejected (another stroke's id, its stamp), "" if none was.
    start_rejected: str = ""
    gap: bool = False
    hold_until_ns: int = 0
    held: list[Event] = field(default_factory=list)


class McuDaq(Daq):
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
        self.stroke_timeout_ns = check_ns("stroke_timeout_ns", stroke_timeout_ns, minimum=1_000_000)
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
        #: How late the device fired the last start against its scheduled instant (START late_us).
        self.last_start_late_ns: int | None = None
        # Sensor levels (A, B) as the device last told them (PONG snapshot, then each EDGE).
        self._levels: list[int] | None = None

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
        self._session_wraps = 0
        self._clock_basis = (0, 0)  # (round trip, host instant) of the sample the clock stands on
        self._clock_jumps = 0
        self._rate_ref: tuple[int, int, int] | None = None
        self._rate_off = 0
        self._rate_refusal = ""  # the device's clock rate was refused: its next handshakes are too
        self._refuse_why = ""  # set by the link thread: drop the link, saying why
        self._bad_stamp_said_ns = -1_000_000_000
        self._overflow_said = False
        self._base_us = 0
        self._base_ns = 0
        self._last_stamp_ns = 0
        self._stroke_id = 0
        self._armed_msg: Arm | None = None
        self._ctx: _StrokeCtx | None = None
        self._pings: dict[int, int] = {}
        self._ping_token = 0
        self._offsets: deque[tuple[int, int, int]] = deque(maxlen=_OFFSET_WINDOW)
        self._last_rx_ns = 0
        self._next_ping_ns = 0
        self._dev_errors_base = (0, 0)
        # Counters of past sessions (each handshake starts a fresh decoder, tracker and unwrapper).
        self._decoder_totals = (0, 0, 0)
        self._lost_total = 0
        self._resets_total = 0
        self._wraps_total = 0
        # The device clock as last heard (raw us, host monotonic ns), to tell a restart at handshake.
        self._dev_heard: tuple[int, int] | None = None
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
            if not self._connected or self._levels is None:
                return None
            return self._levels[0], self._levels[1]

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
            s.wraps = self._session_wraps + self._wraps_total
            s.halts_cleared = getattr(self.transport, "halts_cleared", 0)
            return s.as_dict()

    # -- the clock ---------------------------------------------------------------------------
    def _dev_us(self, raw_us: int) -> int:
        """The unwrapped count of a raw 32-bit stamp: the one nearest the device clock now, as the
        heartbeat tracks it. Stateless: no frame moves a reference that later frames are read by."""
        now_us = self._base_us + (self.clock.now_ns() - self._base_ns) // 1000
        d = (raw_us - now_us) % U32_MOD
        if d >= U32_MOD // 2:
            d -= U32_MOD
        return now_us + d

    def _dev_ns(self, raw_us: int) -> int:
        return self._base_ns + (self._dev_us(raw_us) - self._base_us) * 1000

    def _to_raw_us(self, t_ns: int) -> int:
        return (self._base_us + (t_ns - self._base_ns) // 1000) % U32_MOD

    def _clock_err_ns(self, now_ns: int) -> int:
        """How far the driver's clock may be from the device's: half the round trip of the sample
        it stands on, and what the worst tolerated crystal drifts since."""
        rtt, t_ns = self._clock_basis
        return rtt // 2 + max(0, now_ns - t_ns) * MAX_CLOCK_RATE_ERROR_PPM // 1_000_000

    def _stamp(self, raw_us: int, what: str, behind_ns: int | None = None) -> int | None:
        """A device stamp on the driver's clock, or None when it is not believable: further ahead of
        the device clock than its uncertainty and STAMP_AHEAD_NS, or further behind than the link
        timeout (`behind_ns`). A rejected stamp is counted and logged (once a second), and leaves
        nothing behind."""
        host_now = time.monotonic_ns()
        now = host_now + self.clock.offset_ns
        t = self._dev_ns(raw_us)
        err = self._clock_err_ns(host_now)
        behind = self.link_timeout_ns if behind_ns is None else behind_ns
        if now - behind - err <= t <= now + err + STAMP_AHEAD_NS:
            u = self._dev_us(raw_us)
            if u // U32_MOD > self._session_wraps:
                self._session_wraps = u // U32_MOD
            return t
        self.stats.bad_stamps += 1
        off = t - now
        if host_now - self._bad_stamp_said_ns >= 1_000_000_000:
            self._bad_stamp_said_ns = host_now
            log.warning(
                "%s: %s stamped %s %s the device clock rejected (%d so far)",
                self.name,
                what,
                _fmt_ns(abs(off)),
                "ahead of" if off > 0 else "behind",
                self.stats.bad_stamps,
            )
        return None

    def _anchor(self, raw_us: int, host_mid_ns: int, rtt_ns: int) -> None:
        """Start a device session's timeline at `host_mid_ns` on the driver clock, never going back."""
        self._wraps_total += self._session_wraps
        self._session_wraps = 0
        self._base_us = raw_us
        self._base_ns = max(host_mid_ns + self.clock.offset_ns, self._last_stamp_ns + 1)
        self.clock.offset_ns = self._base_ns - host_mid_ns
        self._clock_basis = (rtt_ns, host_mid_ns)
        self._offsets.clear()
        self._clock_jumps = 0
        self._rate_off = 0
        # The rate is judged against a precise sample of this session (the handshake's, if quick).
        self._rate_ref = (host_mid_ns, self._base_ns, rtt_ns) if rtt_ns <= _RATE_REF_RTT_NS else None

    def _clock_sample(self, raw_us: int, t_send_ns: int, t_recv_ns: int) -> None:
        """A PONG: the device clock at the round trip's middle. A sample that disagrees with the
        clock by more than the two can explain is one bad frame: counted, not taken (three in a
        row: the device's clock jumped, and the session is handshaken again). The device's clock
        rate is judged against the session's first precise sample; off by more than
        MAX_CLOCK_RATE_ERROR_PPM three times in a row, the session is refused."""
        rtt = t_recv_ns - t_send_ns
        mid = (t_send_ns + t_recv_ns) // 2
        dev = self._dev_ns(raw_us)
        off = dev - mid
        ref = self._rate_ref
        if ref is not None and mid - ref[0] >= self.heartbeat_ns // 2:
            span = mid - ref[0]
            ppm = ((dev - ref[1]) - span) * 1_000_000 // span
            slack_ppm = (ref[2] + rtt) * 1_000_000 // span
            if abs(ppm) > MAX_CLOCK_RATE_ERROR_PPM + slack_ppm:
                self._rate_off += 1
                if self._rate_off >= 3 and not self._refuse_why:
                    rate = (dev - ref[1]) / span
                    self._rate_refusal = (
                        f"the device clock runs at {rate:.6f} us per us ({ppm / 10_000:+.3f} %), more than"
                        f" {MAX_CLOCK_RATE_ERROR_PPM / 10_000:.1f} % off: the host cannot time strokes on it"
                        " (a wrong timer prescaler or clock source?)"
                    )
                    self._refuse_why = self._rate_refusal
                    return
            else:
                self._rate_off = 0
        jump = abs(off - self.clock.offset_ns)
        if jump > self._clock_err_ns(t_recv_ns) + rtt // 2 + STAMP_AHEAD_NS:
            self.stats.bad_stamps += 1
            self._clock_jumps += 1
            log.warning(
                "%s: PONG stamped %s off the device clock not taken",
                self.name,
                _fmt_ns(off - self.clock.offset_ns),
            )
            if self._clock_jumps >= 3 and not self._resync_why:
                self._resync_why = f"its clock jumped by {_fmt_ns(off - self.clock.offset_ns)}"
            return
        self._clock_jumps = 0
        self.stats.last_rtt_ns = rtt
        self.stats.max_rtt_ns = max(self.stats.max_rtt_ns, rtt)
        if ref is None and rtt <= _RATE_REF_RTT_NS:
            self._rate_ref = (mid, dev, rtt)
        u = self._dev_us(raw_us)
        self._session_wraps = max(self._session_wraps, u // U32_MOD)
        self._offsets.append((rtt, off, mid))
        best = min(self._offsets)
        self.clock.offset_ns = best[1]
        self._clock_basis = (best[0], best[2])

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
                f"{self.name}: a delay of {_fmt_ns(delay_ns)} is longer than the device's longest,"
                f" {_fmt_ns(dev.max_delay_us * 1000)}"
            )
        self._stroke_id = (self._stroke_id + 1) % U16_MOD
        msg = Arm(self._stroke_id, int(direction), delay_us, self.stroke_timeout_ns // 1000)
        self._armed_msg = msg
        # No wait: the ACK is checked by the COMMAND, which re-arms if this frame was lost.
        try:
            self._send(msg)
        except TransportLost as exc:
            raise self._write_lost(exc) from exc

    def _command(self, t_cmd_ns: int | None) -> int:
        arm = self._armed_msg
        if arm is None:
            raise DaqError(f"{self.name}: command without an armed stroke")
        if t_cmd_ns is None:
            cmd = Command(arm.stroke, 0, 0)
        else:
            check_ns("t_cmd_ns", t_cmd_ns)
            cmd = Command(arm.stroke, self._to_raw_us(t_cmd_ns), 1)
        with self._state:
            self._ctx_new(arm.stroke, Direction(arm.direction))
        ack = self._request(cmd, f"COMMAND stroke {arm.stroke}")
        if ack.status == Status.NOT_ARMED:
            # The ARM frame was lost or refused silently: arm again and repeat the command.
            self._request(arm, f"ARM stroke {arm.stroke}")
            ack = self._request(cmd, f"COMMAND stroke {arm.stroke}")
        if ack.status != Status.OK:
            with self._state:
                self._ctx = None
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
            t = self._stamp(ack.t_us, "ACK of COMMAND")
            return self._host_stamp() if t is None else t

    def _stop(self) -> None:
        self._armed_msg = None
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

    # -- handshake ---------------------------------------------------------------------------
    def _handshake(self) -> None:
        """HELLO until HELLO_ACK: version and capability check, sequence reset, clock anchor.

        A device that is ready answers the first HELLO at once. When the transport may have reset
        the board (`reset_wait_ns`), that first HELLO waits up to reset_wait_ns for its answer
        while the host sends nothing more (the Mega 2560's bootloader stays in programming mode
        while bytes keep coming, and starts the firmware about a second after the last one);
        HELLO is then retried every 4 reply timeouts for as long again as the retries take, or
        1 s, whichever is longer.
        """
        self._keep_decoder_totals()
        with self._wlock:
            self._tx_seq = 0
        reply_ns = 4 * self.reply_timeout_ns
        reset_wait_ns = self.transport.reset_wait_ns
        tries = self.retries if not reset_wait_ns else 1 + max(self.retries, -(-1_000_000_000 // reply_ns))
        waited_ns = 0
        for attempt in range(tries):
            t_send = time.monotonic_ns()
            try:
                self.transport.write(b"\x00")  # ends any partial frame the device holds
                self._send(Hello(PROTOCOL_MAJOR, PROTOCOL_MINOR, self.watchdog_ms))
            except TransportLost:
                self.stats.handshake_failures += 1
                raise
            wait_ns = max(reply_ns, reset_wait_ns) if attempt == 0 else reply_ns
            waited_ns += wait_ns
            deadline = t_send + wait_ns
            while (now := time.monotonic_ns()) < deadline:
                data = self.transport.read(deadline - now)
                for seq, msg in self._decoder.feed(data):
                    if not isinstance(msg, HelloAck):
                        continue  # stale frames of the previous session
                    t_recv = time.monotonic_ns()
                    self._accept_hello(seq, msg, t_send, t_recv)
                    return
        self.stats.handshake_failures += 1
        raise TransportLost(
            f"{self.name}: handshake with {self.transport.describe()} failed: "
            f"no HELLO_ACK to {tries} HELLO within {waited_ns // 1_000_000} ms"
        )

    def _accept_hello(self, seq: int, msg: HelloAck, t_send: int, t_recv: int) -> None:
        if msg.major != PROTOCOL_MAJOR:
            self.stats.handshake_failures += 1
            raise DaqError(
                f"{self.name}: {self.transport.describe()} speaks protocol {msg.major}.{msg.minor}, "
                f"this host speaks {PROTOCOL_MAJOR}.{PROTOCOL_MINOR}: update the firmware or the daemon"
            )
        missing = REQUIRED_CAPS & ~Caps(msg.caps)
        if missing:
            self.stats.handshake_failures += 1
            raise DaqError(f"{self.name}: device lacks required capabilities: {missing!r}")
        if msg.max_delay_us * 1000 < self.max_delay_ns:
            self.stats.handshake_failures += 1
            raise DaqError(
                f"{self.name}: {self.transport.describe()} delays a start by at most"
                f" {_fmt_ns(msg.max_delay_us * 1000)} (HELLO_ACK max_delay_us {msg.max_delay_us}); this"
                f" host may ask for up to {_fmt_ns(self.max_delay_ns)} (its longest target)"
            )
        with self._state:
            restarted = self._note_restart(msg, t_recv)
            if self._rate_refusal:
                if not restarted:
                    self.stats.handshake_failures += 1
                    raise DaqError(f"{self.name}: {self.transport.describe()}: {self._rate_refusal}")
                self._rate_refusal = ""  # a new run of the device (new firmware?): judged afresh
            self.device = msg
            self._dev_heard = (msg.t_us, t_recv)
            self._keep_seq_totals()
            self._rx_seq = SeqTracker()
            self._rx_seq.reset((seq + 1) % U16_MOD)
            self._anchor(msg.t_us, (t_send + t_recv) // 2, t_recv - t_send)
            self._last_rx_ns = t_recv
            self._next_ping_ns = t_recv
            self._dev_errors_base = (self.stats.device_rx_errors, self.stats.device_rx_lost)
            self._levels = None  # until the first PONG of this session
            self._pings.clear()
            self._connected = True
        log.info(
            "%s: handshake with %s: protocol %d.%d, firmware 0x%04X, caps %s",
            self.name,
            self.transport.describe(),
            msg.major,
            msg.minor,
            msg.fw_version,
            Caps(msg.caps),
        )

    def _note_restart(self, msg: HelloAck, t_recv: int) -> bool:
        """At a handshake: has the device restarted since the last session (or was this the first)?
        A restart by its watchdog, not already reported by its BOOT, is reported now."""
        self.stats.reset_cause = msg.reset_cause
        if self._boot_reported:
            self._boot_reported = False  # its BOOT said so already
            return True
        heard = self._dev_heard
        if heard is not None:
            elapsed_ns = t_recv - heard[1]
            expected = (heard[0] + elapsed_ns // 1000) % U32_MOD
            off_ns = abs(((msg.t_us - expected + U32_MOD // 2) % U32_MOD - U32_MOD // 2) * 1000)
            slack_ns = _CLOCK_CONTINUITY_NS + 2 * self.stats.max_rtt_ns + elapsed_ns // 1000
            if off_ns <= slack_ns:
                return False  # the same run of the device (a reconnect): its cause is old news
        if heard is not None:
            self.stats.device_resets += 1
        self._report_reset(msg.reset_cause, in_session=False)
        return True

    def _report_reset(self, cause: int, *, in_session: bool) -> None:
        """A device restart as an event: FAULT DRIVE for its watchdog or a brown-out; any other
        (power, the reset pin) FAULT DISCONNECT when it ended a session, else (found at a handshake,
        after the link's own loss was reported, or the driver's first) only logged."""
        rc = ResetCause(cause & 0x1F)
        bad = ResetCause.WATCHDOG in rc or ResetCause.BROWN_OUT in rc
        if ResetCause.WATCHDOG in rc:
            self.stats.watchdog_resets += 1
        what = _reset_text(cause)
        if not in_session and not bad:
            log.info("%s: device started by %s", self.name, what)
            return
        log.warning("%s: device restarted by %s", self.name, what)
        code = FaultCode.DRIVE if bad else FaultCode.DISCONNECT
        self._deliver(Event.fault_event(self._host_stamp(), code, f"device reset by {what}"))

    def _keep_decoder_totals(self) -> None:
        d = self._decoder
        a, b, c = self._decoder_totals
        self._decoder_totals = (a + d.framing_errors, b + d.crc_errors, c + d.format_errors)
        self._decoder = FrameDecoder()

    def _keep_seq_totals(self) -> None:
        self._lost_total += self._rx_seq.lost
        self._resets_total += self._rx_seq.resets

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
            ctx = self._ctx
            if ctx is not None and ctx.gap and not ctx.reported and now >= ctx.hold_until_ns:
                self._give_up(ctx, "no STROKE report")
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
            ctx = self._ctx
            if ctx is not None:
                self._flush(ctx)
                if ctx.started and not ctx.stopped:
                    self._deliver(Event.stop(self._host_stamp(), ctx.direction, detail=why))
            self._ctx = None
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
            self._handshake()
        except DaqError as exc:
            self.transport.close()
            log.debug("%s: reconnect to %s failed: %s", self.name, self.transport.describe(), exc)
            return False
        self.stats.reconnects += 1
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
                ctx = self._ctx
                if ctx is not None:
                    self._flush(ctx)
                    if not ctx.stopped:
                        self._deliver(Event.stop(self._host_stamp(), ctx.direction, detail="disconnect"))
                self._ctx = None
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
            ctx = self._ctx
            if ctx is not None and not ctx.reported and not ctx.gap:
                ctx.gap = True
                ctx.hold_until_ns = now + REPORT_WAIT_NS
            log.info("%s: %d frame(s) lost before seq %d", self.name, gap, seq)
        if isinstance(msg, Ack):
            w = self._waiters.get(msg.acked_seq)
            if w is not None and w.mtype == msg.acked_type and w.ack is None:
                w.ack = msg
                w.done.set()
        elif isinstance(msg, Pong):
            t_send = self._pings.pop(msg.token, None)
            if t_send is not None:
                self._clock_sample(msg.t_us, t_send, now)
            # The device counts since the HELLO: add the sessions before this one.
            st = StateFlags(msg.state)
            self._levels = [int(StateFlags.SENSOR_A in st), int(StateFlags.SENSOR_B in st)]
            if StateFlags.SYNCED in st:
                self._dev_heard = (msg.t_us, now)  # this session's device clock, for the next handshake
            elif not self._resync_why:
                self._resync_why = "the device says it is not in a session (PONG)"
            self.stats.device_rx_errors = self._dev_errors_base[0] + msg.rx_errors
            self.stats.device_rx_lost = self._dev_errors_base[1] + msg.rx_lost
        elif isinstance(msg, Edge):
            self._on_edge(msg)
        elif isinstance(msg, Start):
            self._on_start(msg)
        elif isinstance(msg, Stopped):
            self._on_stopped(msg)
        elif isinstance(msg, Stroke):
            self._on_stroke(msg)
        elif isinstance(msg, Fault):
            self._on_fault(msg)
        elif isinstance(msg, Boot):
            self._on_boot(msg)
        # HELLO_ACK outside a handshake and host-bound types from a confused peer are ignored.

    def _on_edge(self, msg: Edge) -> None:
        if msg.channel > 1 or msg.level > 1:
            log.warning("%s: EDGE with channel %d level %d ignored", self.name, msg.channel, msg.level)
            return
        t = self._stamp(msg.t_us, f"EDGE of sensor {Channel(msg.channel).name}")
        if t is None:
            return
        ev = Event.edge(t, Channel(msg.channel), msg.level)
        if self._levels is not None:
            self._levels[msg.channel] = msg.level
        ctx = self._ctx
        if ctx is not None and not ctx.reported:
            if ev.channel is ctx.direction.source and ev.level == 0:
                ctx.departed = True
            elif ev.channel is ctx.direction.dest and ev.level == 1:
                ctx.arrived = True
            if ctx.gap:
                ctx.held.append(ev)
                return
        self._deliver(ev)

    def _on_start(self, msg: Start) -> None:
        direction = Direction(msg.direction) if msg.direction <= 1 else None
        if direction is None:
            log.warning("%s: START with direction %d ignored", self.name, msg.direction)
            return
        ctx = self._ctx
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
        if not why:
            t = self._stamp(msg.t_us, f"START of stroke {msg.stroke}")
            if t is None:
                why = f"its START stamped {self._off_text(msg.t_us)}"
        else:
            self.stats.foreign_starts += 1
            log.warning("%s: %s rejected", self.name, why)
        if t is None:
            # Not this stroke's start. Its own may still come, or its STROKE report rebuild it: the
            # stroke's events are held till then, delivered in order; else it ends with a SEQUENCE fault.
            if ctx is not None and not ctx.started and not ctx.reported:
                ctx.start_rejected = ctx.start_rejected or why
                if not ctx.gap:
                    ctx.gap = True
                    ctx.hold_until_ns = time.monotonic_ns() + REPORT_WAIT_NS
            return
        assert ctx is not None
        self.last_start_late_ns = msg.late_us * 1000
        detail = f"late {msg.late_us} us" if msg.late_us else ""
        ev = Event(EventKind.START, t, direction=direction, detail=detail, lateness_ns=msg.late_us * 1000)
        ctx.started = True
        if ctx.gap:
            ctx.held.append(ev)
        else:
            self._deliver(ev)

    def _off_text(self, raw_us: int) -> str:
        off = self._dev_ns(raw_us) - self.clock.now_ns()
        return f"{_fmt_ns(abs(off))} {'ahead of' if off > 0 else 'behind'} the device clock"

    def _on_stopped(self, msg: Stopped) -> None:
        ctx = self._ctx
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
        t = self._stamp(msg.t_us, "STOPPED")
        ev = Event.stop(self._host_stamp() if t is None else t, direction, detail=name)
        if ctx is not None and ctx.gap and not ctx.reported:
            ctx.held.append(ev)
            if direction is not None and ctx.start_rejected:
                # The device sends its STROKE report before STOPPED: none will come to rebuild it.
                self._give_up(ctx, "no STROKE report came before its STOPPED")
        else:
            self._deliver(ev)

    def _on_stroke(self, msg: Stroke) -> None:
        ctx = self._ctx
        if ctx is None or ctx.stroke != msg.stroke:
            return  # a report of a stroke this host session did not command
        ctx.reported = True
        flags = StrokeFlags(msg.flags)
        behind = self.link_timeout_ns + self.stroke_timeout_ns
        rebuilt: list[Event] = []
        if not ctx.started:
            t = self._stamp(msg.t_start_us, f"STROKE {msg.stroke} report's start", behind)
            if t is not None:
                rebuilt.append(Event.start(t, ctx.direction))
                ctx.started = True
        if StrokeFlags.DEPARTED in flags and not ctx.departed:
            t = self._stamp(msg.t_depart_us, f"STROKE {msg.stroke} report's departure", behind)
            if t is not None:
                rebuilt.append(Event.edge(t, ctx.direction.source, 0))
                ctx.departed = True
        if StrokeFlags.ARRIVED in flags and not ctx.arrived:
            t = self._stamp(msg.t_arrive_us, f"STROKE {msg.stroke} report's arrival", behind)
            if t is not None:
                rebuilt.append(Event.edge(t, ctx.direction.dest, 1))
                ctx.arrived = True
        if rebuilt:
            self.stats.recovered_strokes += 1
            log.info(
                "%s: stroke %d rebuilt from its report: %d event(s)", self.name, msg.stroke, len(rebuilt)
            )
        ctx.held.extend(rebuilt)
        self._flush(ctx)
        self._no_start(ctx, "nor did its STROKE report give one")

    def _no_start(self, ctx: _StrokeCtx, why: str) -> None:
        """A stroke whose START was rejected and never came good: a SEQUENCE fault ends it."""
        if ctx.started or not ctx.start_rejected:
            return
        ctx.started = True  # said once
        self.stats.unrecovered_strokes += 1
        self._deliver(
            Event.fault_event(
                self._host_stamp(),
                FaultCode.SEQUENCE,
                f"stroke {ctx.stroke} has no START of its own ({ctx.start_rejected} was rejected), {why}",
            )
        )

    def _on_fault(self, msg: Fault) -> None:
        t = self._stamp(msg.t_us, "FAULT")
        t = self._host_stamp() if t is None else t  # a fault is news whatever its stamp
        code = {
            DeviceFault.STALL: FaultCode.STALL,
            DeviceFault.HOST_SILENT: FaultCode.DISCONNECT,
            DeviceFault.SENSORS: FaultCode.SEQUENCE,
            DeviceFault.DRIVE: FaultCode.DRIVE,
        }.get(msg.code, FaultCode.DRIVE)
        what = (
            DeviceFault(msg.code).name if msg.code in DeviceFault._value2member_map_ else f"code {msg.code}"
        )
        ev = Event.fault_event(t, code, f"device: {what} (detail {msg.detail})")
        ctx = self._ctx
        if ctx is not None and ctx.gap and not ctx.reported:
            ctx.held.append(ev)
        else:
            self._deliver(ev)

    def _on_boot(self, msg: Boot) -> None:
        """The device has just started (1.1): whatever it was doing is gone. Reported at once
        (a hung firmware's stroke is then closed with its cause, not as a stall)."""
        self.stats.device_resets += 1
        self.stats.reset_cause = msg.reset_cause
        self._report_reset(msg.reset_cause, in_session=True)
        self._boot_reported = True
        self._resync_why = f"it restarted ({_reset_text(msg.reset_cause)})"

    # -- stroke bookkeeping (under self._state) ------------------------------------------------
    def _ctx_new(self, stroke: int, direction: Direction) -> None:
        old = self._ctx
        if old is not None and old.gap and not old.reported:
            self._give_up(old, f"stroke {stroke} commanded")
        self._ctx = _StrokeCtx(stroke, direction)

    def _give_up(self, ctx: _StrokeCtx, why: str) -> None:
        """Frames of `ctx` were lost and its report never came: deliver what there is, flag it."""
        ctx.reported = True
        self._flush(ctx)
        if not ctx.started and ctx.start_rejected:
            self._no_start(ctx, f"and {why}")
        elif not ctx.arrived:
            self.stats.unrecovered_strokes += 1
            self._deliver(
                Event.fault_event(
                    self._host_stamp(), FaultCode.WIRE, f"stroke {ctx.stroke}: frames lost and {why}"
                )
            )

    def _flush(self, ctx: _StrokeCtx) -> None:
        held = sorted(ctx.held, key=lambda e: e.t_ns)
        ctx.held = []
        ctx.gap = False
        for ev in held:
            self._deliver(ev)

    def _host_stamp(self) -> int:
        return max(self.clock.now_ns(), self._last_stamp_ns)

    def _drop_oldest(self, events: deque[Event]) -> None:
        """Drop the oldest edge (what floods are made of), else the oldest event: a fault, a start
        or a stop near the head outlives the chatter behind it."""
        self.stats.events_dropped += 1
        for i in range(min(len(events), 64)):
            if events[i].kind is EventKind.EDGE:
                del events[i]
                return
        events.popleft()

    def _deliver(self, ev: Event) -> None:
        self._last_stamp_ns = max(self._last_stamp_ns, ev.t_ns)
        events = self._events
        if len(events) >= self.max_queued_events:
            # Nobody reads as fast as the device talks: the oldest go, counted. A stroke in progress
            # has lost its events: a SEQUENCE fault (at the queue's end) ends it, once per spell.
            self._drop_oldest(events)
            ctx = self._ctx
            if ctx is not None and not ctx.stopped and not self._overflow_said:
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


def _reset_text(cause: int) -> str:
    """ "its watchdog (MCUSR 0x08)" and the like, for logs and fault details."""
    names = {
        ResetCause.WATCHDOG: "its hardware watchdog",
        ResetCause.BROWN_OUT: "a brown-out",
        ResetCause.EXTERNAL: "its reset pin",
        ResetCause.POWER_ON: "power-on",
        ResetCause.JTAG: "JTAG",
    }
    said = [text for bit, text in names.items() if cause & bit]
    return f"{' and '.join(said) or 'an unknown cause'} (MCUSR 0x{cause:02X})"


def _with_where(where: str, why: str) -> str:
    return why if where in why else f"{where}: {why}"


def _fmt_ns(ns: int) -> str:
    """Nanoseconds for people, as usmswitch.protocol.units.format_ns writes them: "12.000 ms", "95.3 us"."""
    sign = "-" if ns < 0 else ""
    mag = abs(ns)
    if mag < 1_000:
        return f"{sign}{mag} ns"
    if mag < 999_950:
        return f"{sign}{mag / 1e3:.1f} us"
    if mag < 999_999_500:
        return f"{sign}{mag / 1e6:.3f} ms"
    return f"{sign}{mag / 1e9:.6f} s"
