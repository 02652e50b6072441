"""What the predictors learned of the drive survives a daemon restart (sensitivities.json), for the
same driver, rig, model and configured sensitivities only."""

from __future__ import annotations

import json
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client
from usmswitch.daemon.sensitivity_memory import SENSITIVITIES_FILE

ARGS = ("--sim-clock", "virtual", "--no-autostart", "--log-level", "info")


def _restored(log: str) -> list[float | None] | None:
    for line in log.splitlines():
        if '"sensitivities restored"' in line:
            return json.loads(line)["sensitivities"]
    return None


def _daemon(tmp: Path, *extra: str, step: bool = False) -> str:
    """Run a daemon; with `step`, 30 cycles at 40 kHz, then 30 at 40.5 kHz. Its log."""
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp, *ARGS, *extra))
    try:
        daemonproc.wait_serving(tmp / "d.sock", proc)
        if step:
            with Client(tmp / "d.sock", timeout=30) as c:
                c.run(count=30, period="25ms", target="12ms").wait()
                c.set_drive(frequency_hz=40_500.0)
                c.run(count=30, period="25ms", target="12ms").wait()
    finally:
        log = daemonproc.stop(proc).decode()
    assert proc.returncode == 0, log[-3000:]
    return log


def test_learned_sensitivities_are_kept_across_a_restart_of_the_same_setup_only(tmp_path: Path) -> None:
    _daemon(tmp_path, step=True)
    path = tmp_path / "state" / SENSITIVITIES_FILE
    saved = json.loads(path.read_text())
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    assert saved["driver"] and saved["rig"] and saved["model"] == "kalman" and saved["configured"] is None
    per_khz, per_100v, _ = saved["sensitivities"]
    assert per_khz == pytest.approx(0.15, abs=0.1)  # the sim's detuning by 500 Hz: ~0.15 per kHz
    assert per_100v is None  # the voltage never stepped: not known

    # The same setup restarts with them (and has nothing new to write).
    assert _restored(_daemon(tmp_path)) == saved["sensitivities"]
    assert json.loads(path.read_text())["saved_wall_ns"] == saved["saved_wall_ns"]

    # Another rig's name, or configured sensitivities (a commissioning): the file is not taken.
    log = _daemon(tmp_path, "--rig", "bench-2")
    assert _restored(log) is None and "learned for another setup" in log
    cfg = tmp_path / "c.toml"
    cfg.write_text('[control]\nsensitivity_frequency = "0.12/kHz"\n')
    log = _daemon(tmp_path, "--config", str(cfg))
    assert _restored(log) is None and "learned for another setup" in log


def test_a_broken_sensitivities_file_is_said_and_the_daemon_starts(tmp_path: Path) -> None:
    (tmp_path / "state").mkdir(mode=0o700)
    (tmp_path / "state" / SENSITIVITIES_FILE).write_text('{"format": 1, "sensitivities": [1, "x"]}')
    log = _daemon(tmp_path)
    assert _restored(log) is None and "sensitivities not restored: bad file" in log
