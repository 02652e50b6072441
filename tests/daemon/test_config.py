"""The TOML configuration: defaults, the example file, overrides, and messages that name the key."""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import pytest

from usmswitch.daemon.config import (
    Config,
    ConfigError,
    apply_overrides,
    client_socket_paths,
    default_socket_path,
    default_state_dir,
    load_config,
    parse_modbus_url,
)

ENV = {"HOME": "/home/lab", "XDG_RUNTIME_DIR": "/run/user/1000"}


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "usmswitchd.toml"
    p.write_text(text)
    return p


def dotted_keys(d: dict, prefix: str = "") -> set[str]:
    out = set()
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and k != "faults":
            out |= dotted_keys(v, key + ".")
        else:
            out.add(key)
    return out


def test_defaults_run_the_simulated_rig_closed_loop_at_12_ms():
    cfg = load_config(None, env=ENV)
    assert cfg.driver.kind == "sim" and cfg.autostart
    assert cfg.control.mode == "closed" and cfg.control.target_ns(0) == cfg.control.target_ns(1) == 12_000_000
    assert cfg.daemon.state_dir == Path("/home/lab/.local/state/usmswitch")
    assert cfg.socket.path == Path("/run/user/1000/usmswitch/usmswitchd.sock")
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.control.window = 3  # type: ignore[misc]


def test_default_paths_follow_systemd_then_xdg_then_home():
    systemd = {"STATE_DIRECTORY": "/var/lib/usmswitch:/var/lib/other", "RUNTIME_DIRECTORY": "/run/usmswitch"}
    assert default_state_dir(systemd) == Path("/var/lib/usmswitch")
    assert default_socket_path(systemd) == Path("/run/usmswitch/usmswitchd.sock")
    assert default_state_dir({"XDG_STATE_HOME": "/x/state"}) == Path("/x/state/usmswitch")
    assert default_socket_path({}) == Path(f"/tmp/usmswitch-{os.getuid()}/usmswitchd.sock")
    paths = client_socket_paths({"USMSWITCH_SOCKET": "/a.sock", **ENV})
    assert paths == [
        Path("/a.sock"),
        Path("/run/user/1000/usmswitch/usmswitchd.sock"),
        Path("/run/usmswitch/usmswitchd.sock"),
    ]


def test_the_example_config_loads_and_documents_every_key(repo_root: Path):
    example = repo_root / "systemd" / "usmswitchd.toml"
    cfg = load_config(example, env=ENV)
    assert cfg.driver.kind == "serial" and not cfg.autostart  # hardware: a motor never moves unasked
    assert cfg.realtime.sched_fifo_priority == 50 and cfg.realtime.mlockall
    assert cfg.daemon.summary_interval_ns == 10_000_000_000
    all_keys = dotted_keys(cfg.to_dict())
    text = example.read_text()
    # Every key appears in the example, set or commented (the two environment-derived paths).
    leaves = {k.split(".")[-1] for k in all_keys} - {"faults"}
    missing = [k for k in sorted(leaves) if not re.search(rf"^#?\s*{k}\s*[=:]", text, re.M)]
    assert "[sim.faults]" in text
    assert missing == []
    docs = (repo_root / "docs" / "config.md").read_text()
    undocumented = [k for k in sorted(leaves | {"target", "faults"}) if f"`{k}`" not in docs]
    assert undocumented == []


def test_file_values_and_units(tmp_path: Path):
    p = write(
        tmp_path,
        """
        [control]
        target_on = "24ms"
        target_off = 12000000
        order = "auto"
        max_order = 4
        window = 200
        model = "centered"
        [cycle]
        period = "0.1s"
        [driver]
        kind = "usb"
        [driver.usb]
        vid = 0xCAFE
        [realtime]
        cpu_affinity = [1, 3]
        [socket]
        mode = 0o640
        tcp = "[::1]:7770"
        tcp_token = "0123456789abcdef"
        [sim.faults.probability]
        bounce = 0.01
        [sim.faults.schedule]
        12 = ["stall"]
        40 = "disconnect"
        """,
    )
    cfg = load_config(p, env=ENV)
    assert (cfg.control.target_on_ns, cfg.control.target_off_ns) == (24_000_000, 12_000_000)
    assert cfg.control.order == "auto" and cfg.control.model == "centered"
    assert cfg.cycle.period_ns == 100_000_000 and not cfg.autostart
    assert cfg.driver.usb.vid == 0xCAFE and cfg.driver.usb.pid == 0x0001
    assert cfg.realtime.cpu_affinity == (1, 3)
    assert cfg.socket.mode == 0o640
    assert cfg.to_dict(redact=True)["socket"]["tcp_token"] == "<redacted>"
    assert cfg.to_dict()["socket"]["tcp_token"] == "0123456789abcdef"
    assert dict(cfg.sim.faults) == {
        "probability": {"bounce": 0.01},
        "schedule": {"12": ["stall"], "40": "disconnect"},
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[control]\nwindow = 3\norder = 2", "control.window: 3 is less than order + 2 = 4"),
        ('[control]\ntarget = "-12ms"', "control.target: duration '-12ms': negative"),
        ("[control]\ntarget = 0", "control.target: 0 must be longer than 0"),
        ('[control]\ntarget = "12"', "control.target: duration '12': needs a unit"),
        ("[control]\norder = 9", "control.order: 9 is outside the allowed range (in 1..8)"),
        ('[control]\norder = "best"', "control.order: 'best' is not an order 1..8 or 'auto'"),
        ('[control]\norder = "auto"\nmax_order = 8\nwindow = 10', "control.window: 10 is less than 18"),
        ('[control]\nmode = "half"', "control.mode: 'half' is not one of 'closed', 'open'"),
        ('[control]\nmodel = "lstm"', "control.model: 'lstm' is not one of 'paper', 'centered'"),
        ("[control]\nwindow = 12.5", "control.window: expected an integer, got 12.5 (float)"),
        ("[control]\nwindow = true", "control.window: expected an integer, got True (bool)"),
        (
            '[control]\nstroke_timeout = "5ms"',
            "control.stroke_timeout: 5.000 ms is not longer than the nominal",
        ),
        ("[control]\nfoo = 1", "control.foo: unknown key (known in [control]: "),
        (
            "[realtime]\nsched_fifo_priority = 100",
            "realtime.sched_fifo_priority: 100 is outside the allowed range",
        ),
        ("[realtime]\ncpu_affinity = [1, 1]", "realtime.cpu_affinity: [1, 1] names a CPU twice"),
        ('[realtime]\nmlockall = "yes"', "realtime.mlockall: expected true or false, got 'yes' (str)"),
        ('[driver]\nkind = "labview"', "driver.kind: 'labview' is not one of 'sim', 'serial', 'usb'"),
        ("[driver.usb]\npid = 70000", "driver.usb.pid: 70000 is outside the allowed range (in 0..65535)"),
        ('[driver.serial]\nport = ""', "driver.serial.port: must not be empty"),
        ('[sim]\nclock = "fast"', "sim.clock: 'fast' is not one of 'real', 'virtual'"),
        (
            '[sim.faults.probability]\nstall = "often"',
            "sim.faults: faults.probability.stall must be a number",
        ),
        ("[sim.faults]\nrain = 1", "sim.faults: faults: unknown key(s) ['rain']"),
        ('[cycle]\nperiod = "10ms"', "cycle.period: 10.000 ms is not longer than the target 12.000 ms"),
        ("[cycle]\ncount = -1", "cycle.count: -1 is outside the allowed range (>= 0)"),
        ('[socket]\ntcp = "127.0.0.1:7770"', "socket.tcp_token: required when socket.tcp is set"),
        (
            '[socket]\ntcp = "localhost"\ntcp_token = "0123456789abcdef"',
            "socket.tcp: 'localhost' is not host:port",
        ),
        (
            '[socket]\ntcp = "127.0.0.1:7770"\ntcp_token = "short"',
            "socket.tcp_token: 5 characters is too short",
        ),
        ("[socket]\nmode = 0o066", "socket.mode: 0o66 leaves the daemon's own user without read and write"),
        ('[socket]\ngroup = "no-such-group-here"', "socket.group: no group named 'no-such-group-here'"),
        ('[modbus]\nurl = "udp:1.2.3.4:502"', "modbus.url: 'udp:1.2.3.4:502' is not 'tcp:host:port'"),
        ("[modbus]\nunit = 300", "modbus.unit: 300 is outside the allowed range (in 0..247)"),
        ("[modbus]\nvoltage_vpp = -5", "modbus.voltage_vpp: -5 must be a positive finite number"),
        ('[daemon]\nlog_level = "verbose"', "daemon.log_level: 'verbose' is not one of"),
        ("daemon = 3", "daemon: expected a table, got 3 (int)"),
        ('[deamon]\nlog_level = "info"', "deamon: unknown key (known sections: "),
    ],
)
def test_bad_values_stop_with_a_message_naming_the_key(tmp_path: Path, text: str, message: str):
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, text), env=ENV)
    assert str(info.value).startswith(message), str(info.value)
    assert info.value.key == message.split(":")[0]


def test_file_errors_name_the_file(tmp_path: Path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.toml")
    bad = write(tmp_path, "[control\nwindow = 3")
    with pytest.raises(ConfigError, match=re.escape(str(bad))):
        load_config(bad)


def test_overrides_from_flags_and_dotted_keys(tmp_path: Path):
    p = write(tmp_path, '[driver]\nkind = "serial"\n[control]\ntarget_on = "24ms"\ntarget_off = "30ms"\n')
    cfg = load_config(
        p, {"sim": True, "window": 50, "log_format": None, "control.late_margin": "20us"}, env=ENV
    )
    assert cfg.driver.kind == "sim" and cfg.autostart
    assert cfg.control.window == 50 and cfg.control.warm_start == 50  # warm start never exceeds the window
    assert cfg.control.late_margin_ns == 20_000
    assert cfg.daemon.log_format == "auto"
    assert (cfg.control.target_on_ns, cfg.control.target_off_ns) == (24_000_000, 30_000_000)
    # A target from the command line means both directions.
    both = apply_overrides(cfg, target="10ms", period="20ms", state_dir=str(tmp_path / "s"), order="2")
    assert (both.control.target_on_ns, both.control.target_off_ns) == (10_000_000, 10_000_000)
    assert both.cycle.period_ns == 20_000_000 and both.control.order == 2
    assert both.daemon.state_dir == tmp_path / "s"
    assert cfg.control.window == 50  # the original is untouched
    with pytest.raises(ConfigError, match=r"control\.window: 3 is less than order"):
        apply_overrides(cfg, window=3, order=2)
    with pytest.raises(ConfigError, match="--frobnicate: no such setting"):
        apply_overrides(cfg, frobnicate=1)
    with pytest.raises(ConfigError, match=r"control\.nope: unknown key"):
        apply_overrides(cfg, **{"control.nope": 1})
    with pytest.raises(ConfigError, match="--sim: expected true or false"):
        apply_overrides(cfg, sim="yes")


def test_to_dict_round_trips_through_the_loader():
    cfg = load_config(None, {"control.order": "auto", "realtime.cpu_affinity": [0]}, env=ENV)
    again = apply_overrides(cfg)
    assert again == cfg
    assert isinstance(again, Config)
    assert "autostart" not in cfg.to_dict()["cycle"]  # None: decided by the driver, not frozen in


def test_explicit_autostart_wins_over_the_driver_rule():
    cfg = load_config(None, {"autostart": False}, env=ENV)
    assert cfg.driver.kind == "sim" and not cfg.autostart
    cfg = load_config(None, {"driver": "serial", "autostart": True}, env=ENV)
    assert cfg.autostart


def test_modbus_urls():
    assert parse_modbus_url("tcp:127.0.0.1:502") == ("tcp", "127.0.0.1", 502)
    assert parse_modbus_url("tcp:[::1]:1502") == ("tcp", "::1", 1502)
    assert parse_modbus_url("rtu:/dev/ttyUSB1:19200") == ("rtu", "/dev/ttyUSB1", 19200)
    for bad in ("rtu:/dev/ttyUSB1", "tcp:host", "tcp:h:0", "rtu:ttyUSB1:9600", "serial:/dev/x:1"):
        with pytest.raises(ValueError, match=re.escape(repr(bad))):
            parse_modbus_url(bad)


def test_modbus_register_map_is_checked_at_load() -> None:
    c = load_config(None, {"modbus.registers": {"temperature": {"table": "holding", "address": 10}}})
    assert dict(c.modbus.registers) == {"temperature": {"table": "holding", "address": 10}}
    with pytest.raises(ConfigError, match=r"modbus\.registers: .*unknown register 'temprature'"):
        load_config(None, {"modbus.registers": {"temprature": {"address": 10}}})
    with pytest.raises(ConfigError, match=r"modbus\.registers"):
        load_config(None, {"modbus.registers": {"enable": {"table": "input"}}})
