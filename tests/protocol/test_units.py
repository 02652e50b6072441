"""Human durations: exact parsing into integer ns and readable formatting."""

from __future__ import annotations

from decimal import Decimal

import pytest
from hypothesis import given
from hypothesis import strategies as st

from usmswitch.protocol.units import MAX_NS, format_ns, parse_duration_ns


@pytest.mark.parametrize(
    ("text", "ns"),
    [
        ("12ms", 12_000_000),
        ("10500us", 10_500_000),
        ("0.012s", 12_000_000),
        ("250ns", 250),
        (12_000_000, 12_000_000),
        ("12 ms", 12_000_000),
        (" 1.5ms ", 1_500_000),
        (".5ms", 500_000),
        ("10_500us", 10_500_000),
        ("12µs", 12_000),
        ("12μs", 12_000),
        ("1e3us", 1_000_000),
        ("0", 0),
        ("-0ms", 0),
        ("0.000000001s", 1),
        # Binary floats would get these wrong: 0.1 + 0.2 style.
        ("0.3s", 300_000_000),
        ("10.000001ms", 10_000_001),
    ],
)
def test_parses_exactly(text, ns):
    assert parse_duration_ns(text) == ns


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("-12ms", "'-12ms': negative"),
        (-1, "-1: negative"),
        ("12", "'12': needs a unit"),
        ("12xs", "unknown unit 'xs'"),
        ("abc", "'abc': not a number"),
        ("", "'': not a number"),
        ("nan ms", "'nan ms'"),
        ("1.5.3ms", "'1.5.3ms'"),
        ("0.5ns", "finer than 1 ns"),
        ("1e30s", "longer than"),
        (1.5, "got float"),
        (True, "boolean"),
        (None, "got NoneType"),
    ],
)
def test_garbage_is_refused_naming_the_text(value, message):
    with pytest.raises(ValueError, match="duration") as info:
        parse_duration_ns(value)
    assert message in str(info.value)


@given(st.integers(min_value=0, max_value=MAX_NS), st.sampled_from(["ns", "us", "ms", "s"]))
def test_any_integer_ns_written_in_any_unit_parses_back(ns, unit):
    scale = {"ns": 0, "us": -3, "ms": -6, "s": -9}[unit]
    text = f"{Decimal(ns).scaleb(scale):f}{unit}"
    assert parse_duration_ns(text) == ns


@pytest.mark.parametrize(
    ("ns", "text"),
    [
        (12_000_000, "12.000 ms"),
        (95_300, "95.3 us"),
        (250, "250 ns"),
        (0, "0 ns"),
        (-95_312, "-95.3 us"),
        (999_999, "1.000 ms"),  # rounds up into the next unit, not "1000.0 us"
        (1_500_000_000, "1.500000 s"),
        (102_700, "102.7 us"),
    ],
)
def test_formats_in_the_unit_that_fits(ns, text):
    assert format_ns(ns) == text


@given(st.integers(min_value=-(10**15), max_value=10**15))
def test_format_parses_back_within_its_shown_precision(ns):
    text = format_ns(ns)
    number, unit = text.split()
    back = parse_duration_ns(f"{number.lstrip('-')}{unit}")
    precision = {"ns": 1, "us": 100, "ms": 1_000, "s": 1_000}[unit]
    assert abs(back - abs(ns)) <= precision // 2


def test_format_refuses_floats():
    with pytest.raises(ValueError, match=r"0\.012"):
        format_ns(0.012)  # type: ignore[arg-type]


def test_format_elapsed_reads_like_an_uptime() -> None:
    from usmswitch.protocol.units import format_elapsed

    s = 1_000_000_000
    assert format_elapsed(14_514_742_000) == "14.5 s"
    assert format_elapsed(59_960_000_000) == "1 min 00 s"  # rounds up into minutes, never "60.0 s"
    assert format_elapsed(725 * s) == "12 min 05 s"
    assert format_elapsed(7380 * s) == "2 h 03 min"
    assert format_elapsed((3 * 86400 + 4 * 3600) * s) == "3 d 04 h"
    with pytest.raises(ValueError):
        format_elapsed(1.5)  # type: ignore[arg-type]


def test_hours_and_minutes_are_units() -> None:
    """Issue 34 item 8: "1h" was refused as an unknown unit."""
    assert parse_duration_ns("1h") == 3_600_000_000_000
    assert parse_duration_ns("2min") == 120_000_000_000
    assert parse_duration_ns("1.5 min") == 90_000_000_000


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("1e999999ms", "longer than"),  # was a decimal.Overflow traceback
        ("1e999999", "needs a unit"),  # was decimal.InvalidOperation
        ("1e-9999999999ms", "finer than 1 ns"),  # was parsed as 0
        ("1234567890123456789.5ns", "finer than 1 ns"),  # 20 digits: exact or refused, never rounded
        ("١٢ms", "ASCII digits"),  # Arabic-Indic digits were taken
    ],
)
def test_a_duration_is_exact_or_refused_with_a_value_error(text: str, says: str) -> None:
    with pytest.raises(ValueError, match=says):
        parse_duration_ns(text)


def test_many_digits_stay_exact() -> None:
    assert parse_duration_ns("9223372036854775807ns") == 2**63 - 1
    assert parse_duration_ns("0.000000001s") == 1
    assert parse_duration_ns("1234567890123456.789000000us") == 1234567890123456789
