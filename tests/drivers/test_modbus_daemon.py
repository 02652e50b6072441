"""usmswitchd with a Modbus drive board: set at start and on request, conditions in every record."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest
from boardsim import BoardServer
from daemonproc import daemon_args, spawn, stop, wait_serving

from usmswitch.client import Client, ErrorCode, RpcError

MS = 1_000_000


@pytest.fixture
def board():
    srv = BoardServer("tcp").start()
    yield srv
    srv.stop()


def start_daemon(tmp: Path, port: int) -> tuple[subprocess.Popen[bytes], Path]:
    cfg = tmp / "d.toml"
    cfg.write_text(
        "[modbus]\nenabled = true\n"
        f'url = "tcp:127.0.0.1:{port}"\nfrequency_hz = 40500.0\nvoltage_vpp = 480.0\npoll_interval = "50ms"\n'
    )
    proc = spawn(daemon_args(tmp, "--no-autostart", "--config", str(cfg)))
    wait_serving(tmp / "d.sock", proc)
    return proc, tmp / "d.sock"


def test_board_set_at_start_on_request_and_read_into_records(tmp_path: Path, board: BoardServer) -> None:
    board.state.temperature_c = 31.25
    proc, sock = start_daemon(tmp_path, board.port)
    try:
        assert (board.state.frequency_hz, board.state.voltage_vpp, board.state.enabled) == (40_500, 480, 1)
        with Client(str(sock), timeout=10) as c:
            time.sleep(0.2)  # a poll or two
            rec = c.switch()
            assert rec["temperature_c"] == pytest.approx(31.25)
            assert rec["frequency_hz"] == pytest.approx(40_500)
            drive = c.set_drive(frequency_hz=39_800.0, voltage_vpp=500.0)
            assert drive["frequency_hz"] == 39_800.0 and drive["voltage_vpp"] == 500.0
            assert board.state.frequency_hz == 39_800
            with pytest.raises(RpcError) as err:  # beyond what the board takes: the caller's error
                c.set_drive(voltage_vpp=5000.0)
            assert err.value.code == ErrorCode.INVALID_PARAMS and "5000" in err.value.message
            # The board stops answering: a logged fault, the daemon and its strokes carry on.
            board.state.hang = True
            with pytest.raises(RpcError) as err:
                c.set_drive(frequency_hz=40_000.0)
            assert err.value.code == ErrorCode.UNAVAILABLE
            time.sleep(0.3)
            rec = c.switch()
            assert rec["t_arrive_ns"] is not None and rec["temperature_c"] is None
            board.state.hang = False
            time.sleep(0.5)
            assert c.switch()["temperature_c"] == pytest.approx(31.25)
    finally:
        err = stop(proc)
    assert proc.returncode == 0
    log = err.decode()
    assert "drive board fault" in log and "drive board answers again" in log


def test_rtu_board_from_the_config_keys(tmp_path: Path) -> None:
    # [modbus] unit, parity and timeout reach the driver: RTU over a pty pair (parity N: a pty
    # refuses even parity, the Modbus default; tests/drivers/test_modbus_board.py checks E and O
    # where they leave us).
    from boardsim import PtyBridge

    bridge = PtyBridge()
    srv = BoardServer("rtu", path=bridge.b, unit=3).start()
    cfg = tmp_path / "d.toml"
    cfg.write_text(
        f'[modbus]\nenabled = true\nurl = "rtu:{bridge.a}:19200"\nunit = 3\nparity = "N"\n'
        'timeout = "500ms"\nfrequency_hz = 40500.0\nvoltage_vpp = 470.0\npoll_interval = "50ms"\n'
    )
    proc = spawn(daemon_args(tmp_path, "--no-autostart", "--config", str(cfg)))
    try:
        wait_serving(tmp_path / "d.sock", proc)
        assert (srv.state.frequency_hz, srv.state.voltage_vpp, srv.state.enabled) == (40_500, 470, 1)
    finally:
        err = stop(proc)
        srv.stop()
        bridge.close()
    assert proc.returncode == 0 and "drive board fault" not in err.decode()


def test_modbus_keys_build_the_driver_spec() -> None:
    from usmswitch.daemon.board import board_spec
    from usmswitch.daemon.config import ConfigError, load_config
    from usmswitch.drivers.modbus_board import ModbusBoard

    cfg = load_config(
        None, {"modbus.url": "rtu:/dev/ttyUSB1:19200", "modbus.unit": 5, "modbus.timeout": "300ms"}
    )
    assert cfg.modbus.parity == "E"  # the Modbus serial line default
    board = ModbusBoard(board_spec(cfg.modbus))
    assert (board.spec.unit, board.spec.parity, board.spec.timeout_ms) == (5, "E", 300)
    assert board._client.comm_params.parity == "E"
    odd = load_config(None, {"modbus.url": "rtu:/dev/ttyUSB1:19200", "modbus.parity": "O"})
    assert ModbusBoard(board_spec(odd.modbus))._client.comm_params.parity == "O"
    tcp = load_config(None, {"modbus.url": "tcp:127.0.0.1:1502"})
    assert "parity" not in board_spec(tcp.modbus)
    with pytest.raises(ConfigError, match=r"modbus\.parity: 'even' is not one of 'E', 'O', 'N'"):
        load_config(None, {"modbus.parity": "even"})
    with pytest.raises(ConfigError, match=r"modbus\.timeout: 20s is outside 10ms\.\.10s"):
        load_config(None, {"modbus.timeout": "20s"})
