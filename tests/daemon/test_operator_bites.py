"""The smaller bites of a new user's first hour (issue 22, part 5), each through the path a user takes:
the daemon as a subprocess, usmswitchctl as a subprocess, the client, the config loader."""

from __future__ import annotations

import importlib.metadata
import os
import subprocess
import sys
import time
from pathlib import Path

import daemonproc
import pytest

import usmswitch
from usmswitch.client import Client, ErrorCode, RpcError, TargetUnreachable, WrongState
from usmswitch.daemon.config import load_config
from usmswitch.drivers.serial_mcu import DEFAULT_BAUD
from usmswitch.protocol.units import parse_duration_ns
from usmswitch.protocol.wire import _BY_CODE

CTL = [sys.executable, "-m", "usmswitch.client.ctl"]
EXIT_CONFIG = 2


def test_a_target_the_rig_cannot_reach_is_refused_at_start_as_set_target_refuses_it(tmp_path: Path) -> None:
    proc = subprocess.run(
        daemonproc.daemon_args(tmp_path, "--target", "5ms"), capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == EXIT_CONFIG
    assert (
        "config error: control.target: target 5.000 ms is below the shortest the rig reaches" in proc.stderr
    )
    assert "Set a target >= " in proc.stderr


def test_usmswitch_socket_naming_a_missing_path_is_an_error_naming_it(tmp_path: Path) -> None:
    missing = tmp_path / "gone.sock"
    env = {**os.environ, "USMSWITCH_SOCKET": str(missing)}
    r = subprocess.run([*CTL, "status"], capture_output=True, text=True, env=env, timeout=30)
    assert r.returncode != 0 and f"$USMSWITCH_SOCKET={missing}" in r.stderr and "does not exist" in r.stderr
    code = "from usmswitch.client import Client\nClient()"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=30)
    assert "FileNotFoundError" in r.stderr and str(missing) in r.stderr


def test_stats_before_the_first_stroke_are_empty_not_an_error(tmp_path: Path) -> None:
    sock = tmp_path / "d.sock"
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, "--no-autostart"))
    try:
        deadline = time.monotonic() + 30
        while not sock.exists():  # the first instant the socket is there, as a script polling for it
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.002)
        with Client(str(sock), timeout=5) as rig:
            stats = rig.stats()
        assert stats["all"]["count"] == 0 and stats["all"]["strokes"] == 0 and stats["run"] is None
    finally:
        log = daemonproc.stop(proc)  # a SIGTERM while the rest may still be starting: a clean exit
    assert proc.returncode == 0, log.decode()[-2000:]


def test_a_bare_number_of_nanoseconds_gets_the_hint_of_its_unit() -> None:
    with pytest.raises(ValueError, match=r"e\.g\. '12ms' \(12000000 ns; or '12000000ns'\)"):
        parse_duration_ns("12000000")
    with pytest.raises(ValueError, match=r"e\.g\. '12ms'$"):
        parse_duration_ns("12")
    r = subprocess.run(
        [*CTL, "--socket", "/nonexistent", "target", "set", "12000000"], capture_output=True, text=True
    )
    assert "12000000ms" not in r.stderr and "'12ms'" in r.stderr


def test_one_baud_rate_the_firmwares_in_the_default_the_example_and_a_flag(repo_root: Path) -> None:
    assert DEFAULT_BAUD == 1_000_000
    assert load_config(None, env={}).driver.serial.baudrate == DEFAULT_BAUD
    example = load_config(repo_root / "systemd" / "usmswitchd.toml", env={})
    assert example.driver.serial.baudrate == DEFAULT_BAUD
    assert load_config(None, {"baudrate": 115_200}, env={}).driver.serial.baudrate == 115_200
    assert "1,000,000 baud" in (repo_root / "docs" / "firmware.md").read_text()


def test_metrics_listen_takes_a_bare_port_in_the_file_as_the_flag_does(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[metrics]\nlisten = 9817\n")
    assert load_config(path, env={}).metrics.listen == "9817"
    assert load_config(None, {"metrics": "9817"}, env={}).metrics.listen == "9817"
    path.write_text("[metrics]\nlisten = 99999\n")
    with pytest.raises(ValueError, match=r"metrics\.listen"):
        load_config(path, env={})


def test_usmswitch_has_a_version() -> None:
    assert usmswitch.__version__ == importlib.metadata.version("usmswitch")


def test_every_error_code_has_its_own_exception() -> None:
    assert set(_BY_CODE) == set(ErrorCode)
    for code, cls in _BY_CODE.items():
        err = RpcError.of(code, "x")
        assert type(err) is cls and isinstance(err, RpcError) and err.code == code
    assert type(RpcError.of(4, "x")) is WrongState and type(RpcError.of(8, "x")) is TargetUnreachable
    assert type(RpcError.of(99, "new")) is RpcError  # a code from a newer daemon


def test_runs_says_it_shows_the_tail_stats_of_a_past_run_its_settings_plot_one_run(tmp_path: Path) -> None:
    sock = tmp_path / "d.sock"
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, "--period", "20ms"))
    try:
        daemonproc.wait_serving(sock, proc)
        with Client(str(sock)) as rig:
            for target in ("12ms", "13ms", "14ms"):
                rig.run(count=6, period="20ms", target=target).wait()
        ctl = [*CTL, "--socket", str(sock)]
        runs = subprocess.run([*ctl, "runs", "-n", "2"], capture_output=True, text=True, check=True).stdout
        with Client(str(sock)) as rig:
            newest = rig.runs(1)[-1]["run_id"]
        assert f"(the last 2 runs; runs 1..{newest - 2} are older: `runs -n N` shows more)" in runs
        with Client(str(sock)) as rig:
            at_12 = next(r["run_id"] for r in rig.runs() if r["settings"].get("target_on_ns") == 12_000_000)
        past = subprocess.run(
            [*ctl, "stats", "--run", str(at_12)], capture_output=True, text=True, check=True
        ).stdout
        assert "state ?" not in past and "T on 12.000 ms / off 12.000 ms (the run's settings)" in past
        for extra in ([], ["--all"]):
            r = subprocess.run(
                [*ctl, "plot", "--out", str(tmp_path / "p.png"), *extra], capture_output=True, text=True
            )
            assert r.returncode == 0, r.stderr
    finally:
        daemonproc.stop(proc)
