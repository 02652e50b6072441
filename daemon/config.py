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
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

from usmswitch.drivers.mcu import DEFAULT_LINK_TIMEOUT_NS, DEFAULT_REPLY_TIMEOUT_NS, MAX_STROKE_TIMEOUT_NS
from usmswitch.drivers.serial_mcu import DEFAULT_BAUD
from usmswitch.fleet.pg_schema import check_url, redact_url
from usmswitch.predictor import DEFAULT_MODEL, MAX_ORDER, MODELS, check_stroke_ns, min_samples
from usmswitch.predictor.factory import OPTIONS as PREDICTOR_OPTIONS
from usmswitch.protocol.sockets import default_socket_path, weak_token
from usmswitch.protocol.units import format_ns
from usmswitch.server.busy_poll import DEFAULT_WINDOW_NS
from usmswitch.sim import FaultPlan

from .config_values import (
    ConfigError,
    Table,
    bool_value,
    checked_text,
    choice,
    cpu_list,
    default_rig,
    duration,
    duration_at_most,
    duration_in,
    duration_text,
    file_mode_value,
    listen_value,
    nonempty_text,
    order_value,
    parse_host_port,
    parse_modbus_url,
    path_value,
    per_unit,
    positive_duration,
    positive_duration_at_most,
    positive_float,
    priority_value,
    raise_collected,
    rig_name,
    show,
    table_int,
    text_value,
)

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
#: A serial or USB device's reply: past the link's timeout the link is called silent first.
MAX_REPLY_TIMEOUT_NS = DEFAULT_LINK_TIMEOUT_NS
MAX_BUSY_POLL_NS = 10_000_000  # past a script's pace between calls: a core polled for nothing
# Modbus RTU parity (the serial line spec's default is even) and the request timeout's bounds,
# the driver's own (drivers/modbus_board.py: timeout_ms 10..10000).
MODBUS_PARITIES = ("E", "O", "N")
MIN_MODBUS_TIMEOUT_NS = 10_000_000
MAX_MODBUS_TIMEOUT_NS = 10_000_000_000


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
    baudrate: int = DEFAULT_BAUD  # the reference firmware's 1,000,000 (one source: drivers/serial_mcu.py)


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
    # A device's ACK or PONG later than this is a lost frame (resent; a stroke's report unchecked).
    reply_timeout_ns: int = DEFAULT_REPLY_TIMEOUT_NS
    serial: SerialConfig = field(default_factory=SerialConfig)
    usb: UsbConfig = field(default_factory=UsbConfig)


@dataclass(frozen=True)
class SimConfig:
    """[sim]: the simulated rig (driver.kind = "sim")."""

    clock: str = "real"  # "virtual" runs as fast as the CPU goes (tests, experiments)
    seed: int | None = None  # None: a new seed at each start (logged and recorded)
    # [sim.faults]: handed to the sim as it is (sim.FaultPlan.from_config checks it at load).
    faults: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))


@dataclass(frozen=True)
class ControlConfig:
    """[control]: the paper's control law and the stroke's safety limits."""

    target_on_ns: int = 12_000_000  # T for "on" strokes
    target_off_ns: int = 12_000_000  # T for "off" strokes
    mode: str = "closed"  # closed: T_d = T - t_hat (Eq. 7); open: T_d = open_delay
    open_delay_ns: int = 0
    model: str = DEFAULT_MODEL  # any of usmswitch.predictor.MODELS; "paper" is Eq. 2-6 exactly
    order: int | str = 1  # 1..8 or "auto" (AIC, Eq. 8)
    max_order: int = 3  # the highest order "auto" considers (the paper's Table 2 goes to 3)
    window: int = 100  # strokes in the least-squares window, per direction
    nominal_ns: int = 10_500_000  # t_hat before a direction's first stroke (both directions)
    nominal_on_ns: int = 10_500_000  # that of "on" strokes (default: nominal)
    nominal_off_ns: int = 10_500_000  # that of "off" strokes (default: nominal)
    # Which of nominal_on/off the config gave (else the driver's model or a commissioning stroke).
    nominal_given: tuple[bool, bool] = field(default=(False, False), metadata={"derived": True})
    warm_start: int = 100  # strokes per direction reloaded from the records at start (<= window)
    # d ln t per kHz, per 100 V, per C the rig is known to have (usmswitch-experiment drive-sensitivity):
    # the "kalman" model predicts a drive step with them from the first. None: not known, learned.
    sensitivity_frequency: float | None = field(default=None, metadata={"unit": "/kHz"})
    sensitivity_voltage: float | None = field(default=None, metadata={"unit": "/100V"})
    sensitivity_temperature: float | None = field(default=None, metadata={"unit": "/C"})
    stroke_timeout_ns: int = 50_000_000  # no arrival by then: stall, drive off, FAULT
    late_margin_ns: int = 50_000  # a start later than this past command + delay is flagged LATE
    # The plausible band's floor: a shorter operating time is not a stroke (flag IMPLAUSIBLE).
    # 0: 0.3 x the direction's known stroke (the median of its last strokes, else its first guess).
    min_stroke_ns: int = 0

    def target_ns(self, direction: int) -> int:
        """T for a direction (0 on, 1 off)."""
        return self.target_off_ns if direction else self.target_on_ns

    def nominal_for(self, direction: int) -> int:
        """The cold-start t_hat of a direction (0 on, 1 off), before its first stroke."""
        return self.nominal_off_ns if direction else self.nominal_on_ns

    @property
    def sensitivities(self) -> tuple[float | None, float | None, float | None] | None:
        """The configured sensitivities as the predictor takes them; None when none is configured."""
        s = (self.sensitivity_frequency, self.sensitivity_voltage, self.sensitivity_temperature)
        return None if s == (None, None, None) else s


@dataclass(frozen=True)
class CycleConfig:
    """[cycle]: the periodic on/off cycler."""

    autostart: bool | None = None  # None: cycle at start on the sim only (see Config.autostart)
    period_ns: int = 50_000_000  # command to command
    count: int = 0  # strokes to run; 0 = until stopped


@dataclass(frozen=True)
class RealtimeConfig:
    """[realtime]: scheduling of the loop thread (refusals are logged, not fatal)."""

    # "auto": SCHED_FIFO 50 where this process may use it (root, CAP_SYS_NICE, RLIMIT_RTPRIO >= 50),
    # else SCHED_OTHER with a warning; 0 = off; 1..99 = that priority, asked for (refused: a warning).
    sched_fifo_priority: int | str = "auto"
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
    tcp_token: str = ""  # "" with tcp: the daemon makes one at each start (usmswitchd.tcp-token)
    max_clients: int = 64  # Unix socket connections served at once
    max_tcp_clients: int = 8  # TCP connections (authenticated or not) served at once, apart from Unix
    busy_poll_ns: int = DEFAULT_WINDOW_NS  # poll this long after a request while a core is spare; 0 = off


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
class RecordsConfig:
    """[records]: copies of the records beyond this machine (the local SQLite file stays the source)."""

    postgres_url: str = ""  # "" = no shipping; "postgresql://usmswitch@db.lab/usmswitch"
    # Retention (daemon/retention.py): old ended runs moved to records-archive.sqlite; 0 = no limit.
    keep_strokes: int = 0
    keep_days: int = 0
    keep_bytes: int = 0


@dataclass(frozen=True)
class MetricsConfig:
    """[metrics]: the Prometheus page."""

    listen: str = ""  # "" = no page; "127.0.0.1:9817" (a bare port listens on loopback)


@dataclass(frozen=True)
class WebConfig:
    """[web]: the browser panel (docs/panel.md)."""

    listen: str = ""  # "" = no panel; "127.0.0.1:8790" (a bare port listens on loopback)
    # Host names the panel answers to besides loopback's (a reverse proxy's public name); any other
    # Host is refused (DNS rebinding).
    allowed_hosts: tuple[str, ...] = ()


def _host_names(key: str, v: Any) -> tuple[str, ...]:
    """[web] allowed_hosts: a list of host names (no port, no scheme)."""
    if not isinstance(v, list) or not all(isinstance(h, str) for h in v):
        raise ConfigError(key, f'a list of host names, like ["rig-a.lab.example"], got {v!r}')
    for h in v:
        if not h or len(h) > 253 or (any(c in h for c in "/:@ ?#") and not h.startswith("[")):
            raise ConfigError(key, f"{h!r} is not a host name (no port, scheme or path)")
    return tuple(h.lower() for h in v)


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
    records: RecordsConfig = field(default_factory=RecordsConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    web: WebConfig = field(default_factory=WebConfig)

    @property
    def autostart(self) -> bool:
        """Whether to cycle at once: as configured, else on the sim only (a motor never moves unasked)."""
        if self.cycle.autostart is not None:
            return self.cycle.autostart
        return self.driver.kind == "sim"

    def to_dict(self, *, redact: bool = False) -> dict[str, Any]:
        """The configuration as a TOML-shaped dict of plain values (durations as exact text with a
        unit, "12ms"): loads back as is.

        `redact=True` hides the TCP token and the database password, for logs and the status reply.
        """
        out = _section_to_dict(self)
        # A nominal nobody gave stays unset, so that the dict loads back to the same first strokes.
        on, off = self.control.nominal_given
        for key, given in (("nominal", on and off), ("nominal_on", on), ("nominal_off", off)):
            if not given:
                del out["control"][key]
        if redact and out["socket"]["tcp_token"]:
            out["socket"]["tcp_token"] = "<redacted>"
        if redact:
            out["records"]["postgres_url"] = redact_url(out["records"]["postgres_url"])
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
    "postgres": "records.postgres_url",
    "metrics": "metrics.listen",
    "web": "web.listen",
    "baudrate": "driver.serial.baudrate",
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


def _build(raw: dict[str, Any], env: Mapping[str, str]) -> Config:
    top = Table(raw, "")
    t = top.table("driver")
    s, u = t.table("serial"), t.table("usb")
    driver = DriverConfig(
        kind=t.get("kind", choice(DRIVERS), "sim"),
        debounce_ns=t.get("debounce", duration_at_most(MAX_DEBOUNCE_NS), 100_000),
        reply_timeout_ns=t.get(
            "reply_timeout",
            duration_at_most(MAX_REPLY_TIMEOUT_NS, positive=True),
            DriverConfig.reply_timeout_ns,
        ),
        serial=SerialConfig(
            port=s.get("port", nonempty_text, SerialConfig.port),
            baudrate=table_int(s, "baudrate", SerialConfig.baudrate, 50, 20_000_000),
        ),
        usb=UsbConfig(
            vid=table_int(u, "vid", UsbConfig.vid, 0, 0xFFFF),
            pid=table_int(u, "pid", UsbConfig.pid, 0, 0xFFFF),
            serial=u.get("serial", text_value, ""),
        ),
    )
    s.done()
    u.done()
    t.done()

    t = top.table("daemon")
    daemon = DaemonConfig(
        state_dir=t.get("state_dir", path_value, default_state_dir(env, sim=driver.kind == "sim")),
        log_format=t.get("log_format", choice(LOG_FORMATS), "auto"),
        log_level=t.get("log_level", choice(LOG_LEVELS), "info"),
        summary_interval_ns=t.get("summary_interval", positive_duration, 5_000_000_000),
        rig=t.get("rig", rig_name, None) or default_rig(),
    )
    t.done()

    t = top.table("sim")
    t.seen.add("faults")
    faults = t.raw.get("faults", {})
    try:
        FaultPlan.from_config(faults)  # the sim owns the table's shape: its own check, our key
    except ValueError as exc:
        t.fail("faults", str(exc))
        faults = {}
    sim = SimConfig(
        clock=t.get("clock", choice(SIM_CLOCKS), "real"),
        seed=table_int(t, "seed", None, 0, 2**63 - 1),
        faults=MappingProxyType(copy.deepcopy(faults)),
    )
    t.done()

    control = _control(top.table("control"))

    t = top.table("cycle")
    cycle = CycleConfig(
        autostart=t.get("autostart", bool_value, None),
        period_ns=t.get("period", positive_duration, 50_000_000),
        count=table_int(t, "count", 0, 0, None),
    )
    longest = max(control.target_on_ns, control.target_off_ns)
    if cycle.period_ns <= longest:
        t.fail(
            "period",
            f"{format_ns(cycle.period_ns)} is not longer than the target {format_ns(longest)}:"
            " the next command would come before the stroke is due",
        )
    t.done()

    t = top.table("realtime")
    prio = t.get("sched_fifo_priority", priority_value, "auto")
    realtime = RealtimeConfig(
        sched_fifo_priority=prio,
        cpu_affinity=t.get("cpu_affinity", cpu_list, ()),
        mlockall=t.get("mlockall", bool_value, False),
    )
    t.done()

    socket = _socket(top.table("socket"), env)
    modbus = _modbus(top.table("modbus"))

    t = top.table("records")
    # "" (off) or a postgresql:// URL naming a database.
    records = RecordsConfig(
        postgres_url=t.get("postgres_url", checked_text(check_url), ""),
        keep_strokes=table_int(t, "keep_strokes", 0, 0, None) or 0,
        keep_days=table_int(t, "keep_days", 0, 0, 36_500) or 0,
        keep_bytes=t.get("keep_bytes", byte_size, 0),
    )
    t.done()
    t = top.table("metrics")
    # "" (off), "host:port", or a bare port (on loopback).
    metrics = MetricsConfig(listen=t.get("listen", listen_value, ""))
    t.done()
    t = top.table("web")
    # "" (off), "host:port", or a bare port (on loopback).
    web = WebConfig(
        listen=t.get("listen", listen_value, ""), allowed_hosts=t.get("allowed_hosts", _host_names, ())
    )
    t.done()
    top.done()
    if driver.kind in ("serial", "usb") and control.stroke_timeout_ns > MAX_STROKE_TIMEOUT_NS:
        # The microcontroller times the stall itself (ARM timeout_us): it takes 1 ms to 10 s.
        top.fail(
            "control.stroke_timeout",
            f"{format_ns(control.stroke_timeout_ns)} is longer than the microcontroller's longest stall"
            f" limit, {format_ns(MAX_STROKE_TIMEOUT_NS)} (docs/mcu-protocol.md, ARM)",
        )
    raise_collected(top.errors)
    return Config(daemon, driver, sim, control, cycle, realtime, socket, modbus, records, metrics, web)


_BYTE_UNITS = {
    "B": 1,
    "KB": 10**3,
    "MB": 10**6,
    "GB": 10**9,
    "TB": 10**12,
    "KiB": 2**10,
    "MiB": 2**20,
    "GiB": 2**30,
}


def byte_size(key: str, v: object) -> int:
    """A size in bytes: an integer, or text with its unit ("2GB", "500 MiB"); 0 for none."""
    if isinstance(v, int) and not isinstance(v, bool) and v >= 0:
        return v
    if isinstance(v, str):
        num = v.strip().rstrip("".join(sorted({c for u in _BYTE_UNITS for c in u})))
        unit = v.strip()[len(num) :].strip()
        if num.strip().isascii() and num.strip().isdigit() and unit in _BYTE_UNITS:
            return int(num) * _BYTE_UNITS[unit]
    units = ", ".join(_BYTE_UNITS)
    raise ConfigError(
        key, f"expected bytes as an integer or text with a unit ({units}), e.g. '2GB'; got {v!r}"
    )


def _control(t: Table) -> ControlConfig:
    d = ControlConfig()
    target_ns = positive_duration_at_most(MAX_TARGET_NS)
    target = t.get("target", target_ns, None)
    on = t.get("target_on", target_ns, target if target is not None else d.target_on_ns)
    off = t.get("target_off", target_ns, target if target is not None else d.target_off_ns)
    model = t.get("model", choice(MODELS), d.model)
    order = t.get("order", order_value, d.order)
    max_order = table_int(t, "max_order", d.max_order, 1, MAX_ORDER)
    window = table_int(t, "window", d.window, 1, 1_000_000)
    if order == "auto":
        need = min_samples(max_order, model)
        if window < need:
            t.fail(
                "window",
                f"{window} is less than {need}, what order = 'auto' needs with max_order = {max_order}"
                f" and model = {model!r}",
            )
    else:
        if window < order + 2:
            t.fail("window", f"{window} is less than order + 2 = {order + 2}")
        if t.has("max_order") and max_order < order:
            t.fail("max_order", f"{max_order} is less than order = {order}")
    nominal = t.get("nominal", positive_duration, d.nominal_ns)
    nominals = {"nominal": nominal}
    for key in ("nominal_on", "nominal_off"):
        nominals[key] = t.get(key, positive_duration, nominal)
    for key, value in nominals.items():
        try:
            check_stroke_ns(value)
        except ValueError as exc:
            t.fail(key, str(exc))
    sensitivity = {
        "sensitivity_frequency": t.get("sensitivity_frequency", per_unit({"/kHz": 1.0, "/Hz": 1e3}), None),
        "sensitivity_voltage": t.get("sensitivity_voltage", per_unit({"/100V": 1.0, "/V": 1e2}), None),
        "sensitivity_temperature": t.get("sensitivity_temperature", per_unit({"/C": 1.0, "/K": 1.0}), None),
    }
    takes = "sensitivities" in PREDICTOR_OPTIONS[model]
    for key, value in sensitivity.items():
        if value is not None and not takes:
            t.fail(key, f"model = {model!r} takes no sensitivities (the 'kalman' model does)")
    # More than the window would be read and thrown away: take what the predictor can hold.
    warm = min(table_int(t, "warm_start", d.warm_start, 0, None), window)
    timeout = t.get("stroke_timeout", positive_duration, d.stroke_timeout_ns)
    longest = max(nominals.values())
    if timeout <= longest:
        t.fail(
            "stroke_timeout",
            f"{format_ns(timeout)} is not longer than the nominal stroke {format_ns(longest)}:"
            " every stroke would stall",
        )
    cfg = ControlConfig(
        target_on_ns=on,
        target_off_ns=off,
        mode=t.get("mode", choice(MODES), d.mode),
        open_delay_ns=t.get("open_delay", duration_at_most(MAX_TARGET_NS), d.open_delay_ns),
        model=model,
        order=order,
        max_order=max_order,
        window=window,
        nominal_ns=nominal,
        nominal_on_ns=nominals["nominal_on"],
        nominal_off_ns=nominals["nominal_off"],
        nominal_given=(
            t.has("nominal") or t.has("nominal_on"),
            t.has("nominal") or t.has("nominal_off"),
        ),
        warm_start=warm,
        **sensitivity,
        stroke_timeout_ns=timeout,
        late_margin_ns=t.get("late_margin", duration, d.late_margin_ns),
        min_stroke_ns=t.get("min_stroke", duration, d.min_stroke_ns),
    )
    t.done()
    return cfg


def _socket(t: Table, env: Mapping[str, str]) -> SocketConfig:
    mode = t.get("mode", file_mode_value, 0o660)
    group = t.get("group", text_value, "")
    if group:
        try:
            grp.getgrnam(group)
        except KeyError:
            t.fail("group", f"no group named {group!r} on this system")
    tcp = t.get("tcp", text_value, "")
    token = t.get("tcp_token", text_value, "")
    if tcp:
        try:
            parse_host_port(tcp)
        except ValueError as exc:
            t.fail("tcp", str(exc))
        # No token: the daemon makes one at each start (docs/protocol.md, TCP); a weak one is refused.
        why = weak_token(token, MIN_TOKEN_CHARS) if token else None
        if why is not None:
            t.fail("tcp_token", f"too weak: {why}; leave it out and the daemon makes one")
    cfg = SocketConfig(
        path=t.get("path", path_value, default_socket_path(env)),
        mode=mode,
        group=group,
        tcp=tcp,
        tcp_token=token,
        max_clients=table_int(t, "max_clients", SocketConfig.max_clients, 1, 4096),
        max_tcp_clients=table_int(t, "max_tcp_clients", SocketConfig.max_tcp_clients, 1, 1024),
        busy_poll_ns=t.get("busy_poll", duration_at_most(MAX_BUSY_POLL_NS), SocketConfig.busy_poll_ns),
    )
    t.done()
    return cfg


def _modbus(t: Table) -> ModbusConfig:
    url = t.get("url", text_value, ModbusConfig.url)
    try:
        parse_modbus_url(url)
    except ValueError as exc:
        t.fail("url", str(exc))
    cfg = ModbusConfig(
        enabled=t.get("enabled", bool_value, False),
        url=url,
        unit=table_int(t, "unit", 1, 0, 247),
        parity=t.get("parity", choice(MODBUS_PARITIES), ModbusConfig.parity),
        timeout_ns=t.get("timeout", duration_in(MIN_MODBUS_TIMEOUT_NS, MAX_MODBUS_TIMEOUT_NS), 200_000_000),
        frequency_hz=t.get("frequency_hz", positive_float, ModbusConfig.frequency_hz),
        voltage_vpp=t.get("voltage_vpp", positive_float, ModbusConfig.voltage_vpp),
        poll_interval_ns=t.get("poll_interval", positive_duration, ModbusConfig.poll_interval_ns),
        registers=t.get("registers", _register_map, MappingProxyType({})),
    )
    t.done()
    return cfg


def _register_map(key: str, v: Any) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise ConfigError(key, f"expected a table of registers, got {show(v)}")
    from usmswitch.drivers.modbus_board import RegisterMap  # pymodbus only when a map is given

    try:
        RegisterMap.from_dict(v)
    except ValueError as exc:
        raise ConfigError(key, str(exc)) from None
    return MappingProxyType({k: dict(spec) for k, spec in v.items()})


def _section_to_dict(obj: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for fl in fields(obj):
        if fl.metadata.get("derived"):
            continue
        value = getattr(obj, fl.name)
        name = fl.name
        if name.endswith("_ns"):
            name = name[: -len("_ns")]
            if isinstance(value, int):
                value = duration_text(value)  # with its unit, as the loader wants it
        if fl.metadata.get("octal"):
            out[name] = f"0o{value:03o}"
        elif fl.metadata.get("unit") and value is not None:
            out[name] = f"{value!r}{fl.metadata['unit']}"  # exact, with its unit, as the loader wants it
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
    "MetricsConfig",
    "ModbusConfig",
    "RealtimeConfig",
    "RecordsConfig",
    "SerialConfig",
    "SimConfig",
    "SocketConfig",
    "UsbConfig",
    "WebConfig",
    "apply_overrides",
    "default_state_dir",
    "load_config",
    "overrides_from",
]
