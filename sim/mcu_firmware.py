"""The emulated firmware of the rig's microcontroller, speaking docs/mcu-protocol.md over a byte stream.

`McuEmulator` is the firmware: it handshakes, arms, fires the start after the armed delay on its
own clock, stamps the limit-sensor edges of the rig (`mcu_rig.Mover` over `UsmSwitchModel`) in
real time, stops the drive on arrival, reports strokes, answers heartbeats and runs the host
watchdog. Its device clock is a free-running 32-bit microsecond counter that can start near the
wrap and drift by a few ppm, as a real crystal does. After each power-on it can sit in a
bootloader that loses the host's bytes for a while (`bootloader_ms`), as an Arduino's does.

It talks bytes through whatever link `attach`es it (`mcu_pty.PtyLink`, `mcu_usb.UsbDevice`).
Wire faults are injected on the device's transmit side: corrupt bytes, dropped frames, delayed
frames, silence, garbage; and on its receive side, lost frames; rig faults: a stall and a sensor
bounce; and a firmware hang, which its hardware watchdog ends with a reset (`inject_hang`).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from usmswitch.drivers.events import Channel, Direction
from usmswitch.drivers.mcu_protocol import (
    MAX_ENCODED,
    MAX_PAYLOAD,
    MESSAGES,
    PROTOCOL_MAJOR,
    PROTOCOL_MINOR,
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
    ProtocolError,
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
    cobs_decode,
    crc16,
    encode_frame,
)

from .mcu_rig import Mover
from .model import UsmSwitchModel

log = logging.getLogger(__name__)

ALL_CAPS = Caps.HW_DELAY | Caps.EDGE_STAMP | Caps.STROKE_REPORT | Caps.STOP_ON_ARRIVAL | Caps.WATCHDOG
FW_VERSION = 0x0102
# The firmware's hardware watchdog (WDTO_30MS: 32 ms at 5 V): a hung main loop resets the chip
# this long after its last pass.
WATCHDOG_RESET_NS = 32_000_000
MAX_DELAY_US = 1_000_000
# COMMAND's t_cmd_us must be within this of the device clock (else BAD_TIME).
MAX_COMMAND_SKEW_US = 1_000_000
_IDLE_WAIT_S = 0.05


@dataclass
class InjectedFaults:
    """How many of each injected fault the emulator actually applied."""

    corrupted: int = 0
    dropped: int = 0
    delayed: int = 0
    silenced: int = 0
    garbage: int = 0
    stalls: int = 0
    bounces: int = 0
    hangs: int = 0


@dataclass
class _Stroke:
    stroke: int
    direction: Direction
    delay_us: int
    timeout_us: int
    t_cmd_ns: int = 0  # host monotonic ns (the physical timeline)
    t_start_ns: int = 0
    t_depart_ns: int | None = None
    t_arrive_ns: int | None = None
    t_cmd_us: int = 0
    t_rx_ns: int = 0
    commanded: bool = False
    started: bool = False
    done: bool = False
    late: bool = False


@dataclass(frozen=True)
class UnknownFrame:
    """A valid frame (COBS, CRC) of a type this protocol version does not define: a newer minor
    version's message. The device answers it with ACK UNKNOWN_TYPE, as the firmware does."""

    TYPE: int
    body: bytes


class _DeviceDecoder:
    """The device's receiver: FrameDecoder's frames and counters, plus the valid frames of an
    unknown type, which FrameDecoder counts as errors but the protocol says to answer."""

    def __init__(self) -> None:
        self.decoder = FrameDecoder()
        self._buf = bytearray()

    @property
    def errors(self) -> int:
        return self.decoder.errors

    def feed(self, data: bytes) -> list[tuple[int, Message | UnknownFrame]]:
        out: list[tuple[int, Message | UnknownFrame]] = []
        self._buf += data
        while (z := self._buf.find(0)) >= 0:
            frame = bytes(self._buf[: z + 1])
            del self._buf[: z + 1]
            unknown = _unknown_frame(frame[:-1])
            if unknown is not None:
                out.append(unknown)
            else:
                out.extend(self.decoder.feed(frame))
        if len(self._buf) > MAX_ENCODED:  # no delimiter in sight: the decoder counts the overrun
            out.extend(self.decoder.feed(bytes(self._buf)))
            self._buf.clear()
        return out


def _unknown_frame(raw: bytes) -> tuple[int, UnknownFrame] | None:
    if not raw or len(raw) > MAX_ENCODED:
        return None
    try:
        payload = cobs_decode(raw)
    except ProtocolError:
        return None
    n = len(payload)
    if n < 5 or n > MAX_PAYLOAD or payload[0] in MESSAGES:
        return None
    if crc16(payload[:-2]) != int.from_bytes(payload[-2:], "little"):
        return None
    return int.from_bytes(payload[1:3], "little"), UnknownFrame(payload[0], payload[3:-2])


class McuEmulator:
    """The firmware: protocol state machine, device clock and the rig model, in real time."""

    def __init__(
        self,
        model: UsmSwitchModel | None = None,
        *,
        seed: int = 0,
        clock_start_us: int = 0,
        drift_ppm: int = 0,
        caps: Caps = ALL_CAPS,
        major: int = PROTOCOL_MAJOR,
        minor: int = PROTOCOL_MINOR,
        start_at: Channel = Channel.A,
        bootloader_ms: int = 0,
        max_delay_us: int = MAX_DELAY_US,
    ) -> None:
        """`bootloader_ms`: after each power-on (`power_cycle()`, as an Arduino's reset when its
        port opens) the firmware starts only once the line has been quiet that long: like the
        Mega 2560's stk500v2 bootloader, bytes meanwhile are lost and restart the wait."""
        if not 0 <= bootloader_ms <= 10_000:
            raise ValueError(f"bootloader_ms must be in 0..10000, got {bootloader_ms!r}")
        self.bootloader_ns = bootloader_ms * 1_000_000
        if not 0 <= clock_start_us < U32_MOD:
            raise ValueError(f"clock_start_us must be a 32-bit count, got {clock_start_us!r}")
        # A crystal is within 100 ppm; up to +-90 % emulates a wrong clock (the host must refuse it).
        if not -900_000 <= drift_ppm <= 9_000_000:
            raise ValueError(f"drift_ppm must be in -900000..9000000, got {drift_ppm!r}")
        if not 0 <= max_delay_us < U32_MOD:
            raise ValueError(f"max_delay_us must be a 32-bit count, got {max_delay_us!r}")
        #: The longest start delay it announces in HELLO_ACK and accepts in ARM.
        self.max_delay_us = max_delay_us
        self.model = model or UsmSwitchModel(seed=seed)
        self.clock_start_us = clock_start_us
        self.drift_ppm = drift_ppm
        self.caps = caps
        self.major = major
        self.minor = minor
        #: The mover and its limit sensors: where the drive takes it, when the edges come.
        self.rig = Mover(self.model, start_at)
        self.injected = InjectedFaults()
        self._lock = threading.RLock()
        # The host's bytes, each with the instant it reached the UART (stamped and queued together).
        self._rx: deque[tuple[int, bytes]] = deque()
        self._rx_lock = threading.Lock()
        self._wake = threading.Event()
        self._timers: list[tuple[int, int, Callable[[], None]]] = []
        self._tick = itertools.count()
        self._writer: Callable[[bytes], None] | None = None
        self._running = False
        self._thread: threading.Thread | None = None
        # fault injection (device transmit side)
        self._corrupt_next = 0
        self._drop_next = 0
        self._drop_only: MsgType | None = None
        self._corrupt_only: MsgType | None = None
        self._delay_next = 0
        self._delay_ns = 0
        self._silent_until_ns = 0
        self._out_busy_until_ns = 0
        self._rx_drop_next = 0
        self._batch: list[bytes] | None = None  # frames that leave in one write (_send_together)
        #: Every stroke that ended, in order, with its physical (host monotonic) stamps.
        self.log: list[_Stroke] = []
        #: Frames the firmware put on the wire (after injection), by type.
        self.sent: dict[MsgType, int] = {}
        #: Frames received from the host, by type.
        self.received: dict[MsgType, int] = {}
        #: Strokes started / arrived / stopped by the watchdog.
        self.strokes_started = 0
        self.strokes_arrived = 0
        self.watchdog_trips = 0
        self.boots = 0
        #: Resets by the hardware watchdog (after an injected hang).
        self.watchdog_resets = 0
        self.watchdog_reset_ns: int | None = None  # when the last one was due (host ns)
        self._hang_next = False
        self._hung = False
        self._boot(ResetCause.POWER_ON)

    # -- power and clock -----------------------------------------------------------------------
    def _boot(self, cause: ResetCause, t_ns: int | None = None) -> None:
        """A reset (`cause`) at `t_ns` (now if None): clock restarts at clock_start_us, no session,
        drive off; once out of the bootloader the firmware says BOOT with the cause, as it reports
        it in HELLO_ACK."""
        with self._lock:
            self.boots += 1
            self.reset_cause = cause
            self._hung = False
            # A watchdog reset's instant, not this thread's: bytes since are the new firmware's.
            self._t_boot_ns = time.monotonic_ns() if t_ns is None else t_ns
            self._bootloader_until_ns = self._t_boot_ns + self.bootloader_ns
            self.bootloader_bytes = 0
            self._decoder = _DeviceDecoder()
            self._rx_err_base = 0
            self._rx_seq = SeqTracker()
            self._tx_seq = 0
            self._synced = False
            self._session_minor = self.minor
            self._watchdog_ns = 0
            self._last_host_ns = self._t_boot_ns
            self._armed: _Stroke | None = None
            self._cur: _Stroke | None = None
            self._gen = 0  # bumps to cancel a stroke's pending timers
            self.rx_errors = 0
            self._timers.clear()
            if self.bootloader_ns == 0 and self._writer_attached():
                # The firmware says BOOT before it reads the UART: a host byte read in between
                # (a PING answered out of session) would come before it, as no chip does.
                self._announce(self._t_boot_ns)
            else:
                until = self._bootloader_until_ns
                self._at(until, lambda: self._announce(until))

    def _writer_attached(self) -> bool:
        return getattr(self, "_writer", None) is not None

    def _announce(self, t_ns: int) -> None:
        """Out of the bootloader at `t_ns`, unless bytes it lost since kept it waiting."""
        if t_ns < self._bootloader_until_ns:
            until = self._bootloader_until_ns
            self._at(until, lambda: self._announce(until))
            return
        self._send(Boot(int(self.reset_cause), FW_VERSION))

    def device_us(self, t_ns: int | None = None) -> int:
        """The raw 32-bit device clock at host monotonic instant `t_ns` (now if None)."""
        t = time.monotonic_ns() if t_ns is None else t_ns
        el = t - self._t_boot_ns
        el += el * self.drift_ppm // 1_000_000
        return (self.clock_start_us + el // 1000) % U32_MOD

    def _host_dur(self, dev_ns: int) -> int:
        """Host nanoseconds that the device's timer counts as `dev_ns` (its crystal drifts)."""
        return dev_ns * 1_000_000 // (1_000_000 + self.drift_ppm)

    def _host_ns(self, raw_us: int, now_ns: int) -> int:
        """Host instant of a raw device stamp near `now_ns` (for COMMAND's t_cmd_us)."""
        d = (raw_us - self.device_us(now_ns)) % U32_MOD
        if d >= U32_MOD // 2:
            d -= U32_MOD
        return now_ns + d * 1000

    # -- links -------------------------------------------------------------------------------
    def attach(self, writer: Callable[[bytes], None]) -> None:
        """Connect the transmit side to a link (the link calls `receive` with host bytes)."""
        with self._lock:
            self._writer = writer

    def detach(self) -> None:
        """The link is gone (cable out): frames are lost until the next attach."""
        with self._lock:
            self._writer = None

    def receive(self, data: bytes) -> None:
        """Bytes from the host (any thread), stamped as they arrive: the chip's UART has them then,
        whenever the firmware thread (late on a busy host) gets to them; it handles them at that
        instant, in order with what fell due before it."""
        with self._rx_lock:
            self._rx.append((time.monotonic_ns(), bytes(data)))
        self._wake.set()

    def catch_up(self) -> None:
        """Do now what the chip has done by now: the bytes received handled at their instants and
        the timers and the host watchdog due by now run, in time order. The firmware thread does
        this whenever it wakes; a harness that reads the device's state calls it rather than wait
        for that thread, which a busy host wakes late."""
        with self._lock:
            self._catch_up()

    def start(self) -> McuEmulator:
        """Run the firmware thread."""
        if not self._running:
            self._running = True
            self._thread = threading.Thread(target=self._run, name="mcu-emulator", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the firmware thread (drive off)."""
        self._running = False
        self._wake.set()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None
        with self._lock:
            self.rig.stop(time.monotonic_ns())

    def power_cycle(self) -> None:
        """Cut and restore power: everything the firmware knew is gone, the clock restarts."""
        with self._lock:
            self._catch_up()  # what came before the power went, the old session had
            self.rig.stop(time.monotonic_ns())
            self._boot(ResetCause.POWER_ON)
        self._wake.set()  # its BOOT is due now

    def inject_hang(self) -> None:
        """The next stroke hangs the firmware's main loop as it starts (a firmware bug): its START
        still goes out (the UART drains by interrupt) and its arrival still cuts the drive (the
        capture interrupt), but nothing else is sent or answered, and no timeout is checked, until
        the hardware watchdog resets the chip WATCHDOG_RESET_NS after the start."""
        with self._lock:
            self._hang_next = True

    # -- fault injection -----------------------------------------------------------------------
    def inject_corrupt(self, frames: int = 1, only: MsgType | None = None) -> None:
        """Flip a byte in each of the next `frames` frames sent (of type `only`, if given)."""
        with self._lock:
            self._corrupt_next += frames
            self._corrupt_only = only

    def inject_drop(self, frames: int = 1, only: MsgType | None = None) -> None:
        """Drop the next `frames` frames (of type `only`, if given): their sequence numbers are spent."""
        with self._lock:
            self._drop_next += frames
            self._drop_only = only

    def inject_delay(self, delay_ns: int, frames: int = 1) -> None:
        """Hold each of the next `frames` frames back by `delay_ns` (later frames queue behind them)."""
        with self._lock:
            self._delay_next += frames
            self._delay_ns = delay_ns

    def inject_silence(self, duration_ns: int) -> None:
        """Send nothing for `duration_ns` (a hung firmware): frames due meanwhile are lost."""
        with self._lock:
            self._silent_until_ns = time.monotonic_ns() + duration_ns
            self.injected.silenced += 1

    def inject_garbage(self, data: bytes) -> None:
        """Put line noise on the wire between frames."""
        with self._lock:
            self.injected.garbage += 1
            self._put_raw(bytes(data))

    def inject_rx_drop(self, frames: int = 1) -> None:
        """Lose the next `frames` frames from the host (the device sees the gap by sequence)."""
        with self._lock:
            self._rx_drop_next += frames

    def inject_stall(self) -> None:
        """The next stroke jams half way (no arrival: the firmware's stroke timeout must act)."""
        with self._lock:
            self.rig.jam_next()

    def inject_bounce(self) -> None:
        """The next arrival bounces: the far sensor goes 1, 0, 1 within 60 us."""
        with self._lock:
            self.rig.bounce_next()

    # -- transmit ------------------------------------------------------------------------------
    def _send(self, msg: Message) -> None:
        seq = self._tx_seq
        self._tx_seq = (seq + 1) % U16_MOD
        now = time.monotonic_ns()
        if now < self._silent_until_ns:
            return
        if self._drop_next and (self._drop_only is None or self._drop_only == msg.TYPE):
            self._drop_next -= 1
            self.injected.dropped += 1
            return
        frame = encode_frame(msg, seq)
        if self._corrupt_next and (self._corrupt_only is None or self._corrupt_only == msg.TYPE):
            self._corrupt_next -= 1
            self.injected.corrupted += 1
            b = bytearray(frame)
            i = len(b) // 2
            b[i] = (b[i] ^ 0x5A) or 0x01  # never a 0x00: the frame must stay one frame
            frame = bytes(b)
        self.sent[msg.TYPE] = self.sent.get(msg.TYPE, 0) + 1
        due = now
        if self._delay_next:
            self._delay_next -= 1
            self.injected.delayed += 1
            due = now + self._delay_ns
        due = max(due, self._out_busy_until_ns)  # a byte stream never reorders
        if due > now:
            self._out_busy_until_ns = due
            self._at(due, lambda f=frame: self._put_raw(f))
        else:
            self._put_raw(frame)

    def _send_together(self, msgs: list[Message]) -> None:
        """Frames the UART sends back to back, in one write: a thread descheduled between two
        writes would part them on the host by milliseconds, as no chip does."""
        self._batch = []
        try:
            for msg in msgs:
                self._send(msg)
        finally:
            data, self._batch = b"".join(self._batch), None
        if data:
            self._put_raw(data)

    def _put_raw(self, data: bytes) -> None:
        if self._batch is not None:
            self._batch.append(data)
            return
        w = self._writer
        if w is None:
            return
        try:
            w(data)
        except OSError as exc:
            log.debug("mcu emulator: write failed: %s", exc)

    # -- the firmware loop -----------------------------------------------------------------------
    def _at(self, t_ns: int, fn: Callable[[], None]) -> None:
        heapq.heappush(self._timers, (t_ns, next(self._tick), fn))

    def _run_due(self, now: int) -> None:
        """Run the timers due by `now` (the lock held). Whatever sends a frame stamped `now` calls
        this first: on the chip a due compare's handler runs before later work, so its frames are
        never behind later-stamped ones, however late this thread wakes."""
        while self._timers and self._timers[0][0] <= now:
            _, _, fn = heapq.heappop(self._timers)
            fn()

    def _run(self) -> None:
        while self._running:
            self._wake.clear()  # before the catch-up: bytes received after it end the wait at once
            with self._lock:
                self._catch_up()
                now = time.monotonic_ns()
                wait = self._timers[0][0] - now if self._timers else _IDLE_WAIT_S * 1e9
                if self._synced:  # wake when the watchdog falls due, not at the next idle look
                    wait = min(wait, self._last_host_ns + self._watchdog_ns + 1_000 - now)
            self._wake.wait(max(0.0, min(wait / 1e9, _IDLE_WAIT_S)))

    def _catch_up(self) -> None:
        """The bytes received by now, each handled at the instant it arrived after what fell due
        before it, then what fell due since (the lock held). A frame is the chip's when its last
        byte is in, not when this thread woke: beside a busy host's work an ARM handled late
        found its stroke running and the COMMAND after it found it ended (BUSY, then NOT_ARMED, for
        two frames sent together), and a COMMAND handled late started its stroke past the wrap."""
        with self._rx_lock:  # every byte stamped before `now` is queued
            now = time.monotonic_ns()
        while self._rx and self._rx[0][0] <= now:
            t_rx, data = self._rx.popleft()
            self._due_by(t_rx)
            self._take(data, t_rx)
        self._due_by(now)

    def _due_by(self, t_ns: int) -> None:
        self._watch_host(t_ns)
        self._run_due(t_ns)

    def _take(self, data: bytes, t_ns: int) -> None:
        """Bytes that reached the UART at `t_ns`."""
        if self._hung:
            return  # a hung main loop reads nothing: the receive ring overflows
        if t_ns < self._bootloader_until_ns:  # in the bootloader: lost, and it stays longer
            self.bootloader_bytes += len(data)
            self._bootloader_until_ns = t_ns + self.bootloader_ns
            return
        frames = self._decoder.feed(data)
        self.rx_errors = self._decoder.errors - self._rx_err_base
        for seq, msg in frames:
            if self._rx_drop_next and not isinstance(msg, Hello):
                self._rx_drop_next -= 1
                self.injected.dropped += 1
                continue
            self._on_frame(seq, msg, t_ns)

    def _watch_host(self, now: int) -> None:
        """The host watchdog, tripped at the instant it fell due, in order with the timers due
        before it: the chip's main loop finds it within a poll, and this thread, woken late on a busy
        host (23.6 ms read for a 20 ms watchdog), is not the chip's clock; the timers go likewise."""
        if self._hung or not self._synced:
            return
        due = self._last_host_ns + self._watchdog_ns + 1_000  # the first device tick past it
        if due > now:
            return
        self._run_due(due - 1)
        now = due
        self._synced = False
        self._armed = None
        self.watchdog_trips += 1
        self._send(
            Fault(DeviceFault.HOST_SILENT, self.device_us(now), min(self._watchdog_ns // 1_000_000, 0xFFFF))
        )
        cur = self._cur
        if cur is not None and not cur.done:
            self._end_stroke(cur, now, StopReason.WATCHDOG, StrokeFlags.WATCHDOG)

    def _on_frame(self, seq: int, msg: Message | UnknownFrame, now: int) -> None:
        self.received[msg.TYPE] = self.received.get(msg.TYPE, 0) + 1
        if isinstance(msg, Hello):
            self._on_hello(seq, msg, now)
            return
        self._rx_seq.check(seq)
        if not self._synced:
            if isinstance(msg, Ping):
                self._pong(msg, now)  # a watchdog-tripped device still says it is alive and unsynced
            else:
                self._ack(msg, seq, Status.NOT_SYNCED, 0, now)
            return
        self._last_host_ns = now
        if isinstance(msg, Ping):
            self._pong(msg, now)
        elif isinstance(msg, Arm):
            self._on_arm(seq, msg, now)
        elif isinstance(msg, Command):
            self._on_command(seq, msg, now)
        elif isinstance(msg, Stop):
            cur = self._cur
            if cur is not None and not cur.done:
                self._end_stroke(cur, now, StopReason.HOST, StrokeFlags.HOST_STOP)
            self._armed = None
            self._ack(msg, seq, Status.OK, 0 if cur is None else cur.stroke, now)
        else:
            self._ack(msg, seq, Status.UNKNOWN_TYPE, 0, now)

    def _ack(
        self,
        msg: Message | UnknownFrame,
        seq: int,
        status: Status,
        stroke: int,
        now: int,
        t_us: int | None = None,
    ) -> None:
        self._send(Ack(msg.TYPE, seq, status, stroke, self.device_us(now) if t_us is None else t_us))

    def _pong(self, msg: Ping, now: int) -> None:
        st = StateFlags(0)
        if self._synced:
            st |= StateFlags.SYNCED
        if self._armed is not None:
            st |= StateFlags.ARMED
        if self.rig.drive_on:
            st |= StateFlags.DRIVE_ON
        a, b = self.rig.sensors()
        if a:
            st |= StateFlags.SENSOR_A
        if b:
            st |= StateFlags.SENSOR_B
        # 1.2: the firmware's lost events and missed edges; this one loses and misses none
        extra = (0, 0) if self._session_minor >= 2 else (None, None)
        self._send(
            Pong(
                msg.token,
                self.device_us(now),
                st,
                self.rx_errors % U16_MOD,
                self._rx_seq.lost % U16_MOD,
                *extra,
            )
        )

    def _edge(self, channel: int, level: int, t_us: int) -> Edge:
        """An EDGE in the session's layout (1.2: with its flags, none here: every edge is stamped)."""
        return Edge(channel, level, t_us, 0 if self._session_minor >= 2 else None)

    def _on_hello(self, seq: int, msg: Hello, now: int) -> None:
        cur = self._cur
        if cur is not None and not cur.done:
            self._end_stroke(cur, now, StopReason.RESET, StrokeFlags.HOST_STOP)
        self._armed = None
        # A new session: the last one's stroke is forgotten, so its id cannot make the new host's
        # first COMMAND a "retransmission" (issue 33), as in the firmware.
        self._cur = None
        self._gen += 1
        self._tx_seq = 0
        self._rx_seq = SeqTracker()
        self._rx_seq.reset((seq + 1) % U16_MOD)
        self._rx_err_base = self._decoder.errors
        self._watchdog_ns = max(10, msg.watchdog_ms) * 1_000_000
        self._last_host_ns = now
        # A host of another major version gets the device's version and no session; the session
        # speaks the lower minor version (1.0: no reset cause).
        self._synced = msg.major == self.major
        minor = min(self.minor, msg.minor) if self._synced else self.minor
        self._session_minor = minor
        cause = int(self.reset_cause) if minor >= 1 else 0
        self._send(
            HelloAck(
                self.major, minor, int(self.caps), FW_VERSION, self.device_us(now), self.max_delay_us, cause
            )
        )

    def _on_arm(self, seq: int, msg: Arm, now: int) -> None:
        cur = self._cur
        if cur is not None and not cur.done:
            self._ack(msg, seq, Status.BUSY, msg.stroke, now)
            return
        if msg.direction > 1 or msg.delay_us > self.max_delay_us or not 1000 <= msg.timeout_us <= 10_000_000:
            self._ack(msg, seq, Status.BAD_ARG, msg.stroke, now)
            return
        self._armed = _Stroke(msg.stroke, Direction(msg.direction), msg.delay_us, msg.timeout_us)
        self._ack(msg, seq, Status.OK, msg.stroke, now)

    def _on_command(self, seq: int, msg: Command, now: int) -> None:
        cur = self._cur
        if cur is not None and cur.stroke == msg.stroke and cur.commanded:
            self._ack(msg, seq, Status.OK, msg.stroke, now, cur.t_cmd_us)  # a retransmission
            return
        if cur is not None and not cur.done:
            self._ack(msg, seq, Status.BUSY, msg.stroke, now)
            return
        arm = self._armed
        if arm is None or arm.stroke != msg.stroke:
            self._ack(msg, seq, Status.NOT_ARMED, msg.stroke, now)
            return
        if msg.at:
            skew = (msg.t_cmd_us - self.device_us(now)) % U32_MOD
            if min(skew, U32_MOD - skew) > MAX_COMMAND_SKEW_US:
                self._ack(msg, seq, Status.BAD_TIME, msg.stroke, now)
                return
            t_cmd_ns, t_cmd_us = self._host_ns(msg.t_cmd_us, now), msg.t_cmd_us
        else:
            t_cmd_ns, t_cmd_us = now, self.device_us(now)
        self._armed = None
        arm.commanded = True
        arm.t_cmd_ns = t_cmd_ns
        arm.t_cmd_us = t_cmd_us
        arm.t_rx_ns = now
        self._cur = arm
        self._gen += 1
        self._ack(msg, seq, Status.OK, msg.stroke, now, t_cmd_us)
        due = t_cmd_ns + self._host_dur(arm.delay_us * 1000)
        gen = self._gen
        self._at(max(due, now), lambda: self._fire(arm, due, gen))

    # -- the stroke ------------------------------------------------------------------------------
    def _fire(self, st: _Stroke, due_ns: int, gen: int) -> None:
        if gen != self._gen or st.done:
            return
        # A hardware timer fires on the instant, whatever this thread's wake-up jitter: the start
        # is late only when the COMMAND itself arrived after the instant.
        t0 = max(due_ns, st.t_rx_ns)
        st.late = t0 > due_ns
        st.started = True
        st.t_start_ns = t0
        self.strokes_started += 1
        d = st.direction
        a, b = self.rig.sensors(t0)
        plan = self.rig.start(d, t0)
        self._send(Start(st.stroke, int(d), self.device_us(t0), (t0 - due_ns) // 1000))
        if plan.there:
            st.t_arrive_ns = t0
            self._end_stroke(st, t0, StopReason.ARRIVED, StrokeFlags.ARRIVED)
            return
        if self._session_minor >= 2 and not (a, b)[int(d.source)]:
            # not at the source either (1.2): it runs, and the host hears of it
            self._send(Fault(DeviceFault.SENSORS, self.device_us(t0), a | b << 1))
        if plan.jammed:
            self.injected.stalls += 1
        if self._hang_next:
            self._hang_next = False
            self._hung = True
            self.injected.hangs += 1
            t_reset = t0 + WATCHDOG_RESET_NS
            if (t_arr := plan.arrive_ns) is not None and t_arr < t_reset:
                self._at(t_arr, lambda: self.rig.stop(t_arr))  # the capture stub's cut
            self._at(t_reset, lambda: self._watchdog_reset(t_reset))
            return
        if (t_dep := plan.depart_ns) is not None:
            self._at(t_dep, lambda: self._depart(st, gen, t_dep))
        if (t_arr := plan.arrive_ns) is not None:
            self._at(t_arr, lambda: self._arrive(st, gen, t_arr))
        t_to = t0 + self._host_dur(st.timeout_us * 1000)
        self._at(t_to, lambda: self._stall(st, gen, t_to))

    def _watchdog_reset(self, t_ns: int) -> None:
        self.watchdog_resets += 1
        self.watchdog_reset_ns = t_ns
        self.rig.stop(t_ns)
        self._boot(ResetCause.WATCHDOG, t_ns)

    def _depart(self, st: _Stroke, gen: int, t_ns: int) -> None:
        if gen != self._gen or st.done:
            return
        st.t_depart_ns = t_ns
        self._send(self._edge(int(st.direction.source), 0, self.device_us(t_ns)))

    def _arrive(self, st: _Stroke, gen: int, t_ns: int) -> None:
        if gen != self._gen or st.done:
            return
        st.t_arrive_ns = t_ns
        self.strokes_arrived += 1
        self._send(self._edge(int(st.direction.dest), 1, self.device_us(t_ns)))
        self._end_stroke(st, t_ns, StopReason.ARRIVED, StrokeFlags.ARRIVED)

    def _stall(self, st: _Stroke, gen: int, t_ns: int) -> None:
        if gen != self._gen or st.done:
            return
        self._send(Fault(DeviceFault.STALL, self.device_us(t_ns), min(st.timeout_us // 1000, 0xFFFF)))
        self._end_stroke(st, t_ns, StopReason.STALL, StrokeFlags.STALL)

    def _end_stroke(self, st: _Stroke, t_ns: int, reason: StopReason, flags: StrokeFlags) -> None:
        """Drive off, then the STROKE report, then STOPPED (that order: see the protocol doc)."""
        st.done = True
        self._gen += 1
        self.log.append(st)
        chatter = self.rig.stop(t_ns)
        if st.t_depart_ns is not None:
            flags |= StrokeFlags.DEPARTED
        if st.late:
            flags |= StrokeFlags.LATE
        us = self.device_us
        self._send(
            Stroke(
                st.stroke,
                int(st.direction),
                int(flags),
                st.t_cmd_us,
                us(st.t_start_ns) if st.started else 0,
                us(st.t_depart_ns) if st.t_depart_ns is not None else 0,
                us(st.t_arrive_ns) if st.t_arrive_ns is not None else 0,
            )
        )
        self._send(Stopped(st.stroke, int(reason), self.device_us(t_ns)))
        if chatter:  # an arrival that bounces: those edges come after the stroke's frames
            self.injected.bounces += 1
            # Stamped as they came, they leave together after the last: the UART, still sending the
            # stroke's frames (hundreds of us), queues them. Sent apart, a late thread left them
            # milliseconds apart, each read as an edge of its own (no bounce, no glitch counted).
            edges = [self._edge(int(ch), level, self.device_us(t_b)) for t_b, ch, level in chatter]
            self._at(chatter[-1][0], lambda: self._send_together(edges))

    @property
    def drive_on(self) -> bool:
        """Whether the emulated drive is switched on now."""
        return self.rig.drive_on

    @property
    def synced(self) -> bool:
        """Whether a host session is open (HELLO seen, watchdog not tripped)."""
        return self._synced
