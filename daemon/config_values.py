"""The config's value parsers and checks: each takes the key it reads, for a message that names it.

`Table` reads one TOML table with typed getters and refuses unknown keys; the parsers check one value
each (a duration with its unit, an integer in bounds, a path, a socket mode, CPUs that exist ...);
`parse_host_port` and `parse_modbus_url` split endpoint strings. `config.py` builds the tree from them.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from socket import gethostname
from typing import Any

from usmswitch.predictor import MAX_ORDER
from usmswitch.protocol.units import UNITS_NS, parse_duration_ns

#: The most a socket's mode may allow: owner and group read and write.
SOCKET_MODE_ALLOWED = 0o660


class ConfigError(ValueError):
    """A bad configuration value; the message starts with the key ("control.window: ...")."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


class ConfigErrors(ConfigError):
    """Every bad value of one configuration at once, a line each (`errors`), so a file is mended in
    one pass, not one error per try."""

    def __init__(self, errors: list[ConfigError]) -> None:
        lines = "\n".join(f"  {e}" for e in errors)
        super().__init__("", f"{len(errors)} problems:\n{lines}")
        self.key = errors[0].key
        self.errors = list(errors)


def raise_collected(errors: list[ConfigError]) -> None:
    """Raise what a read collected: the one error as it is, several as ConfigErrors."""
    if len(errors) == 1:
        raise errors[0]
    if errors:
        raise ConfigErrors(errors)


class Table:
    """One TOML table being read: typed getters that name the key, and a check for unknown keys.

    A bad value is collected (in `errors`, shared by the tables of one file) and its default read
    on, so that every problem of a file is said at once (`raise_collected`)."""

    def __init__(self, raw: Any, name: str, errors: list[ConfigError] | None = None) -> None:
        self.errors: list[ConfigError] = [] if errors is None else errors
        if not isinstance(raw, dict):
            self.errors.append(ConfigError(name, f"expected a table, got {show(raw)}"))
            raw = {}
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
        try:
            return parse(self.key(k), self.raw[k])
        except ConfigError as exc:
            self.errors.append(exc)
            return default

    def fail(self, k: str, message: str) -> None:
        """Collect a problem of key `k` found across values (a window too short for the order)."""
        self.errors.append(ConfigError(self.key(k) if k else self.name, message))

    def table(self, k: str) -> Table:
        self.seen.add(k)
        return Table(self.raw.get(k, {}), self.key(k), self.errors)

    def done(self) -> None:
        unknown = sorted(set(self.raw) - self.seen)
        known = ", ".join(sorted(self.seen))
        where = f"in [{self.name}]" if self.name else "sections"
        for k in unknown:
            self.errors.append(ConfigError(self.key(k), f"unknown key (known {where}: {known})"))


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


def parse_listen(text: str) -> tuple[str, int]:
    """A listening address: "host:port" as parse_host_port, or a bare port meaning loopback."""
    if text.isdigit():
        text = f"127.0.0.1:{text}"
    return parse_host_port(text)


def listen_value(key: str, v: Any) -> str:
    """[metrics] and [web] listen: "host:port", or a port alone (text or TOML integer) on loopback; "" off."""
    if isinstance(v, int) and not isinstance(v, bool):
        v = str(v)
    return checked_text(parse_listen)(key, v)


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
def show(v: Any) -> str:
    return f"{v!r} ({type(v).__name__})"


def text_value(key: str, v: Any) -> str:
    if not isinstance(v, str):
        raise ConfigError(key, f"expected text, got {show(v)}")
    return v


def nonempty_text(key: str, v: Any) -> str:
    if not text_value(key, v):
        raise ConfigError(key, "must not be empty")
    return v


def bool_value(key: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(key, f"expected true or false, got {show(v)}")
    return v


def int_value(key: str, v: Any, lo: int, hi: int | None) -> int:
    # Text is refused, even "100": a quoted number in the file is a mistake worth naming (the
    # command line's integer flags are converted by argparse before they get here).
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(key, f"expected an integer, got {show(v)}")
    if v < lo or (hi is not None and v > hi):
        bound = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        raise ConfigError(key, f"{v} is outside the allowed range ({bound})")
    return v


def table_int(t: Table, k: str, default: int | None, lo: int, hi: int | None) -> int | None:
    return t.get(k, lambda key, v: int_value(key, v, lo, hi), default)


def priority_value(key: str, v: Any) -> int | str:
    """A SCHED_FIFO priority 0..99 (0: off), or "auto" (the default: where permitted)."""
    if v == "auto":
        return "auto"
    if isinstance(v, str) and v.strip().isdigit():
        v = int(v)  # from the command line
    if isinstance(v, str):
        raise ConfigError(key, f'expected "auto" or an integer 0..99, got {show(v)}')
    return int_value(key, v, 0, 99)


def positive_float(key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ConfigError(key, f"expected a number, got {show(v)}")
    if not v > 0 or v == float("inf"):
        raise ConfigError(key, f"{v} must be a positive finite number")
    return float(v)


def duration(key: str, v: Any) -> int:
    if isinstance(v, int) and not isinstance(v, bool) and v != 0:
        # A bare number is ambiguous (12 meant as ms would be a 12 ns target): only 0 is safe.
        raise ConfigError(
            key, f'{v} has no unit: write "{v}ms" (or "{v}us", "{v}s", "{v}ns": text with a unit)'
        )
    try:
        return parse_duration_ns(v)
    except ValueError as exc:
        raise ConfigError(key, str(exc)) from None


def positive_duration(key: str, v: Any) -> int:
    ns = duration(key, v)
    if ns == 0:
        raise ConfigError(key, f"{v!r} must be longer than 0")
    return ns


def duration_at_most(limit_ns: int, positive: bool = False) -> Callable[[str, Any], int]:
    def parse(key: str, v: Any) -> int:
        ns = positive_duration(key, v) if positive else duration(key, v)
        if ns > limit_ns:
            raise ConfigError(key, f"{duration_text(ns)} is longer than the limit {duration_text(limit_ns)}")
        return ns

    return parse


def duration_in(lo_ns: int, hi_ns: int) -> Callable[[str, Any], int]:
    def parse(key: str, v: Any) -> int:
        ns = duration(key, v)
        if not lo_ns <= ns <= hi_ns:
            raise ConfigError(
                key, f"{duration_text(ns)} is outside {duration_text(lo_ns)}..{duration_text(hi_ns)}"
            )
        return ns

    return parse


def positive_duration_at_most(limit_ns: int) -> Callable[[str, Any], int]:
    return duration_at_most(limit_ns, positive=True)


def duration_text(ns: int) -> str:
    """Integer ns as the exact text the loader reads back, in the largest unit that divides it."""
    for unit in ("s", "ms", "us"):
        scale = UNITS_NS[unit]
        if ns % scale == 0:
            return f"{ns // scale}{unit}"
    return f"{ns}ns"


def default_rig() -> str:
    return gethostname() or "localhost"


def rig_name(key: str, v: Any) -> str:
    name = text_value(key, v).strip()
    if not name:
        raise ConfigError(key, "must not be empty (unset it to use the host name)")
    if len(name) > 64 or not name.isprintable():
        raise ConfigError(key, f"{v!r} is not a printable name of at most 64 characters")
    return name


def checked_text(check: Callable[[str], object]) -> Callable[[str, Any], str]:
    """Text that `check` accepts, or "" (a feature left off); check's ValueError names the key."""

    def parse(key: str, v: Any) -> str:
        text = text_value(key, v)
        if text:
            try:
                check(text)
            except ValueError as exc:
                raise ConfigError(key, str(exc)) from None
        return text

    return parse


def choice(choices: tuple[str, ...]) -> Callable[[str, Any], str]:
    def parse(key: str, v: Any) -> str:
        if v not in choices:
            raise ConfigError(key, f"{v!r} is not one of {', '.join(repr(c) for c in choices)}")
        return v

    return parse


def per_unit(units: dict[str, float]) -> Callable[[str, Any], float]:
    """A rate written with its unit, "0.15/kHz": the number per the first unit of `units` (each unit
    maps to the factor that converts to it). A bare number is refused: 0.15 per Hz or per kHz differ
    a thousandfold."""
    first = next(iter(units))

    def parse(key: str, v: Any) -> float:
        if isinstance(v, bool) or not isinstance(v, str):
            example = (
                f'"{v}{first}"' if isinstance(v, int | float) and not isinstance(v, bool) else f'"0.1{first}"'
            )
            raise ConfigError(key, f"{show(v)} has no unit: write it as text with one, e.g. {example}")
        text = v.strip().replace(" ", "")
        for unit, factor in units.items():
            if text.endswith(unit):
                try:
                    x = float(text[: -len(unit)])
                except ValueError:
                    break
                if not math.isfinite(x):
                    break
                return x * factor
        raise ConfigError(key, f'{v!r} is not a number per {" or ".join(units)} (e.g. "0.1{first}")')

    return parse


def order_value(key: str, v: Any) -> int | str:
    if v == "auto":
        return v
    if isinstance(v, str):
        raise ConfigError(key, f"{v!r} is not an order 1..{MAX_ORDER} or 'auto'")
    return int_value(key, v, 1, MAX_ORDER)


def path_value(key: str, v: Any) -> Path:
    if isinstance(v, Path):
        v = str(v)
    if not text_value(key, v):
        raise ConfigError(key, "must not be empty")
    return Path(v).expanduser().absolute()


def file_mode_value(key: str, v: Any) -> int:
    if isinstance(v, str):
        if not re.fullmatch(r"(0o?)?[0-7]{1,4}", v.strip()):
            raise ConfigError(key, f"{v!r} is not an octal file mode like 0o660")
        v = int(v.strip().removeprefix("0o"), 8)
    m = int_value(key, v, 0, 0o777)
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


def cpu_list(key: str, v: Any) -> tuple[int, ...]:
    if not isinstance(v, list):
        raise ConfigError(key, f"expected a list of CPU numbers like [2, 3], got {show(v)}")
    cpus = tuple(int_value(f"{key}[{i}]", c, 0, 4095) for i, c in enumerate(v))
    if len(set(cpus)) != len(cpus):
        raise ConfigError(key, f"{list(cpus)} names a CPU twice")
    have = existing_cpus()
    missing = [c for c in cpus if c not in have]
    if missing:
        listed = ", ".join(map(str, sorted(have)))
        raise ConfigError(key, f"CPU {missing[0]} does not exist on this machine (CPUs: {listed})")
    return cpus
