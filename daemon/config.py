"""The daemon's configuration: a TOML file (stdlib tomllib) and command-line overrides, checked once.

`load_config(path, overrides)` reads the file, lays dotted overrides ("control.window": 50) over it
and validates everything in one place, so a bad file and a bad flag get the same message naming the
key ("control.window: 3 is less than order + 2 = 4"). The result is a tree of frozen dataclasses;
`apply_overrides(config, window=50)` makes a changed copy through the same checks. With no file, the
defaults run the simulated rig. Durations are human strings with a unit ("12ms", "10500us"; a bare
number is refused as ambiguous); in the dataclasses they are integer ns with `_ns` in the field name.
Reference: docs/config.md.
"""

from __future__ import annotations

import copy
import grp
import os
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from socket import gethostname
from types import MappingProxyType
from typing import Any

from usmswitch.predictor import MAX_ORDER, MODELS, check_stroke_ns, min_samples
from usmswitch.sim import FaultPlan

from .sockdir import default_socket_path
from .units import UNITS_NS, format_ns, parse_duration_ns

DRIVERS = ("sim", "serial", "usb")
SIM_CLOCKS = ("real", "virtual")
LOG_FORMATS = ("auto", "json", "console")
LOG_LEVELS = ("debug", "info", "warning", "error", "critical")
MODES = ("closed", "open")
# A token shorter than this can be guessed by anyone who can reach the TCP port.
MIN_TOKEN_CHARS = 16
# The simulated rig keeps its records apart from the hardware's, below the default state directory.
SIM_STATE_SUBDIR = "sim"
# Bounds that match the socket's checks (docs/protocol.md): a target or a delay past 10 s is a typo.
MAX_TARGET_NS = 10_000_000_000
MAX_DEBOUNCE_NS = 10_000_000
# Modbus RTU parity (the serial line spec's default is even) and the request timeout's bounds,
# the driver's own (drivers/modbus_board.py: timeout_ms 10..10000).
MODBUS_PARITIES = ("E", "O", "N")
MIN_MODBUS_TIMEOUT_NS = 10_000_000
MAX_MODBUS_TIMEOUT_NS = 10_000_000_000
# The socket's mode may give the group read and write, never anything to others or any execute bit.
SOCKET_MODE_ALLOWED = 0o660


class ConfigError(ValueError):
    """A bad configuration value; the message starts with the key ("control.window: ...")."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


# -- default paths ---------------------------------------------------------------------------------
def default_state_dir(env: Mapping[str, str] | None = None, *, sim: bool = False) -> Path:
    """Where records live: $STATE_DIRECTORY (systemd), else $XDG_STATE_HOME/usmswitch, else ~/.local/state.

    `sim=True`: the simulated rig's directory, `<that>/sim`, so simulated strokes never share a file
    (and a warm start) with a real rig's.
    """
    env = os.environ if env is None else env
    if env.get("STATE_DIRECTORY"):
        base = Path(env["STATE_DIRECTORY"].split(":")[0])
    elif env.get("XDG_STATE_HOME"):
        base = Path(env["XDG_STATE_HOME"]) / "usmswitch"
    else:
        base = Path(env.get("HOME") or Path.home()) / ".local" / "state" / "usmswitch"
    return base / SIM_STATE_SUBDIR if sim else base


# -- the configuration tree ------------------------------------------------------------------------
@dataclass(frozen=True)
class DaemonConfig:
    """[daemon]: files and logging."""

    state_dir: Path
    log_format: str = "auto"  # json for the service, console in a terminal; auto picks by isatty
    log_level: str = "info"
    summary_interval_ns: int = 5_000_000_000  # the periodic info line with the running statistics
    rig: str = ""  # this rig's name, stamped on every record ("" only before load: load sets the host name)


@dataclass(frozen=True)
class SerialConfig:
    """[driver.serial]: the microcontroller on a serial port."""

    port: str = "/dev/usmswitch"  # the udev rule's stable name; or /dev/serial/by-id/...
    baudrate: int = 115200  # USB CDC adapters ignore it; a real UART needs the firmware's rate


@dataclass(frozen=True)
class UsbConfig:
    """[driver.usb]: the microcontroller on vendor bulk endpoints."""

    vid: int = 0x1209  # pid.codes; edit to the board's (and in systemd/60-usmswitch.rules)
    pid: int = 0x0001
    serial: str = ""  # "" = the first matching device


@dataclass(frozen=True)
class DriverConfig:
    """[driver]: which DAQ the loop runs on."""

    kind: str = "sim"
    debounce_ns: int = 100_000
    serial: SerialConfig = field(default_factory=SerialConfig)
    usb: UsbConfig = field(default_factory=UsbConfig)


@dataclass(frozen=True)
class SimConfig:
    """[sim]: the simulated rig (driver.kind = "sim")."""

    clock: str = "real"  # "virtual" runs as fast as the CPU goes (tests, experiments)
    seed: int = 1
    # [sim.faults]: handed to the sim as it is (sim.FaultPlan.from_config checks it at load).
    faults: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))


@dataclass(frozen=True)
class ControlConfig:
    """[control]: the paper's control law and the stroke's safety limits."""

    target_on_ns: int = 12_000_000  # T for "on" strokes
    target_off_ns: int = 12_000_000  # T for "off" strokes
    mode: str = "closed"  # closed: T_d = T - t_hat (Eq. 7); open: T_d = open_delay
    open_delay_ns: int = 0
    model: str = "paper"  # paper: Eq. 2, no intercept; centered: with an intercept
    order: int | str = 1  # 1..8 or "auto" (AIC, Eq. 8)
    max_order: int = 3  # the highest order "auto" considers (the paper's Table 2 goes to 3)
    window: int = 100  # strokes in the least-squares window, per direction
    nominal_ns: int = 10_500_000  # t_hat until the window holds enough strokes
    warm_start: int = 100  # strokes per direction reloaded from the records at start (<= window)
    stroke_timeout_ns: int = 50_000_000  # no arrival by then: stall, drive off, FAULT
    late_margin_ns: int = 50_000  # a start later than this past command + delay is flagged LATE

    def target_ns(self, direction: int) -> int:
        """T for a direction (0 on, 1 off)."""
        return self.target_off_ns if direction else self.target_on_ns


@dataclass(frozen=True)
class CycleConfig:
    """[cycle]: the periodic on/off cycler."""

    autostart: bool | None = None  # None: cycle at start on the sim only (see Config.autostart)
    period_ns: int = 50_000_000  # command to command
    count: int = 0  # strokes to run; 0 = until stopped


@dataclass(frozen=True)
class RealtimeConfig:
    """[realtime]: scheduling of the loop thread (refusals are logged, not fatal)."""

    sched_fifo_priority: int = 0  # 0 = off, else 1..99
    cpu_affinity: tuple[int, ...] = ()  # () = leave as is
    mlockall: bool = False


@dataclass(frozen=True)
class SocketConfig:
    """[socket]: the msgpack-RPC server."""

    path: Path
    # Written back as octal text ("0o660", what the file says): 432 means nothing to a reader.
    mode: int = field(default=0o660, metadata={"octal": True})
    group: str = ""  # "" = the daemon's own group
    tcp: str = ""  # "" = no TCP; "127.0.0.1:7770"
    tcp_token: str = ""  # required with tcp
    max_clients: int = 64  # Unix socket connections served at once
    max_tcp_clients: int = 8  # TCP connections (authenticated or not) served at once, apart from Unix


@dataclass(frozen=True)
class ModbusConfig:
    """[modbus]: the USM drive board (frequency, voltage, temperature)."""

    enabled: bool = False
    url: str = "tcp:127.0.0.1:502"  # or "rtu:/dev/ttyUSB1:19200"
    unit: int = 1
    parity: str = "E"  # RTU only: "E" (even, the Modbus serial line default), "O" or "N"
    timeout_ns: int = 200_000_000  # one request's answer; a dead board costs this per poll
    frequency_hz: float = 40_000.0
    voltage_vpp: float = 500.0
    poll_interval_ns: int = 1_000_000_000  # temperature and status reads, off the timing path
    # [modbus.registers]: moves registers of docs/modbus.md's map, e.g. temperature = {address = 10}
    registers: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))


@dataclass(frozen=True)
class Config:
    """The whole configuration, one frozen dataclass per TOML section."""

    daemon: DaemonConfig
    driver: DriverConfig
    sim: SimConfig
    control: ControlConfig
    cycle: CycleConfig
    realtime: RealtimeConfig
    socket: SocketConfig
    modbus: ModbusConfig

    @property
    def autostart(self) -> bool:
        """Whether to cycle at once: as configured, else on the sim only (a motor never moves unasked)."""
        if self.cycle.autostart is not None:
            return self.cycle.autostart
        return self.driver.kind == "sim"

    def to_dict(self, *, redact: bool = False) -> dict[str, Any]:
        """The configuration as a TOML-shaped dict of plain values (durations as exact text with a
        unit, "12ms"): loads back as is.

        `redact=True` hides the TCP token, for logs and the status reply.
        """
        out = _section_to_dict(self)
        if redact and out["socket"]["tcp_token"]:
            out["socket"]["tcp_token"] = "<redacted>"
        return out


# -- loading ---------------------------------------------------------------------------------------
def load_config(
    path: str | Path | None = None,
    overrides: Mapping[str, Any] | None = None,
    env: Mapping[str, str] | None = None,
) -> Config:
    """Read a TOML file (None: defaults only), lay `overrides` over it, and validate it all.

    `overrides` takes dotted keys ("control.window") and the flag names of `OVERRIDE_KEYS`; None
    values are skipped, so the CLI can pass `vars(args)` minus `config`.
    """
    raw: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            with p.open("rb") as f:
                raw = tomllib.load(f)
        except FileNotFoundError:
            raise ConfigError("", f"config file {p} does not exist") from None
        except OSError as exc:
            raise ConfigError("", f"config file {p}: {exc.strerror or exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", f"config file {p}: {exc}") from None
    for key, value in overrides_from(**(overrides or {})).items():
        _set_dotted(raw, key, value)
    return _build(raw, os.environ if env is None else env)


# Short names for the command-line flags the daemon offers (the lead's cli.py passes vars(args)).
OVERRIDE_KEYS: dict[str, str] = {
    "driver": "driver.kind",
    "port": "driver.serial.port",
    "state_dir": "daemon.state_dir",
    "rig": "daemon.rig",
    "log_format": "daemon.log_format",
    "log_level": "daemon.log_level",
    "socket": "socket.path",
    "tcp": "socket.tcp",
    "target": "control.target",
    "mode": "control.mode",
    "model": "control.model",
    "order": "control.order",
    "window": "control.window",
    "period": "cycle.period",
    "count": "cycle.count",
    "autostart": "cycle.autostart",
    "seed": "sim.seed",
    "sim_clock": "sim.clock",
    "priority": "realtime.sched_fifo_priority",
}


def overrides_from(**kwargs: Any) -> dict[str, Any]:
    """Turn flag-style keywords (`sim=True, window=50`, None = not given) into dotted override keys."""
    out: dict[str, Any] = {}
    for name, value in kwargs.items():
        if value is None:
            continue
        if name == "sim":
            if not isinstance(value, bool):
                raise ConfigError("--sim", f"expected true or false, got {value!r}")
            if value:
                out["driver.kind"] = "sim"
            continue
        key = name if "." in name else OVERRIDE_KEYS.get(name)
        if key is None:
            known = ", ".join(["sim", *OVERRIDE_KEYS])
            raise ConfigError(
                f"--{name.replace('_', '-')}", f"no such setting (known: {known}; or 'section.key')"
            )
        out[key] = value
    return out


def apply_overrides(config: Config, **kwargs: Any) -> Config:
    """A copy of `config` with flag-style (`window=50`) or dotted (`**{"control.window": 50}`) changes."""
    raw = config.to_dict()
    for key, value in overrides_from(**kwargs).items():
        _set_dotted(raw, key, value)
    return _build(raw, os.environ)


def _set_dotted(raw: dict[str, Any], key: str, value: Any) -> None:
    parts = key.split(".")
    if len(parts) < 2 or not all(parts):
        raise ConfigError(key, "an override key must be 'section.key'")
    node = raw
    for i, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(".".join(parts[: i + 1]), f"is a value, not a table: cannot set {key}")
        node = child
    if key == "control.target":
        # A target given on the command line means both directions.
        node.pop("target_on", None)
        node.pop("target_off", None)
    node[parts[-1]] = value


class _Table:
    """One TOML table being read: typed getters that name the key, and a check for unknown keys."""

    def __init__(self, raw: Any, name: str) -> None:
        if not isinstance(raw, dict):
            raise ConfigError(name, f"expected a table, got {_show(raw)}")
        self.raw = raw
        self.name = name
        self.seen: set[str] = set()

    def key(self, k: str) -> str:
        return f"{self.name}.{k}" if self.name else k

    def has(self, k: str) -> bool:
        self.seen.add(k)
        return k in self.raw

    def get(self, k: str, parse: Callable[[str, Any], Any], default: Any) -> Any:
        self.seen.add(k)
        if k not in self.raw:
            return default
        return parse(self.key(k), self.raw[k])

    def table(self, k: str) -> _Table:
        self.seen.add(k)
        return _Table(self.raw.get(k, {}), self.key(k))

    def done(self) -> None:
        unknown = sorted(set(self.raw) - self.seen)
        if unknown:
            known = ", ".join(sorted(self.seen))
            where = f"in [{self.name}]" if self.name else "sections"
            raise ConfigError(self.key(unknown[0]), f"unknown key (known {where}: {known})")


def _build(raw: dict[str, Any], env: Mapping[str, str]) -> Config:
    top = _Table(raw, "")
    t = top.table("driver")
    s, u = t.table("serial"), t.table("usb")
    driver = DriverConfig(
        kind=t.get("kind", _choice(DRIVERS), "sim"),
        debounce_ns=t.get("debounce", _duration_max(MAX_DEBOUNCE_NS), 100_000),
        serial=SerialConfig(
            port=s.get("port", _nonempty_str, SerialConfig.port),
            baudrate=_t_int(s, "baudrate", SerialConfig.baudrate, 50, 20_000_000),
        ),
        usb=UsbConfig(
            vid=_t_int(u, "vid", UsbConfig.vid, 0, 0xFFFF),
            pid=_t_int(u, "pid", UsbConfig.pid, 0, 0xFFFF),
            serial=u.get("serial", _str, ""),
        ),
    )
    s.done()
    u.done()
    t.done()

    t = top.table("daemon")
    daemon = DaemonConfig(
        state_dir=t.get("state_dir", _path, default_state_dir(env, sim=driver.kind == "sim")),
        log_format=t.get("log_format", _choice(LOG_FORMATS), "auto"),
        log_level=t.get("log_level", _choice(LOG_LEVELS), "info"),
        summary_interval_ns=t.get("summary_interval", _duration_pos, 5_000_000_000),
        rig=t.get("rig", _rig_name, None) or _default_rig(),
    )
    t.done()

    t = top.table("sim")
    t.seen.add("faults")
    faults = t.raw.get("faults", {})
    try:
        FaultPlan.from_config(faults)  # the sim owns the table's shape: its own check, our key
    except ValueError as exc:
        raise ConfigError("sim.faults", str(exc)) from None
    sim = SimConfig(
        clock=t.get("clock", _choice(SIM_CLOCKS), "real"),
        seed=_t_int(t, "seed", 1, 0, 2**64 - 1),
        faults=MappingProxyType(copy.deepcopy(faults)),
    )
    t.done()

    control = _control(top.table("control"))

    t = top.table("cycle")
    cycle = CycleConfig(
        autostart=t.get("autostart", _bool, None),
        period_ns=t.get("period", _duration_pos, 50_000_000),
        count=_t_int(t, "count", 0, 0, None),
    )
    longest = max(control.target_on_ns, control.target_off_ns)
    if cycle.period_ns <= longest:
        raise ConfigError(
            t.key("period"),
            f"{format_ns(cycle.period_ns)} is not longer than the target {format_ns(longest)}:"
            " the next command would come before the stroke is due",
        )
    t.done()

    t = top.table("realtime")
    prio = _t_int(t, "sched_fifo_priority", 0, 0, 99)
    realtime = RealtimeConfig(
        sched_fifo_priority=prio,
        cpu_affinity=t.get("cpu_affinity", _cpu_list, ()),
        mlockall=t.get("mlockall", _bool, False),
    )
    t.done()

    socket = _socket(top.table("socket"), env)
    modbus = _modbus(top.table("modbus"))
    top.done()
    return Config(daemon, driver, sim, control, cycle, realtime, socket, modbus)


def _control(t: _Table) -> ControlConfig:
    d = ControlConfig()
    target_ns = _duration_pos_max(MAX_TARGET_NS)
    target = t.get("target", target_ns, None)
    on = t.get("target_on", target_ns, target if target is not None else d.target_on_ns)
    off = t.get("target_off", target_ns, target if target is not None else d.target_off_ns)
    model = t.get("model", _choice(MODELS), d.model)
    order = t.get("order", _order, d.order)
    max_order = _t_int(t, "max_order", d.max_order, 1, MAX_ORDER)
    window = _t_int(t, "window", d.window, 1, 1_000_000)
    if order == "auto":
        need = min_samples(max_order, model)
        if window < need:
            raise ConfigError(
                t.key("window"),
                f"{window} is less than {need}, what order = 'auto' needs with max_order = {max_order}"
                f" and model = {model!r}",
            )
    else:
        if window < order + 2:
            raise ConfigError(t.key("window"), f"{window} is less than order + 2 = {order + 2}")
        if t.has("max_order") and max_order < order:
            raise ConfigError(t.key("max_order"), f"{max_order} is less than order = {order}")
    nominal = t.get("nominal", _duration_pos, d.nominal_ns)
    try:
        check_stroke_ns(nominal)
    except ValueError as exc:
        raise ConfigError(t.key("nominal"), str(exc)) from None
    # More than the window would be read and thrown away: take what the predictor can hold.
    warm = min(_t_int(t, "warm_start", d.warm_start, 0, None), window)
    timeout = t.get("stroke_timeout", _duration_pos, d.stroke_timeout_ns)
    if timeout <= nominal:
        raise ConfigError(
            t.key("stroke_timeout"),
            f"{format_ns(timeout)} is not longer than the nominal stroke {format_ns(nominal)}:"
            " every stroke would stall",
        )
    cfg = ControlConfig(
        target_on_ns=on,
        target_off_ns=off,
        mode=t.get("mode", _choice(MODES), d.mode),
        open_delay_ns=t.get("open_delay", _duration_max(MAX_TARGET_NS), d.open_delay_ns),
        model=model,
        order=order,
        max_order=max_order,
        window=window,
        nominal_ns=nominal,
        warm_start=warm,
        stroke_timeout_ns=timeout,
        late_margin_ns=t.get("late_margin", _duration, d.late_margin_ns),
    )
    t.done()
    return cfg


def _socket(t: _Table, env: Mapping[str, str]) -> SocketConfig:
    mode = t.get("mode", _file_mode, 0o660)
    group = t.get("group", _str, "")
    if group:
        try:
            grp.getgrnam(group)
        except KeyError:
            raise ConfigError(t.key("group"), f"no group named {group!r} on this system") from None
    tcp = t.get("tcp", _str, "")
    token = t.get("tcp_token", _str, "")
    if tcp:
        try:
            parse_host_port(tcp)
        except ValueError as exc:
            raise ConfigError(t.key("tcp"), str(exc)) from None
        if not token:
            raise ConfigError(t.key("tcp_token"), "required when socket.tcp is set (clients send it first)")
        if len(token) < MIN_TOKEN_CHARS:
            raise ConfigError(
                t.key("tcp_token"),
                f"{len(token)} characters is too short to resist guessing (>= {MIN_TOKEN_CHARS})",
            )
    cfg = SocketConfig(
        path=t.get("path", _path, default_socket_path(env)),
        mode=mode,
        group=group,
        tcp=tcp,
        tcp_token=token,
        max_clients=_t_int(t, "max_clients", SocketConfig.max_clients, 1, 4096),
        max_tcp_clients=_t_int(t, "max_tcp_clients", SocketConfig.max_tcp_clients, 1, 1024),
    )
    t.done()
    return cfg


def _modbus(t: _Table) -> ModbusConfig:
    url = t.get("url", _str, ModbusConfig.url)
    try:
        parse_modbus_url(url)
    except ValueError as exc:
        raise ConfigError(t.key("url"), str(exc)) from None
    cfg = ModbusConfig(
        enabled=t.get("enabled", _bool, False),
        url=url,
        unit=_t_int(t, "unit", 1, 0, 247),
        parity=t.get("parity", _choice(MODBUS_PARITIES), ModbusConfig.parity),
        timeout_ns=t.get(
            "timeout", _duration_range(MIN_MODBUS_TIMEOUT_NS, MAX_MODBUS_TIMEOUT_NS), 200_000_000
        ),
        frequency_hz=t.get("frequency_hz", _positive_float, ModbusConfig.frequency_hz),
        voltage_vpp=t.get("voltage_vpp", _positive_float, ModbusConfig.voltage_vpp),
        poll_interval_ns=t.get("poll_interval", _duration_pos, ModbusConfig.poll_interval_ns),
        registers=t.get("registers", _register_map, MappingProxyType({})),
    )
    t.done()
    return cfg


def _register_map(key: str, v: Any) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise ConfigError(key, f"expected a table of registers, got {_show(v)}")
    from usmswitch.drivers.modbus_board import RegisterMap  # pymodbus only when a map is given

    try:
        RegisterMap.from_dict(v)
    except ValueError as exc:
        raise ConfigError(key, str(exc)) from None
    return MappingProxyType({k: dict(spec) for k, spec in v.items()})


# -- endpoint strings ------------------------------------------------------------------------------
def parse_host_port(text: str) -> tuple[str, int]:
    """Split "127.0.0.1:7770" or "[::1]:7770" into host and port (0 = any free port)."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"{text!r} is not host:port (e.g. '127.0.0.1:7770')")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not 0 <= int(port) <= 65535:
        raise ValueError(f"{text!r}: port {port} is outside 0..65535")
    return host, int(port)


def parse_modbus_url(url: str) -> tuple[str, str, int]:
    """Split "tcp:host:port" or "rtu:/dev/tty...:baudrate" into (kind, host or device, port or baudrate)."""
    kind, sep, rest = url.partition(":")
    if not sep or kind not in ("tcp", "rtu"):
        raise ValueError(f"{url!r} is not 'tcp:host:port' or 'rtu:/dev/ttyX:baudrate'")
    if kind == "tcp":
        try:
            host, port = parse_host_port(rest)
        except ValueError as exc:
            raise ValueError(f"{url!r}: {exc}") from None
        if port == 0:
            raise ValueError(f"{url!r}: port 0 is not a Modbus server's port")
        return kind, host, port
    device, sep, baud = rest.rpartition(":")
    if not sep or not device.startswith("/") or not baud.isdigit() or int(baud) <= 0:
        raise ValueError(f"{url!r} is not 'rtu:/dev/ttyX:baudrate' (e.g. 'rtu:/dev/ttyUSB1:19200')")
    return kind, device, int(baud)


# -- value parsers: each gets the key for its message ------------------------------------------------
def _show(v: Any) -> str:
    return f"{v!r} ({type(v).__name__})"


def _str(key: str, v: Any) -> str:
    if not isinstance(v, str):
        raise ConfigError(key, f"expected text, got {_show(v)}")
    return v


def _nonempty_str(key: str, v: Any) -> str:
    if not _str(key, v):
        raise ConfigError(key, "must not be empty")
    return v


def _bool(key: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(key, f"expected true or false, got {_show(v)}")
    return v


def _int(key: str, v: Any, lo: int, hi: int | None) -> int:
    # Text is refused, even "100": a quoted number in the file is a mistake worth naming (the
    # command line's integer flags are converted by argparse before they get here).
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(key, f"expected an integer, got {_show(v)}")
    if v < lo or (hi is not None and v > hi):
        bound = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        raise ConfigError(key, f"{v} is outside the allowed range ({bound})")
    return v


def _t_int(t: _Table, k: str, default: int, lo: int, hi: int | None) -> int:
    return t.get(k, lambda key, v: _int(key, v, lo, hi), default)


def _positive_float(key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ConfigError(key, f"expected a number, got {_show(v)}")
    if not v > 0 or v == float("inf"):
        raise ConfigError(key, f"{v} must be a positive finite number")
    return float(v)


def _duration(key: str, v: Any) -> int:
    if isinstance(v, int) and not isinstance(v, bool) and v != 0:
        # A bare number is ambiguous (12 meant as ms would be a 12 ns target): only 0 is safe.
        raise ConfigError(
            key, f'{v} has no unit: write "{v}ms" (or "{v}us", "{v}s", "{v}ns": text with a unit)'
        )
    try:
        return parse_duration_ns(v)
    except ValueError as exc:
        raise ConfigError(key, str(exc)) from None


def _duration_pos(key: str, v: Any) -> int:
    ns = _duration(key, v)
    if ns == 0:
        raise ConfigError(key, f"{v!r} must be longer than 0")
    return ns


def _duration_max(limit_ns: int, positive: bool = False) -> Callable[[str, Any], int]:
    def parse(key: str, v: Any) -> int:
        ns = _duration_pos(key, v) if positive else _duration(key, v)
        if ns > limit_ns:
            raise ConfigError(key, f"{duration_text(ns)} is longer than the limit {duration_text(limit_ns)}")
        return ns

    return parse


def _duration_range(lo_ns: int, hi_ns: int) -> Callable[[str, Any], int]:
    def parse(key: str, v: Any) -> int:
        ns = _duration(key, v)
        if not lo_ns <= ns <= hi_ns:
            raise ConfigError(
                key, f"{duration_text(ns)} is outside {duration_text(lo_ns)}..{duration_text(hi_ns)}"
            )
        return ns

    return parse


def _duration_pos_max(limit_ns: int) -> Callable[[str, Any], int]:
    return _duration_max(limit_ns, positive=True)


def duration_text(ns: int) -> str:
    """Integer ns as the exact text the loader reads back, in the largest unit that divides it."""
    for unit in ("s", "ms", "us"):
        scale = UNITS_NS[unit]
        if ns % scale == 0:
            return f"{ns // scale}{unit}"
    return f"{ns}ns"


def _default_rig() -> str:
    return gethostname() or "localhost"


def _rig_name(key: str, v: Any) -> str:
    name = _str(key, v).strip()
    if not name:
        raise ConfigError(key, "must not be empty (unset it to use the host name)")
    if len(name) > 64 or not name.isprintable():
        raise ConfigError(key, f"{v!r} is not a printable name of at most 64 characters")
    return name


def _choice(choices: tuple[str, ...]) -> Callable[[str, Any], str]:
    def parse(key: str, v: Any) -> str:
        if v not in choices:
            raise ConfigError(key, f"{v!r} is not one of {', '.join(repr(c) for c in choices)}")
        return v

    return parse


def _order(key: str, v: Any) -> int | str:
    if v == "auto":
        return v
    if isinstance(v, str):
        raise ConfigError(key, f"{v!r} is not an order 1..{MAX_ORDER} or 'auto'")
    return _int(key, v, 1, MAX_ORDER)


def _path(key: str, v: Any) -> Path:
    if isinstance(v, Path):
        v = str(v)
    if not _str(key, v):
        raise ConfigError(key, "must not be empty")
    return Path(v).expanduser().absolute()


def _file_mode(key: str, v: Any) -> int:
    if isinstance(v, str):
        if not re.fullmatch(r"(0o?)?[0-7]{1,4}", v.strip()):
            raise ConfigError(key, f"{v!r} is not an octal file mode like 0o660")
        v = int(v.strip().removeprefix("0o"), 8)
    m = _int(key, v, 0, 0o777)
    if m & 0o600 != 0o600:
        raise ConfigError(key, f"{oct(m)} leaves the daemon's own user without read and write")
    if m & ~SOCKET_MODE_ALLOWED:
        raise ConfigError(
            key,
            f"{oct(m)} is looser than {oct(SOCKET_MODE_ALLOWED)}: others may get nothing and nobody"
            " execute (anyone who can connect can stop the rig)",
        )
    return m


def existing_cpus() -> frozenset[int]:
    """The CPU numbers this machine has (those the process may run on, and every configured one)."""
    cpus = set(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else set()
    return frozenset(cpus | set(range(os.cpu_count() or 1)))


def _cpu_list(key: str, v: Any) -> tuple[int, ...]:
    if not isinstance(v, list):
        raise ConfigError(key, f"expected a list of CPU numbers like [2, 3], got {_show(v)}")
    cpus = tuple(_int(f"{key}[{i}]", c, 0, 4095) for i, c in enumerate(v))
    if len(set(cpus)) != len(cpus):
        raise ConfigError(key, f"{list(cpus)} names a CPU twice")
    have = existing_cpus()
    missing = [c for c in cpus if c not in have]
    if missing:
        listed = ", ".join(map(str, sorted(have)))
        raise ConfigError(key, f"CPU {missing[0]} does not exist on this machine (CPUs: {listed})")
    return cpus


def _section_to_dict(obj: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for fl in fields(obj):
        value = getattr(obj, fl.name)
        name = fl.name
        if name.endswith("_ns"):
            name = name[: -len("_ns")]
            if isinstance(value, int):
                value = duration_text(value)  # with its unit, as the loader wants it
        if fl.metadata.get("octal"):
            out[name] = f"0o{value:03o}"
        elif is_dataclass(value):
            out[name] = _section_to_dict(value)
        elif isinstance(value, Path):
            out[name] = str(value)
        elif isinstance(value, Mapping):
            out[name] = copy.deepcopy(dict(value))
        elif isinstance(value, tuple):
            out[name] = list(value)
        elif value is not None:
            out[name] = value
    return out


__all__ = [
    "DRIVERS",
    "OVERRIDE_KEYS",
    "Config",
    "ConfigError",
    "ControlConfig",
    "CycleConfig",
    "DaemonConfig",
    "DriverConfig",
    "ModbusConfig",
    "RealtimeConfig",
    "SerialConfig",
    "SimConfig",
    "SocketConfig",
    "UsbConfig",
    "apply_overrides",
    "default_state_dir",
    "duration_text",
    "existing_cpus",
    "load_config",
    "overrides_from",
    "parse_host_port",
    "parse_modbus_url",
]
