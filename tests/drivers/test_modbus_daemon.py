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
        with Client(str(sock), timeout_ns=10_000 * MS) as c:
            time.sleep(0.2)  # a poll or two
            rec = c.switch()
            assert rec["temperature_c"] == pytest.approx(31.25)
            assert rec["frequency_hz"] == pytest.approx(40_500)
            drive = c.set_drive(frequency_hz=39_800.0, voltage_vpp=500.0)
            assert drive["frequency_hz"] == 39_800.0 and drive["voltage_vpp"] == 500.0
            assert board.state.frequency_hz == 39_800
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
