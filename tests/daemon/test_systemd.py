"""The systemd files: the unit verifies cleanly and is hardened, sysusers creates the user, the rest agree."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client
from usmswitch.daemon.config import UsbConfig, load_config
from usmswitch.protocol.sockets import client_socket_paths, rig_socket_path

ANALYZE = shutil.which("systemd-analyze") or ""


@pytest.fixture
def analyze() -> str:
    """systemd-analyze; CI installs it (.ci/run: package systemd), so there a missing one fails."""
    if not ANALYZE:
        why = "systemd-analyze is not installed (apt: systemd)"
        if os.environ.get("CI") == "true":
            pytest.fail(f"{why}, but .ci/run installs it")
        pytest.skip(why)
    return ANALYZE


@pytest.fixture
def unit(repo_root: Path) -> Path:
    return repo_root / "systemd" / "usmswitchd.service"


@pytest.fixture
def template(repo_root: Path) -> Path:
    return repo_root / "systemd" / "usmswitchd@.service"


def runnable_copy(unit_file: Path, dest: Path) -> Path:
    """The unit with ExecStart's packaged /usr/bin/usmswitchd replaced by this venv's (verify insists
    that the binary exists); every other line as shipped."""
    binary = Path(sys.executable).parent / "usmswitchd"
    if not binary.exists():
        binary = Path(shutil.which("true") or "/bin/true")
    text = unit_file.read_text()
    assert "ExecStart=/usr/bin/usmswitchd --config /etc/usmswitch/" in text
    dest.mkdir(parents=True, exist_ok=True)
    copy = dest / unit_file.name
    copy.write_text(text.replace("ExecStart=/usr/bin/usmswitchd ", f"ExecStart={binary} "))
    return copy


def unit_settings(path: Path) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in path.read_text().splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            out.setdefault(key.strip(), []).append(value.strip())
    return out


def test_unit_verifies_with_empty_stderr(analyze: str, unit: Path, tmp_path: Path):
    copy = runnable_copy(unit, tmp_path)
    proc = subprocess.run(
        [analyze, "verify", "--man=no", str(copy)], capture_output=True, text=True, timeout=60
    )
    assert proc.stderr == "" and proc.returncode == 0, proc.stderr


def exposure(analyze: str, unit_file: Path, name: str) -> float:
    proc = subprocess.run(
        [analyze, "security", "--offline=yes", str(unit_file)], capture_output=True, text=True, timeout=60
    )
    m = re.search(rf"Overall exposure level for {re.escape(name)}: (\d+\.\d+)", proc.stdout)
    assert m, proc.stdout + proc.stderr
    return float(m.group(1))


def test_unit_exposure_is_at_most_3(analyze: str, unit: Path):
    level = exposure(analyze, unit, "usmswitchd.service")
    print(f"\nsystemd-analyze security: exposure {level}")
    assert level <= 3.0


def test_template_and_an_instance_verify_with_empty_stderr(analyze: str, template: Path, tmp_path: Path):
    copy = runnable_copy(template, tmp_path)
    instance = tmp_path / "usmswitchd@rigA.service"
    instance.symlink_to(copy.name)  # how `systemctl enable usmswitchd@rigA` names it
    for path in (copy, instance):
        proc = subprocess.run(
            [analyze, "verify", "--man=no", str(path)], capture_output=True, text=True, timeout=60
        )
        assert proc.stderr == "" and proc.returncode == 0, (path.name, proc.stderr)
    assert exposure(analyze, instance, "usmswitchd@rigA.service") <= 3.0


def test_template_is_the_one_rig_unit_but_for_the_per_rig_paths(unit: Path, template: Path):
    one, each = unit_settings(unit), unit_settings(template)
    per_rig = {"Description", "ExecStart", "RuntimeDirectory", "StateDirectory"}
    assert {k: v for k, v in each.items() if k not in per_rig} == {
        k: v for k, v in one.items() if k not in per_rig
    }  # the hardening, watchdog, limits and user are the same: a change to one goes to both
    assert each["ExecStart"] == ["/usr/bin/usmswitchd --config /etc/usmswitch/%i.toml --rig %i"]
    assert each["RuntimeDirectory"] == ["usmswitch/%i"] and each["StateDirectory"] == ["usmswitch/%i"]
    assert "%i" in each["Description"][0]
    # The instance's socket is where `usmswitchctl --rig rigA` and $USMSWITCH_RIG look.
    env = {"RUNTIME_DIRECTORY": "/run/usmswitch/rigA", "STATE_DIRECTORY": "/var/lib/usmswitch/rigA"}
    cfg = load_config(None, {"driver": "serial", "rig": "rigA"}, env=env)
    assert cfg.socket.path == rig_socket_path("rigA") == client_socket_paths({"USMSWITCH_RIG": "rigA"})[0]
    assert cfg.daemon.state_dir == Path("/var/lib/usmswitch/rigA") and cfg.daemon.rig == "rigA"


def _instance(template: Path, rig: str, root: Path) -> tuple[list[str], dict[str, str], Path]:
    """ExecStart of usmswitchd@<rig> and the environment systemd gives it, below `root`."""
    (exec_start,) = unit_settings(template)["ExecStart"]
    argv = exec_start.replace("%i", rig).replace("/etc/usmswitch/", f"{root}/etc/").split()
    runtime, state = root / "run" / "usmswitch" / rig, root / "lib" / "usmswitch" / rig
    env = {**os.environ, "RUNTIME_DIRECTORY": str(runtime), "STATE_DIRECTORY": str(state)}
    return [sys.executable, "-m", "usmswitch.daemon.cli", *argv[1:]], env, runtime / "usmswitchd.sock"


def test_two_rigs_run_side_by_side_as_the_template_runs_them(template: Path, short_tmp: Path):
    (short_tmp / "etc").mkdir()
    procs = {}
    try:
        for rig in ("rigA", "rigB"):
            (short_tmp / "etc" / f"{rig}.toml").write_text(
                '[driver]\nkind = "sim"\n[daemon]\nlog_format = "json"\n[cycle]\nautostart = false\n'
            )
            argv, env, sock = _instance(template, rig, short_tmp)
            procs[rig] = (daemonproc.spawn(argv, env=env), sock, argv, env)
        for rig, (proc, sock, _, _) in procs.items():
            daemonproc.wait_serving(sock, proc)
            with Client(str(sock)) as c:
                rec = c.switch("on")
            assert rec["rig"] == rig  # the instance name stamps the records
            state = short_tmp / "lib" / "usmswitch" / rig / "sim"
            assert (state / "records.sqlite").exists() and (state / "usmswitchd.lock").exists()
        # A second daemon for rigA (its state directory is locked) refuses to start: exit 3.
        _, _, argv, env = procs["rigA"]
        second = subprocess.run(
            [*argv, "--socket", str(short_tmp / "other.sock")],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert second.returncode == 3, second.stderr[-2000:]
        assert "in use by another usmswitchd" in second.stderr and "rigA" in second.stderr
    finally:
        for proc, *_ in procs.values():
            err = daemonproc.stop(proc)
            assert proc.returncode == 0, err.decode()[-2000:]


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
