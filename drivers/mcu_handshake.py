"""The MCU session's handshake: HELLO until HELLO_ACK, its checks, and what a restart found there means.

`McuDaq` (drivers/mcu.py) is the link and its session; this is the part of it that opens a session:
the version and capability checks, the longest delay, the clock rate refusal that stands until the
device really restarts, the sequence reset and the clock anchor, and the report of a restart.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

from .daq import DaqError
from .events import Event, FaultCode
from .mcu_clock import DeviceTimeline, fmt_ns
from .mcu_link import LinkStats, Transport, TransportLost
from .mcu_protocol import (
    PROTOCOL_MAJOR,
    PROTOCOL_MINOR,
    REQUIRED_CAPS,
    U16_MOD,
    Caps,
    FrameDecoder,
    Hello,
    HelloAck,
    ResetCause,
    SeqTracker,
)

if TYPE_CHECKING:
    from .mcu_stroke import StrokeAssembler

log = logging.getLogger("usmswitch.drivers.mcu")


class HandshakeMixin:
    """The handshake half of `McuDaq`: the attributes below are the driver's own."""

    name: str
    transport: Transport
    stats: LinkStats
    timeline: DeviceTimeline
    strokes: StrokeAssembler
    device: HelloAck | None
    retries: int
    reply_timeout_ns: int
    watchdog_ms: int
    max_delay_ns: int
    _state: threading.Condition
    _wlock: threading.Lock
    _tx_seq: int
    _rx_seq: SeqTracker
    _decoder: FrameDecoder
    _decoder_totals: tuple[int, int, int]
    _lost_total: int
    _resets_total: int
    _boot_reported: bool
    _last_rx_ns: int
    _next_ping_ns: int
    _last_stamp_ns: int
    _dev_errors_base: tuple[int, int]
    _pings: dict[int, int]
    _connected: bool

    if TYPE_CHECKING:  # McuDaq's own, named here for the type checker only

        def _send(self, msg: object, waiter: object = None) -> int: ...  # McuDaq's
        def _deliver(self, ev: Event) -> None: ...  # McuDaq's
        def _host_stamp(self) -> int: ...  # McuDaq's

    def _handshake(self, *, reconnect: bool = False) -> None:
        """HELLO until HELLO_ACK: version and capability check, sequence reset, clock anchor.

        A device that is ready answers the first HELLO at once. When the transport may have reset
        the board (`reset_wait_ns`), that first HELLO waits up to reset_wait_ns for its answer
        while the host sends nothing more (the Mega 2560's bootloader stays in programming mode
        while bytes keep coming, and starts the firmware about a second after the last one);
        HELLO is then retried every 4 reply timeouts for as long again as the retries take, or
        1 s, whichever is longer.

        `reconnect`: the link was reopened for this handshake; it is counted as the session is
        marked connected.
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
                    self._accept_hello(seq, msg, t_send, t_recv, reconnect=reconnect)
                    return
        self.stats.handshake_failures += 1
        raise TransportLost(
            f"{self.name}: handshake with {self.transport.describe()} failed: "
            f"no HELLO_ACK to {tries} HELLO within {waited_ns // 1_000_000} ms"
        )

    def _accept_hello(
        self, seq: int, msg: HelloAck, t_send: int, t_recv: int, *, reconnect: bool = False
    ) -> None:
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
                f" {fmt_ns(msg.max_delay_us * 1000)} (HELLO_ACK max_delay_us {msg.max_delay_us}); this"
                f" host may ask for up to {fmt_ns(self.max_delay_ns)} (its longest target)"
            )
        with self._state:
            tl = self.timeline
            restarted = tl.restarted(
                msg,
                t_send,
                t_recv,
                booted=self._boot_reported,
                fw_before=None if self.device is None else self.device.fw_version,
            )
            if tl.rate_refusal:
                if not restarted:
                    self.stats.handshake_failures += 1
                    raise DaqError(f"{self.name}: {self.transport.describe()}: {tl.rate_refusal}")
                tl.rate_refusal = ""  # another run of the device (new firmware?): judged afresh
            self._note_restart(msg, restarted)
            self.device = msg
            tl.heard = (msg.t_us, t_recv)
            self._keep_seq_totals()
            self._rx_seq = SeqTracker()
            self._rx_seq.reset((seq + 1) % U16_MOD)
            mid, rtt = (t_send + t_recv) // 2, t_recv - t_send
            # A reopened link to the same run of the device keeps the timeline; a resync (the clock
            # jumped, the device left the session) and a restarted device are anchored afresh.
            if not (reconnect and not restarted and tl.resumes(msg.t_us, mid, rtt)):
                tl.anchor(msg.t_us, mid, rtt, self._last_stamp_ns + 1)
            self._last_rx_ns = t_recv
            self._next_ping_ns = t_recv
            self._dev_errors_base = (self.stats.device_rx_errors, self.stats.device_rx_lost)
            self.strokes.levels = None  # until the first PONG of this session
            self._pings.clear()
            # Counted with `connected` under one lock: a reader that sees the link back sees it counted.
            if reconnect:
                self.stats.reconnects += 1
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

    def _note_restart(self, msg: HelloAck, restarted: bool) -> None:
        """At a handshake: a restart of the device since the last session, not already reported by
        its BOOT, is reported now (its cause is old news on a reconnect to the same run)."""
        self.stats.reset_cause = msg.reset_cause
        booted, self._boot_reported = self._boot_reported, False
        if not restarted or booted:
            return
        if self.timeline.heard is not None:
            self.stats.device_resets += 1
        self._report_reset(msg.reset_cause, in_session=False)

    def _report_reset(self, cause: int, *, in_session: bool) -> None:
        """A device restart as an event: FAULT DRIVE for its watchdog or a brown-out; any other
        (power, the reset pin) FAULT DISCONNECT when it ended a session, else (found at a handshake,
        after the link's own loss was reported, or the driver's first) only logged."""
        rc = ResetCause(cause & 0x1F)
        bad = ResetCause.WATCHDOG in rc or ResetCause.BROWN_OUT in rc
        if ResetCause.WATCHDOG in rc:
            self.stats.watchdog_resets += 1
        what = reset_text(cause)
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


def reset_text(cause: int) -> str:
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
