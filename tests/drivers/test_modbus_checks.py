"""A drive board that lies (issue 29, item 5): readings outside the board's documented ranges are
rejected and counted, the records keep null, and its fault bits latch the daemon's FAULT with the
drive off. A real pymodbus server on loopback; the daemon as a subprocess."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from boardsim import BoardServer
from daemonproc import daemon_args, spawn, stop, wait_serving

from usmswitch.client import Client, Faulted
from usmswitch.drivers import EventKind, FaultCode, VirtualClock
from usmswitch.drivers.modbus_board import BoardStatus, ModbusBoard

#: What the issue saw: -327.68 C, 65,535 Hz, 65,535 Vpp, OVERTEMP | OVERCURRENT | FAULT.
BROKEN = [0x8000, 0x01 | 0x04 | 0x08 | 0x10, 0xFFFF, 0xFFFF]


@pytest.fixture
def board():
    srv = BoardServer("tcp").start()
    yield srv
    srv.stop()


def test_out_of_range_readings_are_unknown_and_fault_bits_are_a_drive_fault(board: BoardServer) -> None:
    with ModbusBoard(f"tcp:127.0.0.1:{board.port}?timeout_ms=300", clock=VirtualClock(1)) as mb:
        mb.configure(40_000, 500, enable=True)
        good = mb.read()
        assert good.temperature_c == pytest.approx(25.0) and good.frequency_hz == 40_000
        assert mb.take_events() == [] and mb.take_status_faults() == []
        board.state.raw_inputs = BROKEN
        bad = mb.read()
        assert (bad.temperature_c, bad.frequency_hz, bad.voltage_vpp) == (None, None, None)
        assert mb.rejected_readings == 3
        assert bad.status & BoardStatus.OVERTEMP and bad.status & BoardStatus.FAULT
        (why,) = mb.take_status_faults()
        assert "OVERTEMP|OVERCURRENT|FAULT" in why
        (ev,) = mb.take_events()
        assert ev.kind is EventKind.FAULT and ev.fault is FaultCode.DRIVE
        mb.read()  # the same bits again: no second fault
        assert mb.take_status_faults() == [] and mb.rejected_readings == 6
        board.state.raw_inputs = None
        assert mb.read().temperature_c == pytest.approx(25.0)
        board.state.status_bits = 0x08
        mb.read()
        assert "OVERCURRENT" in mb.take_status_faults()[0]


def test_the_daemon_latches_the_boards_fault_bits_and_records_null_not_nonsense(
    tmp_path: Path, board: BoardServer
) -> None:
    cfg = tmp_path / "d.toml"
    cfg.write_text(f'[modbus]\nenabled = true\nurl = "tcp:127.0.0.1:{board.port}"\npoll_interval = "20ms"\n')
    proc = spawn(daemon_args(tmp_path, "--no-autostart", "--config", str(cfg), "--period", "25ms"))
    try:
        wait_serving(tmp_path / "d.sock", proc)
        with Client(str(tmp_path / "d.sock"), timeout=10) as rig:
            time.sleep(0.1)
            assert rig.switch()["temperature_c"] == pytest.approx(25.0)
            rig.start_cycling("25ms", 0)
            time.sleep(0.2)
            board.state.raw_inputs = BROKEN
            deadline = time.monotonic() + 5
            while rig.status()["state"] != "fault":
                assert time.monotonic() < deadline, "the board's fault bits did not latch FAULT"
                time.sleep(0.02)
            status = rig.status()
            assert "drive board fault" in status["fault"] and "OVERTEMP|OVERCURRENT|FAULT" in status["fault"]
            with pytest.raises(Faulted):  # no stroke until a person resets it
                rig.switch()
            recs = rig.history(50)
            assert all(r["temperature_c"] is None or -40 <= r["temperature_c"] <= 150 for r in recs)
            assert all(r["frequency_hz"] is None or r["frequency_hz"] < 60_000 for r in recs)
    finally:
        stop(proc)
    assert proc.returncode == 0
