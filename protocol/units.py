"""Human durations in and out: "12ms", "10500us", "0.012s", "2min", "1h" <-> integer nanoseconds.

Config files, command-line flags and the socket client all take durations from people; this is
the one place that turns them into the integer nanoseconds every API uses, exactly (Decimal, never
float), and back into a readable form.
"""

from __future__ import annotations

import re
from decimal import Decimal, InvalidOperation, localcontext

# Nanoseconds per unit. "µ" (micro sign) and "μ" (Greek mu) both appear in copied text.
UNITS_NS: dict[str, int] = {
    "ns": 1,
    "us": 1_000,
    "µs": 1_000,
    "μs": 1_000,
    "ms": 1_000_000,
    "s": 1_000_000_000,
    "min": 60_000_000_000,
    "h": 3_600_000_000_000,
}
_UNIT_NAMES = "ns, us, ms, s, min, h"

# SQLite stores signed 64-bit integers: about 292 years of nanoseconds.
MAX_NS = 2**63 - 1

_DURATION = re.compile(
    r"""^\s*
    (?P<sign>[+-]?)
    (?P<number>(?:[0-9][0-9_]*(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)
    \s*
    (?P<unit>[^\s0-9.+-][^\s]*)?
    \s*$""",
    re.VERBOSE,
)


def _unit_hint(number: Decimal) -> str:
    """What a bare number most likely meant, written with units: a count of ms when small (a
    target of "12"), else of ns (a raw "12000000" copied from a record), in its natural unit too."""
    if number.adjusted() > 20 or number.adjusted() < -20:
        return "'12ms'"
    if abs(number) < 1000:
        return f"'{number}ms'"
    if number == number.to_integral_value():
        for unit, scale in (("s", 1_000_000_000), ("ms", 1_000_000), ("us", 1_000)):
            if number % scale == 0:
                return f"'{int(number) // scale}{unit}' ({number} ns; or '{number}ns')"
    return f"'{number}ns' or '{number}us'"


def parse_duration_ns(value: str | int) -> int:
    """Turn a human duration ("12ms", "10500us", "0.012s", "250ns") or integer ns into exact ns."""
    if isinstance(value, bool):
        raise ValueError(f"duration {value!r}: a boolean is not a duration")
    if isinstance(value, int):
        if value < 0:
            raise ValueError(f"duration {value!r}: negative")
        if value > MAX_NS:
            raise ValueError(f"duration {value!r}: longer than {MAX_NS} ns")
        return value
    if not isinstance(value, str):
        raise ValueError(
            f"duration {value!r}: expected text with a unit (e.g. '12ms') or integer nanoseconds, "
            f"got {type(value).__name__}"
        )
    m = _DURATION.match(value)
    if m is None:
        raise ValueError(
            f"duration {value!r}: not a number with a unit ({_UNIT_NAMES}), e.g. '12ms' (ASCII digits)"
        )
    unit = m["unit"]
    try:
        number = Decimal(m["number"].replace("_", ""))
    except InvalidOperation:  # pragma: no cover - the pattern admits only valid numbers
        raise ValueError(f"duration {value!r}: {m['number']!r} is not a number") from None
    if unit is None:
        # A bare number is ambiguous ("12" meant as ms would be a 12 ns target): only 0 is safe.
        if number == 0:
            return 0
        raise ValueError(f"duration {value!r}: needs a unit ({_UNIT_NAMES}), e.g. {_unit_hint(number)}")
    scale = UNITS_NS.get(unit)
    if scale is None:
        raise ValueError(f"duration {value!r}: unknown unit {unit!r} (use {_UNIT_NAMES})")
    # Exact, or refused: an exponent far out of range is never handed to arithmetic that would
    # overflow or round, and the product keeps every digit typed.
    if number != 0 and number.adjusted() > 20:
        raise ValueError(f"duration {value!r}: longer than {MAX_NS} ns")
    if number != 0 and number.adjusted() < -20:
        raise ValueError(f"duration {value!r}: finer than 1 ns")
    with localcontext() as ctx:
        ctx.prec = 80
        ns = number * scale
    if m["sign"] == "-" and ns != 0:
        raise ValueError(f"duration {value!r}: negative")
    if ns != ns.to_integral_value():
        raise ValueError(f"duration {value!r}: finer than 1 ns")
    if ns > MAX_NS:
        raise ValueError(f"duration {value!r}: longer than {MAX_NS} ns")
    return int(ns)


def format_ns(ns: int, *, micro: str = "us") -> str:
    """Render integer nanoseconds for people, in the unit that fits: "12.000 ms", "95.3 us", "250 ns".

    `micro="µs"` for figures and reports (a terminal's and a CSV's reader gets plain ASCII "us")."""
    if isinstance(ns, bool) or not isinstance(ns, int):
        raise ValueError(f"format_ns needs integer nanoseconds, got {ns!r}")
    sign = "-" if ns < 0 else ""
    mag = abs(ns)
    if mag < 1_000:
        return f"{sign}{mag} ns"
    # Pick the unit after rounding, so 999_999 ns reads "1.000 ms", not "1000.0 us".
    for exponent, step, unit in _FORMAT_STEPS:
        shown = Decimal(mag).scaleb(exponent).quantize(step)
        if shown < 1000:
            return f"{sign}{shown} {micro if unit == 'us' else unit}"
    return f"{sign}{Decimal(mag).scaleb(-9).quantize(Decimal('0.000001'))} s"


_FORMAT_STEPS = ((-3, Decimal("0.1"), "us"), (-6, Decimal("0.001"), "ms"))


def format_elapsed(ns: int) -> str:
    """A long duration for people, to the precision a person reads: "14.5 s", "12 min 05 s",
    "2 h 03 min", "3 d 04 h" (an uptime, not a measurement: format_ns keeps the digits)."""
    if isinstance(ns, bool) or not isinstance(ns, int):
        raise ValueError(f"format_elapsed needs integer nanoseconds, got {ns!r}")
    if ns < 0:
        return "-" + format_elapsed(-ns)
    if ns < 59_950_000_000:  # below what rounds to "60.0 s"
        return f"{Decimal(ns).scaleb(-9).quantize(Decimal('0.1'))} s"
    s = (ns + 500_000_000) // 1_000_000_000  # whole seconds, rounded
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    if s < 86400:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    return f"{s // 86400} d {s % 86400 // 3600:02d} h"


def is_instant_field(name: str) -> bool:
    """Whether an `_ns` field is an instant on a clock (`t_cmd_ns`, `wall_ns`), not a duration:
    instants print as raw ns (only their differences mean something), durations in units."""
    return name == "wall_ns" or (name.startswith("t_") and name.endswith("_ns") and name != "t_hat_ns")
