"""The command line's vocabulary: exit codes, usage errors, and arguments with human units in."""

from __future__ import annotations

import argparse
import re
from decimal import Decimal, InvalidOperation

from usmswitch.protocol.units import parse_duration_ns

EXIT_OK = 0
EXIT_REFUSED = 1
EXIT_USAGE = 2
EXIT_CONNECT = 3
EXIT_FAULT = 4
#: What a shell reports for a process ended by Ctrl-C; used when a command other than watch is cut.
EXIT_INTERRUPTED = 130
EXIT_PIPE = 141  # our stdout's reader went away (`watch | head`), as a shell shows SIGPIPE

PROG = "usmswitchctl"
DIRECTION_NAMES = ("on", "off")
#: Stroke lines between repeated column headers in `watch`.
WATCH_HEADER_EVERY = 40
#: How often `cycle --wait` checks the state when no notification comes.
WAIT_POLL_NS = 500_000_000


class UsageError(Exception):
    """A bad argument that argparse cannot catch (a unit, a combination); exits 2."""


# -- units -----------------------------------------------------------------------------------------
def duration_arg(text: str) -> int:
    """argparse type: a human duration ("12ms", "10500us", "0.012s") as integer ns."""
    try:
        return parse_duration_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def positive_duration_arg(text: str) -> int:
    """argparse type: a human duration that must be longer than 0 (a target, a period)."""
    ns = duration_arg(text)
    if ns <= 0:
        raise argparse.ArgumentTypeError(f"duration {text!r}: must be longer than 0")
    return ns


_QUANTITY = re.compile(
    r"^\s*(?P<number>[+-]?(?:\d[\d_]*(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?)\s*(?P<unit>\S*)\s*$"
)
# Matched without case ("40khz" and "40KHz" are not ambiguous); the help shows the usual spelling.
_FREQUENCY_UNITS = {"Hz": Decimal(1), "kHz": Decimal(1_000), "MHz": Decimal(1_000_000)}
_VOLTAGE_UNITS = {"V": Decimal(1), "Vpp": Decimal(1), "kV": Decimal(1_000)}


def _quantity(text: str, what: str, units: dict[str, Decimal], example: str) -> float:
    m = _QUANTITY.match(text)
    if m is None:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: not a number with a unit, e.g. {example!r}")
    unit = m["unit"]
    if not unit:
        # As with durations: "40" could mean 40 Hz or 40 kHz, and the wrong guess drives the motor.
        raise argparse.ArgumentTypeError(
            f"{what} {text!r}: needs a unit ({', '.join(units)}), e.g. {example!r}"
        )
    scale = next((v for k, v in units.items() if k.lower() == unit.lower()), None)
    if scale is None:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: unknown unit {unit!r} (use {', '.join(units)})")
    try:
        value = Decimal(m["number"].replace("_", "")) * scale
    except InvalidOperation:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: not a number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: negative")
    return float(value)


def frequency_arg(text: str) -> float:
    """argparse type: an excitation frequency ("40kHz", "39600Hz") in hertz."""
    return _quantity(text, "frequency", _FREQUENCY_UNITS, "40kHz")


def voltage_arg(text: str) -> float:
    """argparse type: an excitation voltage ("500V", "500Vpp") in volts peak-to-peak."""
    return _quantity(text, "voltage", _VOLTAGE_UNITS, "500V")
