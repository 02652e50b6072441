"""The `serial` driver: the rig's microcontroller on a serial port (USB CDC-ACM or a UART adapter).

Config string: `serial:PATH[?baud=N]`, e.g. `serial:/dev/serial/by-id/usb-usmswitch_rig_0001-if00` or
`serial:/dev/ttyACM0?baud=921600`. Use a /dev/serial/by-id path (or a udev symlink such as
/dev/usmswitch): after an unplug the kernel may give the device another ttyACMn, and the driver
reopens by the configured path.
"""

from __future__ import annotations

import errno
import logging
import select
from urllib.parse import parse_qs

import serial

from .mcu import McuDaq, Transport, TransportLost

log = logging.getLogger(__name__)

DEFAULT_BAUD = 921_600
# Linux sets any rate (BOTHER); the firmware's UART decides which work. USB CDC ignores it.
BAUD_RANGE = (50, 20_000_000)


class SerialTransport(Transport):
    """pyserial, opened exclusive and in low-latency mode where the adapter allows it."""

    def __init__(self, path: str, baud: int = DEFAULT_BAUD) -> None:
        if not isinstance(path, str) or not path:
            raise ValueError(f"serial path must be a non-empty string, got {path!r}")
        if isinstance(baud, bool) or not isinstance(baud, int) or not BAUD_RANGE[0] <= baud <= BAUD_RANGE[1]:
            raise ValueError(f"baud must be an integer in {BAUD_RANGE[0]}..{BAUD_RANGE[1]}, got {baud!r}")
        self.path = path
        self.baud = baud
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

    def __init__(self, path: str, baud: int = DEFAULT_BAUD, **kwargs: object) -> None:
        super().__init__(SerialTransport(path, baud), **kwargs)  # type: ignore[arg-type]

    @classmethod
    def from_spec(cls, spec: str, **kwargs: object) -> SerialMcuDaq:
        """Build from a config string `serial:PATH[?baud=N]`."""
        path, baud = parse_serial_spec(spec)
        return cls(path, baud, **kwargs)


def parse_serial_spec(spec: str) -> tuple[str, int]:
    """(path, baud) from `serial:PATH[?baud=N]`; ValueError naming the bad part."""
    if not isinstance(spec, str) or not spec.startswith("serial:"):
        raise ValueError(
            f"serial driver spec must look like 'serial:/dev/ttyACM0[?baud=921600]', got {spec!r}"
        )
    rest = spec[len("serial:") :]
    path, _, query = rest.partition("?")
    if not path:
        raise ValueError(f"serial driver spec {spec!r} has no device path")
    baud = DEFAULT_BAUD
    if query:
        opts = parse_qs(query, keep_blank_values=True, strict_parsing=False)
        unknown = set(opts) - {"baud"}
        if unknown:
            raise ValueError(f"serial driver spec {spec!r}: unknown option(s) {sorted(unknown)}; known: baud")
        if "baud" in opts:
            text = opts["baud"][-1]
            if not text.isdigit():
                raise ValueError(f"serial driver spec {spec!r}: baud must be an integer, got {text!r}")
            baud = int(text)
            if not BAUD_RANGE[0] <= baud <= BAUD_RANGE[1]:
                raise ValueError(
                    f"serial driver spec {spec!r}: baud {baud} is not in {BAUD_RANGE[0]}..{BAUD_RANGE[1]}"
                )
    return path, baud
