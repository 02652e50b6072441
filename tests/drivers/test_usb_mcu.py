"""The USB MCU driver through real pyusb code and a fake pyusb backend wired to the firmware emulator."""

from __future__ import annotations

import errno

import pytest
import usb.core
from mcu_rig import FAST, run_stroke, wait_for

from usmswitch.drivers import DaqDisconnected, Direction, EventKind, FaultCode
from usmswitch.drivers.usb_mcu import UsbMcuDaq, parse_usb_spec
from usmswitch.sim.mcu_emulator import McuEmulator, UsbBackend, UsbDevice


@pytest.fixture
def two_rigs():
    emus = [McuEmulator(seed=s).start() for s in (1, 2)]
    devs = [UsbDevice(emus[0], serial="RIG-A"), UsbDevice(emus[1], serial="RIG-B")]
    yield emus, devs, UsbBackend(*devs)
    for e in emus:
        e.stop()


def test_pyusb_sees_the_emulated_device(two_rigs) -> None:
    _, _, backend = two_rigs
    found = list(usb.core.find(find_all=True, idVendor=0x1209, idProduct=0x0001, backend=backend))
    assert sorted(d.serial_number for d in found) == ["RIG-A", "RIG-B"]


def test_strokes_on_the_device_chosen_by_serial(two_rigs) -> None:
    emus, _, backend = two_rigs
    daq = UsbMcuDaq.from_spec("usb:1209:0001:RIG-B", backend=backend, **FAST)
    with daq:
        d = Direction.ON
        for _ in range(3):
            seen = run_stroke(daq, d)
            assert seen.events[-1].detail == "arrived"
            true_op = emus[1].log[-1].t_arrive_ns - emus[1].log[-1].t_start_ns
            op = seen.edge(d.dest, 1).t_ns - seen.start.t_ns
            assert abs(op - true_op) <= 1_000
            d = d.opposite
    assert emus[1].strokes_arrived == 3 and emus[0].strokes_started == 0


def test_unplug_and_replug(two_rigs) -> None:
    emus, devs, backend = two_rigs
    with UsbMcuDaq(0x1209, 0x0001, "RIG-A", backend=backend, **FAST) as daq:
        run_stroke(daq, Direction.ON)
        devs[0].unplug()
        ev = daq.recv(1_000_000_000)
        while ev is not None and ev.kind is not EventKind.FAULT:
            ev = daq.recv(1_000_000_000)
        assert ev is not None and ev.fault is FaultCode.DISCONNECT and "RIG-A" in ev.detail
        with pytest.raises(DaqDisconnected):
            daq.arm(Direction.OFF, 1_000_000)
        devs[0].replug()
        assert wait_for(lambda: daq.connected)
        seen = run_stroke(daq, Direction.OFF)
        assert seen.events[-1].detail == "arrived"
        assert daq.link_stats()["reconnects"] == 1 and emus[0].boots == 2


def test_absent_device_and_bad_spec(two_rigs) -> None:
    _, _, backend = two_rigs
    with pytest.raises(DaqDisconnected, match="no such device"):
        UsbMcuDaq(0x1209, 0x0001, "RIG-Z", backend=backend).open()
    assert parse_usb_spec("usb:1209:0001") == (0x1209, 0x0001, None)
    assert parse_usb_spec("1209:0001:X") == (0x1209, 0x0001, "X")
    assert parse_usb_spec("usb:1209:0001:AB:CD") == (0x1209, 0x0001, "AB:CD")
    for bad, match in [("usb:1209", "VID:PID"), ("usb:12g9:0001", "hexadecimal"), ("usb:12345:1", "16-bit")]:
        with pytest.raises(ValueError, match=match):
            parse_usb_spec(bad)


class StallingBackend(UsbBackend):
    """The fake backend with endpoint halts: a halted endpoint answers every bulk transfer with
    EPIPE until the host clears it with CLEAR_FEATURE(ENDPOINT_HALT) (pyusb's clear_halt), as a
    device that stalled its pipe does."""

    def __init__(self, *devices: UsbDevice) -> None:
        super().__init__(*devices)
        self.halted: set[int] = set()
        self.clears = 0

    def halt(self, *eps: int) -> None:
        self.halted.update(eps)

    def clear_halt(self, dev_handle: UsbDevice, ep: int) -> None:
        self.clears += 1
        self.halted.discard(ep)

    def _check(self, ep: int) -> None:
        if ep in self.halted:
            raise usb.core.USBError("Pipe error", -9, errno.EPIPE)

    def bulk_write(self, dev_handle, ep, intf, data, timeout):  # type: ignore[no-untyped-def]
        self._check(ep)
        return super().bulk_write(dev_handle, ep, intf, data, timeout)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):  # type: ignore[no-untyped-def]
        self._check(ep)
        return super().bulk_read(dev_handle, ep, intf, buff, timeout)


def test_an_endpoint_halt_is_cleared_and_the_transfer_retried() -> None:
    """Issue 29 item 6: a stall that only CLEAR_FEATURE(ENDPOINT_HALT) clears had failed the
    handshake for good (32 times in 3 s). Now EPIPE is cleared with clear_halt and retried: the
    handshake and the strokes go on, and nothing is reported lost."""
    emu = McuEmulator(seed=4).start()
    dev = UsbDevice(emu, serial="RIG-H")
    backend = StallingBackend(dev)
    try:
        backend.halt(UsbDevice.EP_OUT, UsbDevice.EP_IN)  # halted before the first HELLO
        with UsbMcuDaq(0x1209, 0x0001, "RIG-H", backend=backend, **FAST) as daq:
            assert daq.connected
            run_stroke(daq, Direction.ON)
            backend.halt(UsbDevice.EP_IN)  # and again mid-session
            seen = run_stroke(daq, Direction.OFF)
            assert seen.events[-1].detail == "arrived"
            stats = daq.link_stats()
        assert stats["halts_cleared"] == backend.clears == 3
        assert stats["disconnects"] == 0 and stats["handshake_failures"] == 0
    finally:
        emu.stop()
