"""The MCU emulator behind a pyusb backend, so the `usb` driver runs real pyusb code against it.

`UsbDevice` is one emulated device (vendor class, bulk OUT 0x01 and bulk IN 0x81); `UsbBackend` is
the backend `usb.core.find(backend=...)` enumerates them through, unplug and replug included.
"""

from __future__ import annotations

import array
import errno
import threading
import time

import usb.backend
import usb.core

from .mcu_firmware import FW_VERSION, McuEmulator


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
