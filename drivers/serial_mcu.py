"""The `serial` driver: the rig's microcontroller on a serial port (USB CDC-ACM or a UART adapter).

Config string: `serial:PATH[?baud=N][&reset_wait_ms=N]`, e.g.
`serial:/dev/serial/by-id/usb-Arduino__www.arduino.cc__0042_...-if00` or
`serial:/dev/ttyACM0?baud=1000000&reset_wait_ms=0`. Use a /dev/serial/by-id path (or a udev
symlink such as /dev/usmswitch): after an unplug the kernel may give the device another ttyACMn,
and the driver reopens by the configured path.

`baud` defaults to 1,000,000, the reference firmware's rate (exact at 16 MHz; the Mega's USB
bridge passes it on to the UART). `reset_wait_ms` (default 2000) is how long the first HELLO after
opening the port waits for its answer: an Arduino resets when the port opens (DTR) and spends
1-2 s in its bootloader, which more bytes would keep there; a device that is ready answers at once,
so the wait costs nothing then. Set 0 for a board whose auto-reset is disabled
(docs/firmware.md) to fail fast when it does not answer.
"""

from __future__ import annotations

import errno
import logging
import select
from typing import NamedTuple
from urllib.parse import parse_qs

import serial

from .mcu import McuDaq
from .mcu_link import Transport, TransportLost

log = logging.getLogger(__name__)

DEFAULT_BAUD = 1_000_000
DEFAULT_RESET_WAIT_MS = 2000
RESET_WAIT_RANGE = (0, 10_000)
# Linux sets any rate (BOTHER); the firmware's UART decides which work. USB CDC ignores it.
BAUD_RANGE = (50, 20_000_000)


class SerialTransport(Transport):
    """pyserial, opened exclusive and in low-latency mode where the adapter allows it."""

    def __init__(
        self, path: str, baud: int = DEFAULT_BAUD, reset_wait_ms: int = DEFAULT_RESET_WAIT_MS
    ) -> None:
        if not isinstance(path, str) or not path:
            raise ValueError(f"serial path must be a non-empty string, got {path!r}")
        if isinstance(baud, bool) or not isinstance(baud, int) or not BAUD_RANGE[0] <= baud <= BAUD_RANGE[1]:
            raise ValueError(f"baud must be an integer in {BAUD_RANGE[0]}..{BAUD_RANGE[1]}, got {baud!r}")
        lo, hi = RESET_WAIT_RANGE
        if (
            isinstance(reset_wait_ms, bool)
            or not isinstance(reset_wait_ms, int)
            or not lo <= reset_wait_ms <= hi
        ):
            raise ValueError(f"reset_wait_ms must be an integer in {lo}..{hi}, got {reset_wait_ms!r}")
        self.path = path
        self.baud = baud
        self.reset_wait_ns = reset_wait_ms * 1_000_000
        self._port: serial.Serial | None = None
        #: Whether the last open got ASYNC_LOW_LATENCY (ptys and some adapters refuse it).
        self.low_latency = False

    def describe(self) -> str:
        return f"serial {self.path}"

    def open(self) -> None:
        self.close()
        try:
            port = serial.Serial(self.path, self.baud, timeout=0, write_timeout=0.5, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportLost(f"cannot open {self.path}: {exc}") from exc
        try:
            port.set_low_latency_mode(True)
            self.low_latency = True
        except (ValueError, OSError, NotImplementedError) as exc:
            # A pty or an adapter without TIOCSSERIAL: the protocol still works, with USB's latency.
            self.low_latency = False
            log.debug("serial %s: low-latency mode refused: %s", self.path, exc)
        port.reset_input_buffer()
        self._port = port

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError) as exc:
                log.debug("serial %s: close: %s", self.path, exc)

    def write(self, data: bytes) -> None:
        port = self._port
        if port is None:
            raise TransportLost(f"{self.path} is not open")
        try:
            port.write(data)
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            raise TransportLost(f"write to {self.path}: {exc}") from exc

    def read(self, timeout_ns: int) -> bytes:
        port = self._port
        if port is None:
            raise TransportLost(f"{self.path} is not open")
        try:
            # The port is non-blocking (timeout=0): wait here, then take whatever is there.
            ready, _, _ = select.select([port.fileno()], [], [], timeout_ns / 1e9)
            if not ready:
                return b""
            return port.read(max(1, port.in_waiting))
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EINTR):
                return b""
            raise TransportLost(f"read from {self.path}: {exc}") from exc
        except (serial.SerialException, TypeError, AttributeError) as exc:
            raise TransportLost(f"read from {self.path}: {exc}") from exc


class SerialMcuDaq(McuDaq):
    """The MCU protocol over a serial port."""

    name = "serial"

    def __init__(
        self,
        path: str,
        baud: int = DEFAULT_BAUD,
        *,
        reset_wait_ms: int = DEFAULT_RESET_WAIT_MS,
        **kwargs: object,
    ) -> None:
        super().__init__(SerialTransport(path, baud, reset_wait_ms), **kwargs)  # type: ignore[arg-type]

    @classmethod
    def from_spec(cls, spec: str, **kwargs: object) -> SerialMcuDaq:
        """Build from a config string `serial:PATH[?baud=N][&reset_wait_ms=N]`."""
        path, baud, reset_wait_ms = parse_serial_spec(spec)
        kwargs.setdefault("reset_wait_ms", reset_wait_ms)
        return cls(path, baud, **kwargs)


class SerialSpec(NamedTuple):
    path: str
    baud: int
    reset_wait_ms: int


_SPEC_FORM = "'serial:/dev/ttyACM0[?baud=1000000][&reset_wait_ms=2000]'"


def parse_serial_spec(spec: str) -> SerialSpec:
    """(path, baud, reset_wait_ms) from `serial:PATH[?baud=N][&reset_wait_ms=N]`; ValueError naming the
    bad part."""
    if not isinstance(spec, str) or not spec.startswith("serial:"):
        raise ValueError(f"serial driver spec must look like {_SPEC_FORM}, got {spec!r}")
    rest = spec[len("serial:") :]
    path, _, query = rest.partition("?")
    if not path:
        raise ValueError(f"serial driver spec {spec!r} has no device path")
    values = {"baud": DEFAULT_BAUD, "reset_wait_ms": DEFAULT_RESET_WAIT_MS}
    ranges = {"baud": BAUD_RANGE, "reset_wait_ms": RESET_WAIT_RANGE}
    if query:
        opts = parse_qs(query, keep_blank_values=True, strict_parsing=False)
        unknown = set(opts) - set(values)
        if unknown:
            raise ValueError(
                f"serial driver spec {spec!r}: unknown option(s) {sorted(unknown)}; "
                "known: baud, reset_wait_ms"
            )
        for key, (lo, hi) in ranges.items():
            if key not in opts:
                continue
            text = opts[key][-1]
            if not text.isdigit():
                raise ValueError(f"serial driver spec {spec!r}: {key} must be an integer, got {text!r}")
            value = int(text)
            if not lo <= value <= hi:
                raise ValueError(f"serial driver spec {spec!r}: {key} {value} is not in {lo}..{hi}")
            values[key] = value
    return SerialSpec(path, values["baud"], values["reset_wait_ms"])
