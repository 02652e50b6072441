"""The `modbus` driver: the USM drive board's excitation frequency, voltage, enable and temperature.

Over Modbus RTU (serial) or TCP with pymodbus 3.16. Far too slow to stamp edges: it sets the
drive conditions at start and on request, and reads them outside the timing path for the records.
A board that stops answering raises `BoardError` (a `DaqError`) and queues one FAULT DRIVE event;
it never crashes the caller. The register map is in docs/modbus.md and configurable.

Config strings: `tcp:HOST:PORT[?unit=N&timeout_ms=M]`, `rtu:PATH:BAUD[?unit=N&parity=N|E|O&timeout_ms=M]`.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from enum import IntFlag
from typing import Any, Literal
from urllib.parse import parse_qs

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException

from .clock import Clock, MonotonicClock
from .daq import DaqError
from .events import Conditions, Event, FaultCode

log = logging.getLogger(__name__)

Table = Literal["holding", "input"]
DEFAULT_TIMEOUT_MS = 200


class BoardError(DaqError):
    """The drive board did not answer or refused a request; the message says which and why."""


class BoardStatus(IntFlag):
    """The status register's bits."""

    ENABLED = 0x01
    RUNNING = 0x02
    OVERTEMP = 0x04
    OVERCURRENT = 0x08
    FAULT = 0x10


#: Status bits that mean the board has stopped being a safe drive: each latches a FAULT.
FAULT_BITS = BoardStatus.OVERTEMP | BoardStatus.OVERCURRENT | BoardStatus.FAULT
#: The motor temperature a reading may plausibly have (the sensor's range; outside: a broken
#: sensor or register, never a temperature to record).
TEMPERATURE_RANGE_C = (-40.0, 150.0)


@dataclass(frozen=True)
class Reg:
    """One register: its table, address, the engineering units per count, and signedness."""

    table: Table
    address: int
    scale: float = 1.0
    signed: bool = False

    def __post_init__(self) -> None:
        if self.table not in ("holding", "input"):
            raise ValueError(f"register table must be 'holding' or 'input', got {self.table!r}")
        if (
            isinstance(self.address, bool)
            or not isinstance(self.address, int)
            or not 0 <= self.address <= 0xFFFF
        ):
            raise ValueError(f"register address must be an integer 0..65535, got {self.address!r}")
        if not isinstance(self.scale, int | float) or not self.scale > 0:
            raise ValueError(f"register scale must be a positive number, got {self.scale!r}")

    def to_value(self, raw: int) -> float:
        """Engineering value of a raw 16-bit register."""
        if self.signed and raw >= 0x8000:
            raw -= 0x10000
        return raw * self.scale

    def to_raw(self, value: float, name: str) -> int:
        """Raw 16-bit register for an engineering value; ValueError naming `name` if it does not fit."""
        raw = round(value / self.scale)
        lo, hi = (-0x8000, 0x7FFF) if self.signed else (0, 0xFFFF)
        if not lo <= raw <= hi:
            raise ValueError(f"{name}={value} does not fit its register ({raw} counts, range {lo}..{hi})")
        return raw & 0xFFFF


@dataclass(frozen=True)
class RegisterMap:
    """Where the board keeps each quantity. Defaults: docs/modbus.md."""

    frequency_set: Reg = Reg("holding", 0, 1.0)  # Hz
    voltage_set: Reg = Reg("holding", 1, 1.0)  # Vpp
    enable: Reg = Reg("holding", 2, 1.0)  # 0 / 1
    temperature: Reg = Reg("input", 0, 0.01, signed=True)  # degC
    status: Reg = Reg("input", 1, 1.0)  # BoardStatus bits
    frequency: Reg = Reg("input", 2, 1.0)  # Hz, measured
    voltage: Reg = Reg("input", 3, 1.0)  # Vpp, measured

    def __post_init__(self) -> None:
        for name in ("frequency_set", "voltage_set", "enable"):
            if getattr(self, name).table != "holding":
                raise ValueError(f"register {name} is written, so it must be a holding register")

    @classmethod
    def from_dict(cls, config: Mapping[str, Any]) -> RegisterMap:
        """Override defaults from config, e.g. {"temperature": {"table": "holding", "address": 10}}."""
        known = {f.name for f in fields(cls)}
        changes: dict[str, Reg] = {}
        for name, spec in config.items():
            if name not in known:
                raise ValueError(f"modbus register map: unknown register {name!r}; known: {sorted(known)}")
            if not isinstance(spec, Mapping):
                raise ValueError(f"modbus register map: {name} must be a table of table/address/scale/signed")
            bad = set(spec) - {"table", "address", "scale", "signed"}
            if bad:
                raise ValueError(f"modbus register map: {name}: unknown key(s) {sorted(bad)}")
            try:
                changes[name] = replace(getattr(cls(), name), **dict(spec))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"modbus register map: {name}: {exc}") from None
        return cls(**changes)


@dataclass(frozen=True)
class BoardReading:
    """One poll of the board's measured values."""

    temperature_c: float | None  # None: the register held a value outside its documented range
    frequency_hz: float | None
    voltage_vpp: float | None
    status: BoardStatus


@dataclass(frozen=True)
class ModbusSpec:
    """A parsed `tcp:` / `rtu:` config string."""

    kind: Literal["tcp", "rtu"]
    target: str  # host, or serial path
    port_or_baud: int
    unit: int = 1
    parity: str = "E"  # the Modbus serial line spec's default (RTU; TCP has none)
    timeout_ms: int = DEFAULT_TIMEOUT_MS


def parse_modbus_spec(spec: str) -> ModbusSpec:
    """`tcp:HOST:PORT[?...]` or `rtu:PATH:BAUD[?...]`; ValueError naming the bad part."""
    example = "'tcp:127.0.0.1:5020' or 'rtu:/dev/ttyUSB1:19200', options ?unit=1&timeout_ms=200&parity=E"
    if not isinstance(spec, str):
        raise ValueError(f"modbus spec must be a string like {example}, got {spec!r}")
    kind, sep, rest = spec.partition(":")
    if not sep or kind not in ("tcp", "rtu"):
        raise ValueError(f"modbus spec must start with tcp: or rtu: ({example}), got {spec!r}")
    body, _, query = rest.partition("?")
    target, sep, num = body.rpartition(":")
    if not sep or not target or not num.isdigit():
        what = "PORT" if kind == "tcp" else "BAUD"
        raise ValueError(
            f"modbus spec {spec!r}: expected {kind}:{'HOST' if kind == 'tcp' else 'PATH'}:{what}"
        )
    if kind == "tcp":
        target = target.strip("[]")
        if not 1 <= int(num) <= 65535:
            raise ValueError(f"modbus spec {spec!r}: TCP port {num} is not in 1..65535")
    elif int(num) not in (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400):
        raise ValueError(f"modbus spec {spec!r}: baud {num} is not a standard Modbus RTU rate")
    out = ModbusSpec(kind, target, int(num))  # type: ignore[arg-type]
    if query:
        opts = parse_qs(query, keep_blank_values=True)
        unknown = set(opts) - {"unit", "timeout_ms", "parity"}
        if unknown:
            raise ValueError(f"modbus spec {spec!r}: unknown option(s) {sorted(unknown)}")
        if "unit" in opts:
            u = opts["unit"][-1]
            if not u.isdigit() or not 0 <= int(u) <= 247:
                raise ValueError(f"modbus spec {spec!r}: unit must be 0..247, got {u!r}")
            out = replace(out, unit=int(u))
        if "timeout_ms" in opts:
            t = opts["timeout_ms"][-1]
            if not t.isdigit() or not 10 <= int(t) <= 10_000:
                raise ValueError(f"modbus spec {spec!r}: timeout_ms must be 10..10000, got {t!r}")
            out = replace(out, timeout_ms=int(t))
        if "parity" in opts:
            p = opts["parity"][-1].upper()
            if p not in ("N", "E", "O"):
                raise ValueError(f"modbus spec {spec!r}: parity must be N, E or O, got {p!r}")
            out = replace(out, parity=p)
    return out


class ModbusBoard:
    """The USM drive board: set frequency/voltage/enable, read temperature and status."""

    name = "modbus"

    def __init__(
        self,
        spec: str | ModbusSpec,
        *,
        registers: RegisterMap | None = None,
        clock: Clock | None = None,
        frequency_range_hz: tuple[float, float] = (30_000.0, 50_000.0),
        voltage_max_vpp: float = 600.0,
    ) -> None:
        self.spec = parse_modbus_spec(spec) if isinstance(spec, str) else spec
        self.registers = registers or RegisterMap()
        self.clock = clock or MonotonicClock()
        lo, hi = frequency_range_hz
        if not 0 < lo < hi:
            raise ValueError(
                f"frequency_range_hz must be (low, high) with 0 < low < high, got {frequency_range_hz!r}"
            )
        self.frequency_range_hz = (float(lo), float(hi))
        if not voltage_max_vpp > 0:
            raise ValueError(f"voltage_max_vpp must be > 0, got {voltage_max_vpp!r}")
        self.voltage_max_vpp = float(voltage_max_vpp)
        s = self.spec
        timeout_s = s.timeout_ms / 1000
        if s.kind == "tcp":
            self._client: ModbusTcpClient | ModbusSerialClient = ModbusTcpClient(
                s.target, port=s.port_or_baud, timeout=timeout_s, retries=0, reconnect_delay=0.05
            )
        else:
            self._client = ModbusSerialClient(
                s.target, baudrate=s.port_or_baud, parity=s.parity, timeout=timeout_s, retries=0
            )
        self._lock = threading.Lock()  # one request at a time: the socket thread and the slack path
        self._events: deque[Event] = deque(maxlen=100)
        #: False from a failed request until the next one that succeeds.
        self.ok = True
        #: Requests that failed (no answer, exception response, connection refused).
        self.failures = 0
        #: Readings outside their documented range (rejected: recorded as unknown).
        self.rejected_readings = 0
        self._out_of_range: set[str] = set()
        self._fault_bits = BoardStatus(0)
        self._status_faults: deque[str] = deque(maxlen=16)
        #: Replies that answered another request (late ones, after a timeout): dropped with the link.
        self.stale_replies = 0
        self.last_error = ""
        self.last_reading: BoardReading | None = None

    def describe(self) -> str:
        """Where the board is, for logs and errors."""
        s = self.spec
        return f"modbus {s.kind}:{s.target}:{s.port_or_baud} unit {s.unit}"

    # -- lifecycle ---------------------------------------------------------------------------
    def open(self) -> None:
        """Connect; BoardError if the board cannot be reached."""
        with self._lock:
            if not self._client.connect():
                self._failed(f"cannot connect to {self.describe()}")

    def close(self) -> None:
        """Release the connection. Safe to call twice."""
        with self._lock:
            self._client.close()

    def __enter__(self) -> ModbusBoard:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- setting -----------------------------------------------------------------------------
    def configure(self, frequency_hz: float, voltage_vpp: float, enable: bool = True) -> None:
        """Set the excitation and enable the drive: the daemon's start-up and `set_drive` request."""
        self.set_frequency(frequency_hz)
        self.set_voltage(voltage_vpp)
        self.set_enabled(enable)

    def set_frequency(self, frequency_hz: float) -> None:
        """Set the excitation frequency (Hz), within `frequency_range_hz`."""
        lo, hi = self.frequency_range_hz
        if (
            isinstance(frequency_hz, bool)
            or not isinstance(frequency_hz, int | float)
            or not lo <= frequency_hz <= hi
        ):
            raise ValueError(f"frequency_hz must be a number in {lo:g}..{hi:g}, got {frequency_hz!r}")
        self._write(self.registers.frequency_set, frequency_hz, "frequency_hz")

    def set_voltage(self, voltage_vpp: float) -> None:
        """Set the excitation amplitude (Vpp), within (0, voltage_max_vpp]."""
        if (
            isinstance(voltage_vpp, bool)
            or not isinstance(voltage_vpp, int | float)
            or not 0 < voltage_vpp <= self.voltage_max_vpp
        ):
            raise ValueError(
                f"voltage_vpp must be a number in (0, {self.voltage_max_vpp:g}], got {voltage_vpp!r}"
            )
        self._write(self.registers.voltage_set, voltage_vpp, "voltage_vpp")

    def set_enabled(self, enable: bool) -> None:
        """Switch the drive stage's output on or off."""
        if not isinstance(enable, bool):
            raise ValueError(f"enable must be True or False, got {enable!r}")
        self._write(self.registers.enable, 1 if enable else 0, "enable")

    def _write(self, reg: Reg, value: float, name: str) -> None:
        """A write is done only when the board holds the value: the reply must echo it and a
        read-back must find it (a late reply to an earlier request is never taken for the answer)."""
        raw = reg.to_raw(value, name)
        what = f"write {name}={value:g} to holding register {reg.address}"
        with self._lock:
            rr = self._call(
                lambda: self._client.write_register(reg.address, raw, device_id=self.spec.unit), what
            )
            echo = list(getattr(rr, "registers", None) or [])
            if getattr(rr, "address", None) != reg.address or echo[:1] != [raw]:
                self._stale(f"{what}: the reply does not echo it ({rr})")
            held = self._read_block("holding", reg.address, 1)[0]
            if held != raw:
                self._failed(f"{what}: the board holds {reg.to_value(held):g}, not {value:g}")

    # -- reading -----------------------------------------------------------------------------
    def read(self) -> BoardReading:
        """Poll the measured values (one request per table span); BoardError if the board fails."""
        r = self.registers
        regs = {
            "temperature": r.temperature,
            "status": r.status,
            "frequency": r.frequency,
            "voltage": r.voltage,
        }
        raw: dict[str, int] = {}
        with self._lock:
            for table in ("holding", "input"):
                mine = {k: v for k, v in regs.items() if v.table == table}
                if not mine:
                    continue
                lo = min(v.address for v in mine.values())
                hi = max(v.address for v in mine.values())
                if hi - lo < 32:
                    values = self._read_block(table, lo, hi - lo + 1)
                    raw.update({k: values[v.address - lo] for k, v in mine.items()})
                else:
                    for k, v in mine.items():
                        raw[k] = self._read_block(table, v.address, 1)[0]
        lo_f, hi_f = self.frequency_range_hz
        status = BoardStatus(raw["status"] & 0x1F)
        if not status & BoardStatus.ENABLED and raw["frequency"] == raw["voltage"] == 0:
            # Output off: nothing to measure. Unknown, not a bad reading.
            lo_f = 0.0
        reading = BoardReading(
            temperature_c=self._in_range(
                "temperature", r.temperature.to_value(raw["temperature"]), *TEMPERATURE_RANGE_C
            ),
            frequency_hz=self._in_range("frequency", r.frequency.to_value(raw["frequency"]), lo_f, hi_f),
            voltage_vpp=self._in_range(
                "voltage", r.voltage.to_value(raw["voltage"]), 0.0, self.voltage_max_vpp
            ),
            status=status,
        )
        self._check_status(reading.status)
        self.last_reading = reading
        return reading

    def _in_range(self, name: str, value: float, lo: float, hi: float) -> float | None:
        """The value, or None (counted, logged once per spell) when outside the board's documented range."""
        if lo <= value <= hi:
            self._out_of_range.discard(name)
            return value
        self.rejected_readings += 1
        if name not in self._out_of_range:
            self._out_of_range.add(name)
            log.warning(
                "%s: %s reads %g, outside %g..%g: rejected (recorded as unknown)",
                self.describe(),
                name,
                value,
                lo,
                hi,
            )
        return None

    def _check_status(self, status: BoardStatus) -> None:
        """A fault bit newly set is a DRIVE fault event (the daemon latches FAULT, drive off)."""
        bits = status & FAULT_BITS
        if bits and bits != self._fault_bits:
            names = "|".join(b.name or "" for b in BoardStatus if b & bits)
            why = f"{self.describe()}: the board reports {names} (status 0x{int(status):02x})"
            log.error("%s", why)
            self._status_faults.append(why)
            self._events.append(Event.fault_event(self.clock.now_ns(), FaultCode.DRIVE, why))
        self._fault_bits = bits

    def take_status_faults(self) -> list[str]:
        """Fault bits newly set since the last call, described (what latches the daemon's FAULT)."""
        out = list(self._status_faults)
        self._status_faults.clear()
        return out

    def _read_block(self, table: Table, address: int, count: int) -> list[int]:
        c = self._client
        fn = c.read_input_registers if table == "input" else c.read_holding_registers
        rr = self._call(
            lambda: fn(address, count=count, device_id=self.spec.unit),
            f"read {count} {table} register(s) at {address}",
        )
        regs = list(rr.registers)
        want_fc = 4 if table == "input" else 3
        if getattr(rr, "function_code", want_fc) != want_fc or len(regs) != count:
            self._stale(f"read {table} {address}: a reply of another request ({rr})")
            self._failed(f"read {table} {address}: got a reply to another request; link reset")
        return regs

    def conditions(self) -> Conditions | None:
        """Drive conditions for the stroke records; None (logged, FAULT queued) if the board fails."""
        try:
            rd = self.read()
        except BoardError:
            return None
        return Conditions(
            temperature_c=rd.temperature_c, frequency_hz=rd.frequency_hz, voltage_vpp=rd.voltage_vpp
        )

    def ping(self) -> bool:
        """True when the board answers a read now."""
        try:
            self.read()
        except BoardError:
            return False
        return True

    def take_events(self) -> list[Event]:
        """FAULT events queued since the last call (one per transition from answering to failing)."""
        out = list(self._events)
        self._events.clear()
        return out

    # -- failures ----------------------------------------------------------------------------
    def _call(self, fn: Any, what: str) -> Any:
        try:
            rr = fn()
        except ModbusException as exc:
            if "transaction id" in str(exc):
                self._stale(f"{what}: {exc}")
            else:
                self._drop_link()  # its late reply must not be read as the next request's
            self._failed(f"{what}: {exc}")
        except OSError as exc:
            self._drop_link()
            self._failed(f"{what}: {exc}")
        if rr.isError():
            self._failed(f"{what}: exception response {rr}")
        if not self.ok:
            log.warning("%s: answering again", self.describe())
        self.ok = True
        return rr

    def _stale(self, why: str) -> None:
        self.stale_replies += 1
        log.warning("%s: stale reply dropped, link reset: %s", self.describe(), why)
        self._drop_link()

    def _drop_link(self) -> None:
        """Close the connection: replies still in flight die with it (the next request reconnects)."""
        self._client.close()

    def _failed(self, why: str) -> None:
        self.failures += 1
        self.last_error = why
        if self.ok:
            self.ok = False
            log.error("%s: %s", self.describe(), why)
            self._events.append(
                Event.fault_event(self.clock.now_ns(), FaultCode.DRIVE, f"{self.describe()}: {why}")
            )
        else:
            log.debug("%s: %s", self.describe(), why)
        raise BoardError(f"{self.describe()}: {why}")
