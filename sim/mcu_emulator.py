"""An emulator of the rig's microcontroller firmware, speaking docs/mcu-protocol.md over a byte stream.

`McuEmulator` is the firmware: it handshakes, arms, fires the start after the armed delay on its
own clock, stamps the limit-sensor edges of the rig model (`UsmSwitchModel`) in real time, stops
the drive on arrival, reports strokes, answers heartbeats and runs the host watchdog. Its device
clock is a free-running 32-bit microsecond counter that can start near the wrap and drift by a
few ppm, as a real crystal does.

It reaches the host through a link: `PtyLink` (a pty pair whose slave path is the "serial port",
unplug and replug included) or `UsbBackend` (a pyusb backend, so the `usb` driver runs real pyusb
code against it). Wire faults are injected on the device's transmit side: corrupt bytes, dropped
frames, delayed frames, silence, garbage; rig faults: a stall and a sensor bounce.
"""

from __future__ import annotations

import array
import contextlib
import errno
import heapq
import itertools
import logging
import os
import queue
import select
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import usb.backend
import usb.core

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

from .model import UsmSwitchModel

log = logging.getLogger(__name__)

ALL_CAPS = Caps.HW_DELAY | Caps.EDGE_STAMP | Caps.STROKE_REPORT | Caps.STOP_ON_ARRIVAL | Caps.WATCHDOG
FW_VERSION = 0x0100
MAX_DELAY_US = 1_000_000
# COMMAND's t_cmd_us must be within this of the device clock (else BAD_TIME).
MAX_COMMAND_SKEW_US = 1_000_000
_IDLE_WAIT_S = 0.05
BOUNCE_NS = 30_000


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
    ) -> None:
        """`bootloader_ms`: after each power-on (`power_cycle()`, as an Arduino's reset when its
        port opens) the firmware starts only once the line has been quiet that long: like the
        Mega 2560's stk500v2 bootloader, bytes meanwhile are lost and restart the wait."""
        if not 0 <= bootloader_ms <= 10_000:
            raise ValueError(f"bootloader_ms must be in 0..10000, got {bootloader_ms!r}")
        self.bootloader_ns = bootloader_ms * 1_000_000
        if not 0 <= clock_start_us < U32_MOD:
            raise ValueError(f"clock_start_us must be a 32-bit count, got {clock_start_us!r}")
        if not -1000 <= drift_ppm <= 1000:
            raise ValueError(f"drift_ppm must be in -1000..1000, got {drift_ppm!r}")
        self.model = model or UsmSwitchModel(seed=seed)
        self.clock_start_us = clock_start_us
        self.drift_ppm = drift_ppm
        self.caps = caps
        self.major = major
        self.minor = minor
        p = self.model.params
        self._stroke_mm = p.stroke_mm
        self._release_mm = p.release_mm
        self._pos_mm = 0.0 if start_at is Channel.A else p.stroke_mm
        self.injected = InjectedFaults()
        self._lock = threading.RLock()
        self._rx: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
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
        self._stall_next = False
        self._bounce_next = False
        self._rx_drop_next = 0
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
        self._boot()

    # -- power and clock -----------------------------------------------------------------------
    def _boot(self) -> None:
        """Power-on reset: clock restarts at clock_start_us, no session, drive off."""
        with self._lock:
            self.boots += 1
            self._t_boot_ns = time.monotonic_ns()
            self._bootloader_until_ns = self._t_boot_ns + self.bootloader_ns
            self.bootloader_bytes = 0
            self._decoder = _DeviceDecoder()
            self._rx_err_base = 0
            self._rx_seq = SeqTracker()
            self._tx_seq = 0
            self._synced = False
            self._watchdog_ns = 0
            self._last_host_ns = self._t_boot_ns
            self._armed: _Stroke | None = None
            self._cur: _Stroke | None = None
            self._gen = 0  # bumps to cancel a stroke's pending timers
            self._drive_on = False
            self.rx_errors = 0
            self._timers.clear()

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
        """Bytes from the host (any thread)."""
        self._rx.put(bytes(data))

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
        self._rx.put(None)
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None
        with self._lock:
            self._drive_off(time.monotonic_ns())

    def power_cycle(self) -> None:
        """Cut and restore power: everything the firmware knew is gone, the clock restarts."""
        with self._lock:
            self._drive_off(time.monotonic_ns())
            self._boot()

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
            self._stall_next = True

    def inject_bounce(self) -> None:
        """The next arrival bounces: the far sensor goes 1, 0, 1 within 60 us."""
        with self._lock:
            self._bounce_next = True

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

    def _put_raw(self, data: bytes) -> None:
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

    def _run(self) -> None:
        while self._running:
            with self._lock:
                now = time.monotonic_ns()
                while self._timers and self._timers[0][0] <= now:
                    _, _, fn = heapq.heappop(self._timers)
                    fn()
                self._check_watchdog(now)
                wait = self._timers[0][0] - now if self._timers else _IDLE_WAIT_S * 1e9
                if self._synced:  # wake when the watchdog falls due, not at the next idle look
                    wait = min(wait, self._last_host_ns + self._watchdog_ns + 1 - now)
            try:
                data = self._rx.get(timeout=max(0.0, min(wait / 1e9, _IDLE_WAIT_S)))
            except queue.Empty:
                continue
            if data is None:
                continue
            with self._lock:
                now = time.monotonic_ns()
                if now < self._bootloader_until_ns:  # in the bootloader: lost, and it stays longer
                    self.bootloader_bytes += len(data)
                    self._bootloader_until_ns = now + self.bootloader_ns
                    continue
                frames = self._decoder.feed(data)
                self.rx_errors = self._decoder.errors - self._rx_err_base
                now = time.monotonic_ns()
                for seq, msg in frames:
                    if self._rx_drop_next and not isinstance(msg, Hello):
                        self._rx_drop_next -= 1
                        self.injected.dropped += 1
                        continue
                    self._on_frame(seq, msg, now)

    def _check_watchdog(self, now: int) -> None:
        if not self._synced or now - self._last_host_ns <= self._watchdog_ns:
            return
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
        if self._drive_on:
            st |= StateFlags.DRIVE_ON
        a, b = self._sensors()
        if a:
            st |= StateFlags.SENSOR_A
        if b:
            st |= StateFlags.SENSOR_B
        self._send(
            Pong(msg.token, self.device_us(now), st, self.rx_errors % U16_MOD, self._rx_seq.lost % U16_MOD)
        )

    def _on_hello(self, seq: int, msg: Hello, now: int) -> None:
        cur = self._cur
        if cur is not None and not cur.done:
            self._end_stroke(cur, now, StopReason.RESET, StrokeFlags.HOST_STOP)
        self._armed = None
        self._tx_seq = 0
        self._rx_seq = SeqTracker()
        self._rx_seq.reset((seq + 1) % U16_MOD)
        self._rx_err_base = self._decoder.errors
        self._watchdog_ns = max(10, msg.watchdog_ms) * 1_000_000
        self._last_host_ns = now
        # A host of another major version gets the device's version and no session.
        self._synced = msg.major == self.major
        self._send(
            HelloAck(self.major, self.minor, int(self.caps), FW_VERSION, self.device_us(now), MAX_DELAY_US)
        )

    def _on_arm(self, seq: int, msg: Arm, now: int) -> None:
        cur = self._cur
        if cur is not None and not cur.done:
            self._ack(msg, seq, Status.BUSY, msg.stroke, now)
            return
        if msg.direction > 1 or msg.delay_us > MAX_DELAY_US or not 1000 <= msg.timeout_us <= 10_000_000:
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
    def _sensors(self) -> tuple[int, int]:
        a = 1 if self._pos_mm <= self._release_mm else 0
        b = 1 if self._pos_mm >= self._stroke_mm - self._release_mm else 0
        return a, b

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
        self._drive_on = True
        self._send(Start(st.stroke, int(st.direction), self.device_us(t0), (t0 - due_ns) // 1000))
        d = st.direction
        distance = (self._stroke_mm - self._pos_mm) if d is Direction.ON else self._pos_mm
        src_active = self._sensors()[int(d.source)] == 1
        if distance <= self._release_mm:
            self._pos_mm = self._stroke_mm if d is Direction.ON else 0.0
            st.t_arrive_ns = t0
            self._end_stroke(st, t0, StopReason.ARRIVED, StrokeFlags.ARRIVED)
            return
        jam = 0.5 if self._stall_next else None
        if self._stall_next:
            self._stall_next = False
            self.injected.stalls += 1
        stroke = self.model.next_stroke(d, t0, distance_mm=distance, jam_fraction=jam)
        if src_active and stroke.end_mm >= self._release_mm:
            t_dep = t0 + stroke.time_at_ns(self._release_mm)
            self._at(t_dep, lambda: self._edge(st, gen, d.source, 0, t_dep))
        if stroke.operating_ns is not None:
            t_arr = t0 + stroke.operating_ns
            self._at(t_arr, lambda: self._arrive(st, gen, t_arr))
        self._stroke_model = stroke
        t_to = t0 + self._host_dur(st.timeout_us * 1000)
        self._at(t_to, lambda: self._stall(st, gen, t_to))

    def _edge(self, st: _Stroke, gen: int, ch: Channel, level: int, t_ns: int) -> None:
        if gen != self._gen or st.done:
            return
        if ch is st.direction.source and level == 0:
            st.t_depart_ns = t_ns
        self._send(Edge(int(ch), level, self.device_us(t_ns)))

    def _arrive(self, st: _Stroke, gen: int, t_ns: int) -> None:
        if gen != self._gen or st.done:
            return
        d = st.direction
        self._pos_mm = self._stroke_mm if d is Direction.ON else 0.0
        st.t_arrive_ns = t_ns
        self.strokes_arrived += 1
        self._send(Edge(int(d.dest), 1, self.device_us(t_ns)))
        self._end_stroke(st, t_ns, StopReason.ARRIVED, StrokeFlags.ARRIVED)
        if self._bounce_next:
            # The contact chatters after the arrival: those edges come after the stroke's frames.
            self._bounce_next = False
            self.injected.bounces += 1
            ch = int(d.dest)
            for k, level in ((1, 0), (2, 1)):
                t_b = t_ns + k * BOUNCE_NS
                self._at(t_b, lambda t_b=t_b, level=level: self._send(Edge(ch, level, self.device_us(t_b))))

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
        if st.started and reason is not StopReason.ARRIVED:
            # The mover stops where it is when the drive is cut mid-stroke.
            sm = getattr(self, "_stroke_model", None)
            if sm is not None:
                travelled = sm.displacement_mm(t_ns - st.t_start_ns)
                self._pos_mm = (
                    min(self._stroke_mm, self._pos_mm + travelled)
                    if st.direction is Direction.ON
                    else max(0.0, self._pos_mm - travelled)
                )
        self._drive_off(t_ns)
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

    def _drive_off(self, t_ns: int) -> None:
        if self._drive_on:
            self._drive_on = False
            self.model.drive_off(t_ns)

    @property
    def drive_on(self) -> bool:
        """Whether the emulated drive is switched on now."""
        return self._drive_on

    @property
    def synced(self) -> bool:
        """Whether a host session is open (HELLO seen, watchdog not tripped)."""
        return self._synced


class PtyLink:
    """The emulator behind a pty pair: the slave's path, via a stable symlink, is the serial port.

    `unplug()` closes the pty (the host's reads fail with EIO, as on a USB-serial unplug) and
    removes the symlink; `replug()` makes a new pty and points the symlink at it, as udev does for
    /dev/serial/by-id.
    """

    def __init__(self, emulator: McuEmulator, link_path: str | os.PathLike[str]) -> None:
        self.emulator = emulator
        self.link_path = Path(link_path)
        self._master = -1
        self._slave = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.plugged = False
        self.bytes_in = 0

    @property
    def slave_path(self) -> str:
        """The current pty slave device."""
        return os.ttyname(self._slave)

    def plug(self) -> PtyLink:
        """Create the pty, point the symlink at it, start pumping bytes."""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tty.setraw(self._master)
        tmp = self.link_path.with_name(self.link_path.name + ".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(self._slave))
        tmp.replace(self.link_path)
        self._stop.clear()
        self._thread = threading.Thread(target=self._pump, args=(self._master,), name="pty-link", daemon=True)
        self._thread.start()
        master = self._master
        self.emulator.attach(lambda data: _write_all(master, data))
        self.plugged = True
        return self

    def _pump(self, fd: int) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([fd], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(fd, 4096)
            except OSError:
                return  # closed by unplug, or the slave side hung up for good
            if data:
                self.bytes_in += len(data)
                self.emulator.receive(data)

    def unplug(self) -> None:
        """Pull the cable: the pty goes away and so does the symlink."""
        if not self.plugged:
            return
        self.plugged = False
        self.emulator.detach()
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1
        self.link_path.unlink(missing_ok=True)

    def replug(self, *, power_cycle: bool = True) -> None:
        """Plug back in (a bus-powered MCU reboots: clock and session restart)."""
        if power_cycle:
            self.emulator.power_cycle()
        self.plug()

    def close(self) -> None:
        """Unplug for good."""
        self.unplug()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


# -- USB -------------------------------------------------------------------------------------------
class _Desc:
    """A descriptor object: attributes as pyusb's backends expose them."""

    def __init__(self, **kw: object) -> None:
        self.__dict__.update(kw)


class UsbDevice:
    """One emulated USB device: vendor class interface 0 with bulk OUT 0x01 and bulk IN 0x81."""

    EP_OUT = 0x01
    EP_IN = 0x81
    MAX_PACKET = 64

    def __init__(
        self, emulator: McuEmulator, vid: int = 0x1209, pid: int = 0x0001, serial: str = "EMU0001"
    ) -> None:
        self.emulator = emulator
        self.vid = vid
        self.pid = pid
        self.serial = serial
        self.plugged = True
        self._inbox = bytearray()
        self._cv = threading.Condition()
        emulator.attach(self._from_device)

    def _from_device(self, data: bytes) -> None:
        with self._cv:
            self._inbox += data
            self._cv.notify_all()

    def unplug(self) -> None:
        """Pull the cable."""
        with self._cv:
            self.plugged = False
            self._inbox.clear()
            self._cv.notify_all()
        self.emulator.detach()

    def replug(self, *, power_cycle: bool = True) -> None:
        """Plug back in (the MCU reboots when bus-powered)."""
        if power_cycle:
            self.emulator.power_cycle()
        with self._cv:
            self.plugged = True
        self.emulator.attach(self._from_device)


def _no_device() -> usb.core.USBError:
    return usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)


class UsbBackend(usb.backend.IBackend):
    """A pyusb backend whose devices are emulators: `usb.core.find(backend=...)` finds them."""

    def __init__(self, *devices: UsbDevice) -> None:
        super().__init__()
        self.devices = list(devices)

    def enumerate_devices(self):  # type: ignore[no-untyped-def]
        return [d for d in self.devices if d.plugged]

    def get_device_descriptor(self, dev: UsbDevice) -> _Desc:
        return _Desc(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=64,
            idVendor=dev.vid,
            idProduct=dev.pid,
            bcdDevice=FW_VERSION,
            iManufacturer=1,
            iProduct=2,
            iSerialNumber=3,
            bNumConfigurations=1,
            address=1 + self.devices.index(dev),
            bus=1,
            port_number=1,
            port_numbers=(1,),
            speed=2,
        )

    def get_configuration_descriptor(self, dev: UsbDevice, config: int) -> _Desc:
        if config != 0:
            raise usb.core.USBError("Invalid configuration", -2, errno.EINVAL)
        return _Desc(
            bLength=9,
            bDescriptorType=2,
            wTotalLength=32,
            bNumInterfaces=1,
            bConfigurationValue=1,
            iConfiguration=0,
            bmAttributes=0x80,
            bMaxPower=50,
            extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev: UsbDevice, intf: int, alt: int, config: int) -> _Desc:
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError(f"no interface {intf} alt {alt} in configuration {config}")
        return _Desc(
            bLength=9,
            bDescriptorType=4,
            bInterfaceNumber=0,
            bAlternateSetting=0,
            bNumEndpoints=2,
            bInterfaceClass=0xFF,
            bInterfaceSubClass=0,
            bInterfaceProtocol=0,
            iInterface=0,
            extra_descriptors=[],
        )

    def get_endpoint_descriptor(self, dev: UsbDevice, ep: int, intf: int, alt: int, config: int) -> _Desc:
        if (intf, alt, config) != (0, 0, 0) or ep not in (0, 1):
            raise IndexError(f"no endpoint {ep}")
        return _Desc(
            bLength=7,
            bDescriptorType=5,
            bEndpointAddress=(UsbDevice.EP_OUT, UsbDevice.EP_IN)[ep],
            bmAttributes=0x02,
            wMaxPacketSize=UsbDevice.MAX_PACKET,
            bInterval=0,
            bRefresh=0,
            bSynchAddress=0,
            extra_descriptors=[],
        )

    def open_device(self, dev: UsbDevice) -> UsbDevice:
        if not dev.plugged:
            raise _no_device()
        return dev

    def close_device(self, dev_handle: UsbDevice) -> None:
        return None

    def set_configuration(self, dev_handle: UsbDevice, config_value: int) -> None:
        if not dev_handle.plugged:
            raise _no_device()

    def get_configuration(self, dev_handle: UsbDevice) -> int:
        return 1

    def claim_interface(self, dev_handle: UsbDevice, intf: int) -> None:
        if not dev_handle.plugged:
            raise _no_device()

    def release_interface(self, dev_handle: UsbDevice, intf: int) -> None:
        return None

    def is_kernel_driver_active(self, dev_handle: UsbDevice, intf: int) -> bool:
        return False

    def clear_halt(self, dev_handle: UsbDevice, ep: int) -> None:
        return None

    def bulk_write(self, dev_handle: UsbDevice, ep: int, intf: int, data: array.array, timeout: int) -> int:
        if not dev_handle.plugged:
            raise _no_device()
        if ep != UsbDevice.EP_OUT:
            raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
        dev_handle.emulator.receive(bytes(data))
        return len(data)

    def bulk_read(self, dev_handle: UsbDevice, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        if ep != UsbDevice.EP_IN:
            raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
        deadline = time.monotonic() + (timeout / 1000 if timeout else 3600.0)
        with dev_handle._cv:
            while True:
                if not dev_handle.plugged:
                    raise _no_device()
                if dev_handle._inbox:
                    # One bulk transfer: up to the buffer, in whole packets as the host controller does.
                    n = min(len(buff), len(dev_handle._inbox))
                    buff[:n] = array.array("B", dev_handle._inbox[:n])
                    del dev_handle._inbox[:n]
                    return n
                left = deadline - time.monotonic()
                if left <= 0:
                    raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
                dev_handle._cv.wait(left)

    def ctrl_transfer(
        self,
        dev_handle: UsbDevice,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: array.array,
        timeout: int,
    ) -> int:
        if not dev_handle.plugged:
            raise _no_device()
        # GET_DESCRIPTOR (string): the language table and the three strings.
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:
            index = wValue & 0xFF
            if index == 0:
                body = b"\x09\x04"
            else:
                text = {1: "usmswitch", 2: "usmswitch rig MCU (emulated)", 3: dev_handle.serial}.get(index)
                if text is None:
                    raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
                body = text.encode("utf-16-le")
            desc = bytes([2 + len(body), 3]) + body
            n = min(len(data), len(desc))
            data[:n] = array.array("B", desc[:n])
            return n
        raise usb.core.USBError("Pipe error", -9, errno.EPIPE)


def main(argv: list[str] | None = None) -> int:
    """Run the emulator on a pty until SIGTERM/SIGINT: `python -m usmswitch.sim.mcu_emulator --link PATH`."""
    import argparse
    import signal

    ap = argparse.ArgumentParser(
        description="usmswitch MCU firmware emulator on a pty (serial driver target)"
    )
    ap.add_argument("--link", required=True, help="symlink to create for the pty slave, e.g. /tmp/usmswitch")
    ap.add_argument("--seed", type=int, default=0, help="rig model seed")
    ap.add_argument("--clock-start-us", type=int, default=0, help="device clock at power-on (wrap tests)")
    ap.add_argument("--drift-ppm", type=int, default=0, help="device crystal error")
    args = ap.parse_args(argv)
    emu = McuEmulator(seed=args.seed, clock_start_us=args.clock_start_us, drift_ppm=args.drift_ppm).start()
    link = PtyLink(emu, args.link).plug()
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    print(f"mcu emulator on {link.slave_path} via {args.link}", flush=True)
    done.wait()
    link.close()
    emu.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
