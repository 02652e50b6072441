"""The systemd files: the unit verifies cleanly and is hardened, sysusers creates the user, the rest agree."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from usmswitch.daemon.config import UsbConfig, load_config
from usmswitch.daemon.sockdir import client_socket_paths

ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed (apt: systemd)")


@pytest.fixture
def unit(repo_root: Path) -> Path:
    return repo_root / "systemd" / "usmswitchd.service"


def unit_settings(path: Path) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in path.read_text().splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            out.setdefault(key.strip(), []).append(value.strip())
    return out


@needs_analyze
def test_unit_verifies_with_empty_stderr(unit: Path, tmp_path: Path):
    # verify insists that ExecStart's binary exists. The unit names the packaged /usr/bin/usmswitchd,
    # which this checkout does not install, so verify a copy that points at this venv's entry point
    # (the same program); every other line is verified as shipped.
    binary = Path(sys.executable).parent / "usmswitchd"
    if not binary.exists():
        binary = Path(shutil.which("true") or "/bin/true")
    text = unit.read_text()
    assert "ExecStart=/usr/bin/usmswitchd --config /etc/usmswitch/usmswitchd.toml" in text
    copy = tmp_path / unit.name
    copy.write_text(text.replace("ExecStart=/usr/bin/usmswitchd ", f"ExecStart={binary} "))
    proc = subprocess.run(
        [ANALYZE, "verify", "--man=no", str(copy)], capture_output=True, text=True, timeout=60
    )
    assert proc.stderr == "" and proc.returncode == 0, proc.stderr


@needs_analyze
def test_unit_exposure_is_at_most_3(unit: Path):
    proc = subprocess.run(
        [ANALYZE, "security", "--offline=yes", str(unit)], capture_output=True, text=True, timeout=60
    )
    m = re.search(r"Overall exposure level for usmswitchd\.service: (\d+\.\d+)", proc.stdout)
    assert m, proc.stdout + proc.stderr
    exposure = float(m.group(1))
    print(f"\nsystemd-analyze security: exposure {exposure}")
    assert exposure <= 3.0


def test_unit_agrees_with_the_config_defaults(unit: Path):
    s = unit_settings(unit)
    assert s["Type"] == ["notify"] and s["NotifyAccess"] == ["main"] and s["WatchdogSec"]
    assert s["Restart"] == ["on-failure"]
    assert s["User"] == ["usmswitch"]
    # The daemon's defaults under systemd land in the unit's directories.
    env = {"STATE_DIRECTORY": "/var/lib/usmswitch", "RUNTIME_DIRECTORY": "/run/usmswitch"}
    assert s["StateDirectory"] == ["usmswitch"] and s["RuntimeDirectory"] == ["usmswitch"]
    assert s["ConfigurationDirectory"] == ["usmswitch"]
    cfg = load_config(None, {"driver": "serial"}, env=env)
    assert cfg.socket.path == Path("/run/usmswitch/usmswitchd.sock") in client_socket_paths({})
    assert cfg.daemon.state_dir == Path("/var/lib/usmswitch")
    # The simulated rig's records stay apart from the hardware's.
    assert load_config(None, env=env).daemon.state_dir == Path("/var/lib/usmswitch/sim")
    # The real-time limits the example config relies on.
    assert s["LimitRTPRIO"] == ["99"] and s["LimitMEMLOCK"] == ["infinity"]
    assert "ProtectSystem" in s and s["ProtectSystem"] == ["strict"] and s["DevicePolicy"] == ["closed"]


SYSUSERS = shutil.which("systemd-sysusers")


@pytest.mark.skipif(SYSUSERS is None, reason="systemd-sysusers is not installed")
def test_sysusers_creates_the_service_user(repo_root: Path, tmp_path: Path):
    (tmp_path / "etc").mkdir()
    conf = repo_root / "systemd" / "usmswitch.sysusers"
    proc = subprocess.run(
        [SYSUSERS, f"--root={tmp_path}", str(conf)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    passwd = {
        line.split(":")[0]: line.split(":") for line in (tmp_path / "etc/passwd").read_text().splitlines()
    }
    groups = {
        line.split(":")[0]: line.split(":") for line in (tmp_path / "etc/group").read_text().splitlines()
    }
    user = passwd["usmswitch"]
    assert user[3] == groups["usmswitch"][2]  # primary group usmswitch
    assert user[6] == "/usr/sbin/nologin"
    assert "usmswitch" in groups["dialout"][3].split(",")


def test_udev_rule_matches_the_configured_usb_ids(repo_root: Path):
    rules = [
        line
        for line in (repo_root / "systemd" / "60-usmswitch.rules").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert len(rules) == 2
    vid, pid = f"{UsbConfig.vid:04x}", f"{UsbConfig.pid:04x}"
    for rule in rules:
        pairs = re.findall(r'([A-Z]+(?:\{[^}]+\})?)(==|!=|\+=|:=|=)"([^"]*)"', rule)
        # Every comma-separated clause is a well-formed KEY op "value".
        assert len(pairs) == rule.count(",") + 1, rule
        d = {k: v for k, _, v in pairs}
        assert d.get("ATTRS{idVendor}", d.get("ATTR{idVendor}")) == vid
        assert d.get("ATTRS{idProduct}", d.get("ATTR{idProduct}")) == pid
        assert d["GROUP"] == "usmswitch" and d["MODE"] == "0660"
    assert 'SYMLINK+="usmswitch"' in rules[0]
    assert load_config(None, env={}).driver.serial.port == "/dev/usmswitch"
