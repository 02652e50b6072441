"""usmswitchd with a Modbus drive board: set at start and on request, conditions in every record."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from boardsim import BoardServer

from usmswitch.daemon.client import Client, ErrorCode, RpcError

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
    sock = tmp / "d.sock"
    proc = subprocess.Popen(
        [sys.executable, "-m", "usmswitch.daemon.cli", "--sim", "--no-autostart", "--config", str(cfg),
         "--state-dir", str(tmp / "state"), "--socket", str(sock), "--log-format", "json"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )  # fmt: skip
    end = time.monotonic() + 20
    while True:
        assert proc.poll() is None, proc.stderr.read().decode()[-3000:]
        try:
            with Client(str(sock), timeout_ns=5_000 * MS) as c:
                c.stats()
            return proc, sock
        except (OSError, RpcError):
            assert time.monotonic() < end
            time.sleep(0.05)


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
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0
    log = err.decode()
    assert "drive board fault" in log and "drive board answers again" in log
