"""The TOML configuration: defaults, the example file, overrides, and messages that name the key."""

from __future__ import annotations

import dataclasses
import os
import re
import socket
from pathlib import Path

import pytest

from usmswitch.daemon.config import (
    Config,
    ConfigError,
    apply_overrides,
    default_state_dir,
    load_config,
)
from usmswitch.daemon.config_values import ConfigErrors, parse_listen, parse_modbus_url
from usmswitch.daemon.service import direction_predictors
from usmswitch.predictor import DEFAULT_MODEL
from usmswitch.protocol.sockets import client_socket_paths, default_socket_path

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


def toml_lines(d: dict, prefix: str = "") -> list[str]:
    """A plain dict of str, int, float, bool, lists and tables as TOML (enough for Config.to_dict())."""
    out, tables = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            tables.append((k, v))
        elif isinstance(v, bool):
            out.append(f"{k} = {str(v).lower()}")
        else:
            out.append(f"{k} = {v!r}")
    for k, v in tables:
        out += [f"[{prefix}{k}]", *toml_lines(v, f"{prefix}{k}.")]
    return out


def test_defaults_run_the_simulated_rig_closed_loop_at_12_ms():
    cfg = load_config(None, env=ENV)
    assert cfg.driver.kind == "sim" and cfg.autostart
    assert cfg.control.mode == "closed" and cfg.control.target_ns(0) == cfg.control.target_ns(1) == 12_000_000
    # The simulated rig's records live apart from a real rig's (no warm start from simulated strokes).
    assert cfg.daemon.state_dir == Path("/home/lab/.local/state/usmswitch/sim")
    assert load_config(None, {"driver": "serial"}, env=ENV).daemon.state_dir == Path(
        "/home/lab/.local/state/usmswitch"
    )
    assert cfg.daemon.rig == socket.gethostname()
    assert (cfg.socket.max_clients, cfg.socket.max_tcp_clients) == (64, 8)
    assert cfg.socket.busy_poll_ns == 200_000
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
        target_off = "12000000ns"
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
        cpu_affinity = [1, 0]
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
    assert cfg.realtime.cpu_affinity == (1, 0)
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
        (
            '[control]\nnominal_off = "60ms"',
            "control.stroke_timeout: 50.000 ms is not longer than the nominal stroke 60.000 ms",
        ),
        ('[control]\nnominal_on = "0ms"', "control.nominal_on: '0ms' must be longer than 0"),
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
        # Issue 35: weak tokens refused (no token at all: the daemon makes one).
        ('[socket]\ntcp = "127.0.0.1:7770"\ntcp_token = "aaaaaaaaaaaaaaaa"', "socket.tcp_token: too weak"),
        (
            '[socket]\ntcp = "127.0.0.1:7770"\ntcp_token = "passwordpassword"',
            "socket.tcp_token: too weak: it is 'password' repeated",
        ),
        ('[socket]\ntcp = "127.0.0.1:7770"\ntcp_token = "                "', "socket.tcp_token: too weak"),
        (
            '[socket]\ntcp = "localhost"\ntcp_token = "0123456789abcdef"',
            "socket.tcp: 'localhost' is not host:port",
        ),
        (
            '[socket]\ntcp = "127.0.0.1:7770"\ntcp_token = "short"',
            "socket.tcp_token: too weak: 5 characters is too short",
        ),
        ("[socket]\nmode = 0o066", "socket.mode: 0o66 leaves the daemon's own user without read and write"),
        ('[socket]\ngroup = "no-such-group-here"', "socket.group: no group named 'no-such-group-here'"),
        ('[modbus]\nurl = "udp:1.2.3.4:502"', "modbus.url: 'udp:1.2.3.4:502' is not 'tcp:host:port'"),
        ("[modbus]\nunit = 300", "modbus.unit: 300 is outside the allowed range (in 0..247)"),
        ("[modbus]\nvoltage_vpp = -5", "modbus.voltage_vpp: -5 must be a positive finite number"),
        ('[daemon]\nlog_level = "verbose"', "daemon.log_level: 'verbose' is not one of"),
        # Bounds and types that match the socket's (issue 10).
        ('[control]\ntarget = "10001ms"', "control.target: 10001ms is longer than the limit 10s"),
        ('[control]\ntarget_on = "292y"', "control.target_on: duration '292y': unknown unit"),
        ('[control]\nopen_delay = "11s"', "control.open_delay: 11s is longer than the limit 10s"),
        ('[driver]\ndebounce = "10s"', "driver.debounce: 10s is longer than the limit 10ms"),
        ('[driver]\ndebounce = "10001us"', "driver.debounce: 10001us is longer than the limit 10ms"),
        ("[control]\ntarget = 12", 'control.target: 12 has no unit: write "12ms"'),
        ("[cycle]\nperiod = 50000000", 'cycle.period: 50000000 has no unit: write "50000000ms"'),
        ("[driver]\ndebounce = 100", 'driver.debounce: 100 has no unit: write "100ms"'),
        ('[driver]\nreply_timeout = "401ms"', "driver.reply_timeout: 401ms is longer than the limit 400ms"),
        ("[driver]\nreply_timeout = 25", 'driver.reply_timeout: 25 has no unit: write "25ms"'),
        ('[control]\nwindow = "100"', "control.window: expected an integer, got '100' (str)"),
        ('[control]\norder = "2"', "control.order: '2' is not an order 1..8 or 'auto'"),
        ('[cycle]\ncount = "5"', "cycle.count: expected an integer, got '5' (str)"),
        ("[socket]\nmax_clients = 1.5", "socket.max_clients: expected an integer, got 1.5 (float)"),
        ("[socket]\nmax_tcp_clients = true", "socket.max_tcp_clients: expected an integer, got True"),
        ("[socket]\nmax_tcp_clients = 0", "socket.max_tcp_clients: 0 is outside the allowed range"),
        ("[socket]\nbusy_poll = 200", 'socket.busy_poll: 200 has no unit: write "200ms"'),
        ('[socket]\nbusy_poll = "11ms"', "socket.busy_poll: 11ms is longer than the limit 10ms"),
        ('[sim]\nseed = "7"', "sim.seed: expected an integer, got '7' (str)"),
        ("[realtime]\ncpu_affinity = [999]", "realtime.cpu_affinity: CPU 999 does not exist on this machine"),
        ('[realtime]\ncpu_affinity = "0"', "realtime.cpu_affinity: expected a list of CPU numbers"),
        ('[realtime]\ncpu_affinity = ["0"]', "realtime.cpu_affinity[0]: expected an integer, got '0'"),
        ("[socket]\nmode = 0o777", "socket.mode: 0o777 is looser than 0o660"),
        ("[socket]\nmode = 0o664", "socket.mode: 0o664 is looser than 0o660"),
        ("[socket]\nmode = 0o670", "socket.mode: 0o670 is looser than 0o660"),
        ("[socket]\nmode = 0o760", "socket.mode: 0o760 is looser than 0o660"),
        ('[daemon]\nrig = ""', "daemon.rig: must not be empty"),
        ('[daemon]\nrig = "a\\nb"', "daemon.rig: 'a\\nb' is not a printable name"),
        (
            '[records]\npostgres_url = "mysql://db/x"',
            "records.postgres_url: 'mysql://db/x' is not a PostgreSQL",
        ),
        (
            '[records]\npostgres_url = "postgresql://u:pw@db:5432"',
            "records.postgres_url: 'postgresql://u:***@db",
        ),
        (
            '[records]\npostgres_url = "postgresql://db:port/x"',
            "records.postgres_url: 'postgresql://db:port/x':",
        ),
        ("[records]\npostgres_url = 5", "records.postgres_url: expected text, got 5 (int)"),
        ('[metrics]\nlisten = "localhost"', "metrics.listen: 'localhost' is not host:port"),
        ('[metrics]\nlisten = "127.0.0.1:70000"', "metrics.listen: '127.0.0.1:70000': port 70000 is outside"),
        ('[metrics]\nport = "9817"', "metrics.port: unknown key (known in [metrics]: listen)"),
        (
            "[control]\nsensitivity_frequency = 0.15",
            "control.sensitivity_frequency: 0.15 (float) has no unit",
        ),
        (
            '[control]\nsensitivity_voltage = "-0.2"',
            "control.sensitivity_voltage: '-0.2' is not a number per",
        ),
        ('[control]\nsensitivity_frequency = "0.1/MHz"', "control.sensitivity_frequency: '0.1/MHz' is not"),
        (
            '[control]\nmodel = "paper"\nsensitivity_frequency = "0.1/kHz"',
            "control.sensitivity_frequency: model = 'paper' takes no sensitivities",
        ),
        ("daemon = 3", "daemon: expected a table, got 3 (int)"),
        ('[deamon]\nlog_level = "info"', "deamon: unknown key (known sections: "),
    ],
)
def test_bad_values_stop_with_a_message_naming_the_key(tmp_path: Path, text: str, message: str):
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, text), env=ENV)
    assert str(info.value).startswith(message), str(info.value)
    assert info.value.key == message.split(":")[0]


def test_bounds_at_the_limit_and_tight_socket_modes_are_accepted(tmp_path: Path):
    p = write(
        tmp_path,
        """
        [daemon]
        rig = "bench-3"
        [control]
        target = "10s"
        open_delay = "10s"
        mode = "open"
        [cycle]
        period = "11s"
        [driver]
        debounce = "10ms"
        [socket]
        mode = "0600"
        max_clients = 100
        max_tcp_clients = 2
        busy_poll = "0us"
        """,
    )
    cfg = load_config(p, env=ENV)
    assert cfg.control.target_on_ns == cfg.control.open_delay_ns == 10_000_000_000
    assert cfg.driver.debounce_ns == 10_000_000 and cfg.daemon.rig == "bench-3"
    assert (cfg.socket.mode, cfg.socket.max_clients, cfg.socket.max_tcp_clients) == (0o600, 100, 2)
    assert cfg.socket.busy_poll_ns == 0
    for mode in (0o640, 0o620, 0o660):
        assert load_config(None, {"socket.mode": mode}, env=ENV).socket.mode == mode
    # Zero needs no unit (nothing is ambiguous about it).
    assert load_config(None, {"control.open_delay": 0}, env=ENV).control.open_delay_ns == 0


def test_a_bare_number_from_the_command_line_is_refused_too():
    with pytest.raises(ConfigError, match=r"control\.target: duration \'12\': needs a unit"):
        load_config(None, {"target": "12"}, env=ENV)
    with pytest.raises(ConfigError, match=r'control\.target: 12 has no unit: write "12ms"'):
        load_config(None, {"target": 12}, env=ENV)


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
    both = apply_overrides(cfg, target="10ms", period="20ms", state_dir=str(tmp_path / "s"), order=2)
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


def test_to_dict_round_trips_through_the_loader(tmp_path: Path):
    cfg = load_config(None, {"control.order": "auto", "realtime.cpu_affinity": [0]}, env=ENV)
    again = apply_overrides(cfg)
    assert again == cfg
    # Durations come out as text with their unit, exactly, so the dict loads back from a file too.
    d = cfg.to_dict()
    assert d["control"]["target_on"] == "12ms" and "nominal" not in d["control"]  # not given: a guess
    given = load_config(None, {"control.nominal_off": "9ms"}, env=ENV)
    assert given.control.nominal_given == (False, True) and given.to_dict()["control"]["nominal_off"] == "9ms"
    assert "nominal_on" not in given.to_dict()["control"] and apply_overrides(given) == given
    assert d["daemon"]["summary_interval"] == "5s" and d["control"]["open_delay"] == "0s"
    odd = load_config(None, {"control.late_margin": "1234567ns"}, env=ENV)
    assert odd.to_dict()["control"]["late_margin"] == "1234567ns"
    assert load_config(write(tmp_path, "\n".join(toml_lines(d))), env=ENV) == cfg
    assert isinstance(again, Config)
    assert "autostart" not in cfg.to_dict()["cycle"]  # None: decided by the driver, not frozen in


def test_postgres_url_and_metrics_listen_from_file_and_flags(tmp_path: Path):
    p = write(
        tmp_path, '[records]\npostgres_url = "postgresql://rig:s3cret@db.lab:5433/usm?sslmode=require"\n'
    )
    cfg = load_config(p, env=ENV)
    assert cfg.records.postgres_url == "postgresql://rig:s3cret@db.lab:5433/usm?sslmode=require"
    assert cfg.metrics.listen == ""  # off unless asked
    # The password never reaches a log or the status reply; the URL round-trips unredacted.
    assert (
        cfg.to_dict(redact=True)["records"]["postgres_url"]
        == "postgresql://rig:***@db.lab:5433/usm?sslmode=require"
    )
    assert "s3cret" not in repr(cfg.to_dict(redact=True))
    assert apply_overrides(cfg) == cfg
    flags = load_config(None, {"postgres": "postgres://db/usm", "metrics": "9817"}, env=ENV)
    assert flags.records.postgres_url == "postgres://db/usm" and flags.metrics.listen == "9817"
    assert flags.to_dict(redact=True)["records"]["postgres_url"] == "postgres://db/usm"  # no password: as is
    # A bare port listens on loopback only; anything wider is written out.
    assert parse_listen("9817") == ("127.0.0.1", 9817)
    assert parse_listen("[::1]:9817") == ("::1", 9817) and parse_listen("0.0.0.0:0") == ("0.0.0.0", 0)


def test_web_listen_from_file_and_flag(tmp_path: Path):
    assert load_config(None, env=ENV).web.listen == ""  # no panel unless asked
    cfg = load_config(write(tmp_path, "[web]\nlisten = 8790\n"), env=ENV)
    assert cfg.web.listen == "8790" and parse_listen(cfg.web.listen) == ("127.0.0.1", 8790)
    assert load_config(None, {"web": "[::1]:0"}, env=ENV).web.listen == "[::1]:0"
    assert apply_overrides(cfg) == cfg and cfg.to_dict()["web"] == {"listen": "8790", "allowed_hosts": []}
    with pytest.raises(ConfigError, match=r"web.listen: 'localhost' is not host:port"):
        load_config(write(tmp_path, '[web]\nlisten = "localhost"\n'), env=ENV)
    with pytest.raises(
        ConfigError, match=r"web.port: unknown key \(known in \[web\]: allowed_hosts, listen\)"
    ):
        load_config(write(tmp_path, "[web]\nport = 8790\n"), env=ENV)


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


def test_each_direction_gets_its_own_nominal(tmp_path: Path):
    cfg = load_config(write(tmp_path, '[control]\nnominal = "9ms"\nnominal_off = "8.5ms"'), env=ENV)
    assert (cfg.control.nominal_for(0), cfg.control.nominal_for(1)) == (9_000_000, 8_500_000)
    on, off = direction_predictors(cfg)
    assert (on.predict(), off.predict()) == (9_000_000.0, 8_500_000.0)
    assert cfg.control.model == DEFAULT_MODEL


def test_sensitivities_with_their_units_reach_the_kalman_predictors_and_write_back(tmp_path: Path):
    text = '[control]\nsensitivity_frequency = "150e-6/Hz"\nsensitivity_voltage = "-0.0023/V"\n'
    cfg = load_config(write(tmp_path, text), env=ENV)
    f, v, t = cfg.control.sensitivities
    assert f == pytest.approx(0.15) and v == pytest.approx(-0.23) and t is None
    on, off = direction_predictors(cfg)
    assert on.known_sensitivities == off.known_sensitivities == (f, v, None)
    again = load_config(overrides={f"control.{k}": x for k, x in cfg.to_dict()["control"].items()}, env=ENV)
    assert again.control.sensitivities == cfg.control.sensitivities  # written with the unit, exactly
    assert load_config(env=ENV).control.sensitivities is None  # unset: learned
    # What the predictors learned before (sensitivities.json) is taken over the configured values.
    on, off = direction_predictors(cfg, (0.16, -0.2, 0.01))
    assert on.known_sensitivities == off.known_sensitivities == (0.16, -0.2, 0.01)


def test_every_problem_of_a_file_is_said_at_once(tmp_path: Path) -> None:
    """Issue 37 item 7: errors came one at a time (mend, run, the next one), and an unknown section's
    message listed 8 sections where there are 11. Now every bad value, cross-check and unknown key
    is said in one error, a line each, and the sections listed are all of them."""
    text = (
        '[bogus]\nx = 1\n[control]\nwindow = "big"\nstroke_timeout = "1ms"\n'
        '[cycle]\nperiod = "nope"\n[web]\nlisten = "x:y"\n'
    )
    with pytest.raises(ConfigErrors) as got:
        load_config(write(tmp_path, text), env=ENV)
    keys = [e.key for e in got.value.errors]
    assert keys == ["control.window", "control.stroke_timeout", "cycle.period", "web.listen", "bogus"]
    msg = str(got.value)
    assert msg.startswith("5 problems:\n  control.window: ") and msg.count("\n") == 5
    sections = "control, cycle, daemon, driver, metrics, modbus, realtime, records, sim, socket, web"
    assert f"bogus: unknown key (known sections: {sections})" in msg
    # One problem reads as it always did.
    with pytest.raises(ConfigError, match=r"^cycle\.period: duration 'nope'") as one:
        load_config(write(tmp_path, '[cycle]\nperiod = "nope"\n'), env=ENV)
    assert not isinstance(one.value, ConfigErrors)


def test_the_drivers_reply_timeout_reaches_the_serial_driver(tmp_path: Path) -> None:
    """`[driver] reply_timeout`: a slow link's ACKs and PONGs (a USB-serial adapter's latency
    timer, a loaded test host's fake device) are not lost frames; 25 ms unless set."""
    from usmswitch.daemon.daqfactory import make_daq
    from usmswitch.drivers.mcu import DEFAULT_REPLY_TIMEOUT_NS

    base = {"driver.kind": "serial", "driver.serial.port": str(tmp_path / "no-such-tty")}
    assert make_daq(load_config(None, base, env=ENV)).reply_timeout_ns == DEFAULT_REPLY_TIMEOUT_NS
    cfg = load_config(None, {**base, "driver.reply_timeout": "250ms"}, env=ENV)
    assert cfg.driver.reply_timeout_ns == 250_000_000
    assert make_daq(cfg).reply_timeout_ns == 250_000_000  # built, not opened: no device needed
    with pytest.raises(ConfigError, match=r"driver\.reply_timeout: '0ms' must be longer than 0"):
        load_config(None, {"driver.reply_timeout": "0ms"}, env=ENV)
