"""The pieces of an MCU link that are not the protocol's logic: the byte transport a driver plugs in
(a serial port, USB bulk endpoints), the device's clock as the host keeps it, the link's counters.

`mcu.McuDaq` runs the protocol over them; `serial_mcu` and `usb_mcu` implement `Transport`.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass

from .clock import DEFAULT_SPIN_MARGIN_NS, MonotonicClock
from .daq import DaqDisconnected, check_ns


class TransportLost(DaqDisconnected):
    """The byte transport failed: unplugged, port closed, device gone."""


class Transport(ABC):
    """A bidirectional byte pipe to the MCU: a serial port, a pair of USB bulk endpoints."""

    #: How long the first HELLO after an open waits for its answer before HELLO is retried: a
    #: board that resets when its port opens (Arduino, DTR) sits in its bootloader meanwhile, and
    #: more bytes would keep some bootloaders there. 0 for a device that is ready at once.
    reset_wait_ns: int = 0

    @abstractmethod
    def open(self) -> None:
        """Open the device; raises TransportLost (absent, busy) with the reason."""

    @abstractmethod
    def close(self) -> None:
        """Release the device; safe to call twice and after a loss."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Send all of `data`; raises TransportLost if the device went away."""

    @abstractmethod
    def read(self, timeout_ns: int) -> bytes:
        """Whatever bytes arrive within `timeout_ns` (b"" if none); raises TransportLost."""

    @abstractmethod
    def describe(self) -> str:
        """Where the device is, for logs and errors."""


class DeviceClock(MonotonicClock):
    """The device's timeline on the host: `time.monotonic_ns() + offset_ns`, the offset kept by heartbeats."""

    def __init__(self, spin_margin_ns: int = DEFAULT_SPIN_MARGIN_NS) -> None:
        super().__init__(check_ns("spin_margin_ns", spin_margin_ns))
        #: Device timeline minus host monotonic time, in ns (written by the link thread only).
        self.offset_ns = 0

    def now_ns(self) -> int:
        return time.monotonic_ns() + self.offset_ns


@dataclass
class LinkStats:
    """Counters of everything that went wrong on the link and what was done about it."""

    framing_errors: int = 0
    crc_errors: int = 0
    format_errors: int = 0
    lost_frames: int = 0
    seq_resets: int = 0
    retransmits: int = 0
    reply_timeouts: int = 0
    silences: int = 0
    disconnects: int = 0
    reconnects: int = 0
    handshake_failures: int = 0
    recovered_strokes: int = 0
    unrecovered_strokes: int = 0
    device_rx_errors: int = 0
    device_rx_lost: int = 0
    wraps: int = 0
    #: Sessions lost by the device's side (it restarted, or left the session) and handshaken again.
    resyncs: int = 0
    #: Device restarts seen (BOOT, or a handshake whose device clock had started again), and of
    #: those, by its hardware watchdog; the last reset cause it reported (ResetCause bits).
    device_resets: int = 0
    watchdog_resets: int = 0
    reset_cause: int = 0
    #: Stamps (EDGE, START, STOPPED, FAULT, STROKE, PONG, ACK) too far from the device clock: rejected.
    bad_stamps: int = 0
    #: STARTs naming another stroke (or a second START, or the other direction): rejected.
    foreign_starts: int = 0
    #: STARTs off the instant the host commanded, or whose `late_us` is not the lateness the host
    #: measures (beyond START_TOLERANCE_NS): the stroke is kept with a flag, not learned.
    start_mismatches: int = 0
    #: Strokes whose end found the device clock off the host's (the PONG asked for at each
    #: STROKE report): the stroke is flagged MISMATCH.
    clock_doubts: int = 0
    #: COMMANDs none of whose tries was acknowledged: the stroke's own frames were followed.
    unacked_commands: int = 0
    #: Events dropped, oldest first, from the full queue between the link thread and the loop.
    events_dropped: int = 0
    #: USB endpoint halts (EPIPE) cleared with CLEAR_FEATURE(ENDPOINT_HALT) and the transfer retried.
    halts_cleared: int = 0
    max_rtt_ns: int = 0
    last_rtt_ns: int = 0

    def as_dict(self) -> dict[str, int]:
        """Plain dict for status replies and logs."""
        return dict(self.__dict__)
