"""usmswitchd's command line as a subprocess: --version, --check-config, and the documented exit codes."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from usmswitch.daemon import cli, service
from usmswitch.daemon.config import load_config
from usmswitch.protocol.version import PACKAGE_VERSION
from usmswitch.protocol.wire import PROTOCOL_VERSION

DAEMON = [sys.executable, "-m", "usmswitch.daemon.cli"]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*DAEMON, *args], capture_output=True, text=True, timeout=60, check=False)


def test_version() -> None:
    r = run("--version")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"usmswitchd {PACKAGE_VERSION} (protocol {PROTOCOL_VERSION})"
    assert PACKAGE_VERSION != "0+unknown"  # the test venv installs the package


def test_check_config_prints_the_socket_mode_in_octal(tmp_path: Path) -> None:
    conf = tmp_path / "rig.toml"
    conf.write_text("[socket]\nmode = 0o640\n")
    r = run("--check-config", "--config", str(conf), "--state-dir", str(tmp_path / "s"))
    assert r.returncode == 0, r.stderr
    printed = json.loads(r.stdout)
    assert printed["socket"]["mode"] == "0o640"  # not 416
    # What it prints loads back: the octal text is a mode the loader takes.
    again = load_config(None, {"socket.mode": printed["socket"]["mode"]})
    assert again.socket.mode == 0o640


def test_bad_flag_exits_2() -> None:
    r = run("--order", "nine")
    assert r.returncode == cli.EXIT_CONFIG == 2 and "--order" in r.stderr


def test_every_exit_status_is_documented(repo_root: Path) -> None:
    text = (repo_root / "docs" / "service.md").read_text()
    start = text.index("**Exit status.**")
    section = text[start : text.index("- **", start)]
    documented = {int(m) for m in re.findall(r"^\s*\| (\d+) \|", section, re.M)}
    assert documented == {0, cli.EXIT_CONFIG, cli.EXIT_START, service.EXIT_RECORDS_LOST}


def test_model_flag_takes_every_model_and_names_a_bad_one(tmp_path: Path) -> None:
    from usmswitch.predictor import MODELS

    for model in MODELS:
        r = run("--check-config", "--model", model, "--state-dir", str(tmp_path / "s"))
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout)["control"]["model"] == model
    r = run("--check-config", "--model", "arima")
    assert r.returncode == 2 and "invalid choice: 'arima'" in r.stderr


def test_check_config_refuses_the_target_the_daemon_refuses_at_start(tmp_path: Path) -> None:
    """Issue 37 item 6: `--check-config` passed `target = "5ms"`, which the daemon then refused at
    start (exit 2). One set of checks: the same refusal, the same message, from both."""
    conf = tmp_path / "c.toml"
    conf.write_text('[control]\ntarget = "5ms"\n')
    state = ["--state-dir", str(tmp_path / "s"), "--socket", str(tmp_path / "d.sock"), "--seed", "7"]
    checked = run("--sim", "--check-config", "--config", str(conf), *state)
    started = run("--sim", "--config", str(conf), *state)
    assert checked.returncode == started.returncode == 2, (checked.stderr, started.stderr)
    said = [line for line in checked.stderr.splitlines() if "config error" in line]
    assert said and "control.target: target 5.000 ms is below the shortest the rig reaches" in said[0]
    assert said[0] in started.stderr.splitlines()
    # Hardware with no nominal: nothing known of the rig until its first strokes commission it.
    fine = run("--driver", "serial", "--check-config", "--config", str(conf), *state)
    assert fine.returncode == 0, fine.stderr
