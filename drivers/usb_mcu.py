"""The `usb` driver: the rig's microcontroller as a vendor-class USB device with two bulk endpoints.

The same MCU protocol as `serial` (docs/mcu-protocol.md), the COBS byte stream carried in bulk
transfers. Config string: `usb:VID:PID[:SERIAL]` in hex, e.g. `usb:1209:0001` or
`usb:1209:0001:E6605838` when several rigs share a host. The pyusb backend is injectable
(`backend=`), so tests run the real pyusb code against an emulated device.
"""

from __future__ import annotations

import errno
import logging
from typing import Any

import usb.core
import usb.util

from .mcu import McuDaq
from .mcu_link import Transport, TransportLost

log = logging.getLogger(__name__)

_TIMEOUT_ERRNOS = (errno.ETIMEDOUT,)
_READ_SIZE = 512


class UsbTransport(Transport):
    """pyusb: find by VID/PID/serial, claim the vendor interface, bulk OUT and bulk IN."""

    def __init__(
        self, vid: int, pid: int, serial: str | None = None, *, backend: Any = None, interface: int = 0
    ) -> None:
        for name, v in (("vid", vid), ("pid", pid)):
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 0xFFFF:
                raise ValueError(f"{name} must be a 16-bit integer, got {v!r}")
        if serial is not None and (not isinstance(serial, str) or not serial):
            raise ValueError(f"serial must be a non-empty string or None, got {serial!r}")
        self.vid = vid
        self.pid = pid
        self.serial = serial
        self.backend = backend
        self.interface = interface
        self._dev: Any = None
        self._ep_out: Any = None
        self._ep_in: Any = None
        #: Endpoint halts (EPIPE) cleared with CLEAR_FEATURE(ENDPOINT_HALT) and retried.
        self.halts_cleared = 0

    def describe(self) -> str:
        sn = f" serial {self.serial}" if self.serial else ""
        return f"usb {self.vid:04x}:{self.pid:04x}{sn}"

    def _match(self, dev: Any) -> bool:
        if self.serial is None:
            return True
        try:
            return dev.serial_number == self.serial
        except (usb.core.USBError, ValueError):
            return False  # a device we may not query (permissions): not ours

    def open(self) -> None:
        self.close()
        try:
            dev = usb.core.find(
                idVendor=self.vid, idProduct=self.pid, custom_match=self._match, backend=self.backend
            )
        except (usb.core.NoBackendError, usb.core.USBError) as exc:
            raise TransportLost(f"{self.describe()}: cannot enumerate: {exc}") from exc
        if dev is None:
            raise TransportLost(f"{self.describe()}: no such device")
        try:
            try:
                if dev.is_kernel_driver_active(self.interface):
                    dev.detach_kernel_driver(self.interface)
            except (NotImplementedError, usb.core.USBError):
                pass  # backends without kernel drivers (and the emulator) have nothing to detach
            dev.set_configuration()
            cfg = dev.get_active_configuration()
            intf = cfg[(self.interface, 0)]
            usb.util.claim_interface(dev, self.interface)
            self._ep_out = usb.util.find_descriptor(
                intf,
                custom_match=lambda e: (
                    usb.util.endpoint_direction(e.bEndpointAddress) == usb.util.ENDPOINT_OUT
                    and usb.util.endpoint_type(e.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
                ),
            )
            self._ep_in = usb.util.find_descriptor(
                intf,
                custom_match=lambda e: (
                    usb.util.endpoint_direction(e.bEndpointAddress) == usb.util.ENDPOINT_IN
                    and usb.util.endpoint_type(e.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
                ),
            )
        except (usb.core.USBError, KeyError, IndexError, ValueError) as exc:
            usb.util.dispose_resources(dev)
            raise TransportLost(
                f"{self.describe()}: cannot set up interface {self.interface}: {exc}"
            ) from exc
        if self._ep_out is None or self._ep_in is None:
            usb.util.dispose_resources(dev)
            raise TransportLost(
                f"{self.describe()}: interface {self.interface} lacks a bulk IN/OUT endpoint pair"
            )
        self._dev = dev

    def close(self) -> None:
        dev, self._dev = self._dev, None
        if dev is not None:
            try:
                usb.util.release_interface(dev, self.interface)
            except usb.core.USBError as exc:
                log.debug("%s: release: %s", self.describe(), exc)
            usb.util.dispose_resources(dev)

    def write(self, data: bytes) -> None:
        ep = self._ep_out
        if self._dev is None or ep is None:
            raise TransportLost(f"{self.describe()} is not open")
        for attempt in (0, 1):
            try:
                ep.write(data, timeout=500)
                return
            except usb.core.USBError as exc:
                if attempt == 0 and self._cleared(ep, exc):
                    continue
                raise TransportLost(f"{self.describe()}: bulk write: {exc}") from exc

    def read(self, timeout_ns: int) -> bytes:
        ep = self._ep_in
        if self._dev is None or ep is None:
            raise TransportLost(f"{self.describe()} is not open")
        # pyusb treats 0 as "no timeout": wait at least 1 ms.
        timeout_ms = max(1, timeout_ns // 1_000_000)
        for attempt in (0, 1):
            try:
                return bytes(ep.read(_READ_SIZE, timeout=timeout_ms))
            except usb.core.USBTimeoutError:
                return b""
            except usb.core.USBError as exc:
                if exc.errno in _TIMEOUT_ERRNOS:
                    return b""
                if attempt == 0 and self._cleared(ep, exc):
                    continue
                raise TransportLost(f"{self.describe()}: bulk read: {exc}") from exc
        return b""

    def _cleared(self, ep: Any, exc: usb.core.USBError) -> bool:
        """An endpoint halt (EPIPE: the device stalled the pipe) is cleared with CLEAR_FEATURE
        (ENDPOINT_HALT), as libusb drivers do, and the transfer retried once; False if it was
        not a halt or the clear failed (then the link is lost as for any other error)."""
        if exc.errno != errno.EPIPE or self._dev is None:
            return False
        try:
            self._dev.clear_halt(ep)
        except usb.core.USBError as clear_exc:
            log.warning(
                "%s: endpoint 0x%02x halted, clear failed: %s",
                self.describe(),
                ep.bEndpointAddress,
                clear_exc,
            )
            return False
        self.halts_cleared += 1
        log.warning(
            "%s: endpoint 0x%02x halted (%s): cleared, retrying", self.describe(), ep.bEndpointAddress, exc
        )
        return True


class UsbMcuDaq(McuDaq):
    """The MCU protocol over USB bulk endpoints."""

    name = "usb"

    def __init__(
        self, vid: int, pid: int, serial: str | None = None, *, backend: Any = None, **kwargs: Any
    ) -> None:
        super().__init__(UsbTransport(vid, pid, serial, backend=backend), **kwargs)

    @classmethod
    def from_spec(cls, spec: str, *, backend: Any = None, **kwargs: Any) -> UsbMcuDaq:
        """Build from a config string `usb:VID:PID[:SERIAL]` (hex ids)."""
        vid, pid, serial = parse_usb_spec(spec)
        return cls(vid, pid, serial, backend=backend, **kwargs)


def parse_usb_spec(spec: str) -> tuple[int, int, str | None]:
    """(vid, pid, serial) from `[usb:]VID:PID[:SERIAL]`; ValueError naming the bad part."""
    if not isinstance(spec, str):
        raise ValueError(f"usb driver spec must look like 'usb:1209:0001[:SERIAL]', got {spec!r}")
    parts = spec.removeprefix("usb:").split(":", 2)
    if len(parts) < 2:
        raise ValueError(f"usb driver spec {spec!r}: expected usb:VID:PID[:SERIAL]")
    ids = []
    for name, text in zip(("VID", "PID"), parts[:2], strict=True):
        try:
            v = int(text, 16)
        except ValueError:
            raise ValueError(f"usb driver spec {spec!r}: {name} {text!r} is not hexadecimal") from None
        if not 0 <= v <= 0xFFFF or len(text) > 4:
            raise ValueError(f"usb driver spec {spec!r}: {name} {text!r} is not a 16-bit id")
        ids.append(v)
    serial = parts[2] if len(parts) == 3 else None
    if serial == "":
        raise ValueError(f"usb driver spec {spec!r}: empty serial number")
    return ids[0], ids[1], serial
