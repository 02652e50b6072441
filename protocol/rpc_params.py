"""The parameters of every documented socket method: their checks and defaults (docs/protocol.md).

The server process validates each request against `PARAMS` before the daemon sees it, so a handler
gets a full, checked list.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .record import check_label, check_notes
from .units import format_ns
from .wire import MAX_HISTORY, ErrorCode, RpcError

_REQUIRED = object()
_MAX_TARGET_NS = 10_000_000_000
_MAX_PERIOD_NS = 3_600_000_000_000
_MAX_COUNT = 1_000_000_000
_MAX_ID = 2**62
#: runs' upper bound on n.
MAX_RUNS = 1_000
#: A queued run's priority is in -MAX_PRIORITY..MAX_PRIORITY (higher first; 0 by default).
MAX_PRIORITY = 1000
#: Strokes an `export` call returns at most: a chunk of CSV text (~2.5 MB); the client asks again after it.
MAX_EXPORT_STROKES = 10_000


def show(value: object) -> str:
    """A value for an error message, cut short so an attacker's megabyte is not echoed back."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _human_ns(ns: int) -> str:
    """A duration in a message, as people read it: 250 ns, 95.3 us, 12.000 ms, 12.000 s."""
    return format_ns(ns) if abs(ns) < 1_000_000_000 else f"{ns / 1e9:.3f} s"


def _integer(name: str, lo: int, hi: int) -> Callable[[str, object], object]:
    def check(method: str, value: object) -> object:
        if type(value) is int and not lo <= value <= hi and name.endswith("_ns"):
            # A duration out of range: said in units, not as 12000000000 (a panel's box in ms).
            raise RpcError(
                ErrorCode.INVALID_PARAMS,
                f"{method}: {name} must be from {_human_ns(lo)} to {_human_ns(hi)}, got {_human_ns(value)}",
            )
        if type(value) is not int or not lo <= value <= hi:
            raise RpcError(
                ErrorCode.INVALID_PARAMS,
                f"{method}: {name} must be an integer in [{lo}, {hi}], got {show(value)}",
            )
        return value

    return check


def _optional(check: Callable[[str, object], object]) -> Callable[[str, object], object]:
    """`check`, or nil for "not given"."""

    def optional(method: str, value: object) -> object:
        return None if value is None else check(method, value)

    return optional


def _boolean(name: str) -> Callable[[str, object], object]:
    def check(method: str, value: object) -> object:
        if type(value) is not bool:
            raise RpcError(
                ErrorCode.INVALID_PARAMS, f"{method}: {name} must be true or false, got {show(value)}"
            )
        return value

    return check


def _choice(name: str, options: tuple[str, ...]) -> Callable[[str, object], object]:
    def check(method: str, value: object) -> object:
        if value not in options or type(value) is not str:
            raise RpcError(
                ErrorCode.INVALID_PARAMS,
                f"{method}: {name} must be one of {list(options)}, got {show(value)}",
            )
        return value

    return check


def _string(name: str) -> Callable[[str, object], object]:
    def check(method: str, value: object) -> object:
        if type(value) is not str:
            raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: {name} must be a string, got {show(value)}")
        return value

    return check


def _text(name: str, max_len: int) -> Callable[[str, object], object]:
    def check(method: str, value: object) -> object:
        if type(value) is not str or len(value) > max_len:
            raise RpcError(
                ErrorCode.INVALID_PARAMS,
                f"{method}: {name} must be a string of at most {max_len} characters, got {show(value)}",
            )
        return value

    return check


def _label(method: str, value: object) -> object:
    """A run's label (record.check_label), or "" for none."""
    if value == "" and type(value) is str:
        return value
    try:
        return check_label(value)
    except ValueError as exc:
        raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: {exc}") from None


def _notes(method: str, value: object) -> object:
    try:
        return check_notes(value)
    except ValueError as exc:
        raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: {exc}") from None


def _topics(method: str, value: object) -> object:
    if type(value) is not list or not all(type(t) is str for t in value):
        raise RpcError(
            ErrorCode.INVALID_PARAMS, f"{method}: topics must be an array of strings, got {show(value)}"
        )
    return value


_DRIVE_KEYS = {"frequency_hz": (1.0, 1e7), "voltage_vpp": (0.0, 1e4)}


def _drive(method: str, value: object) -> object:
    if type(value) is not dict:
        raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: settings must be a map, got {show(value)}")
    for key, item in value.items():
        if key == "enabled":
            if type(item) is not bool:
                raise RpcError(
                    ErrorCode.INVALID_PARAMS, f"{method}: enabled must be true or false, got {show(item)}"
                )
        elif key in _DRIVE_KEYS:
            lo, hi = _DRIVE_KEYS[key]
            if type(item) not in (int, float) or not lo <= item <= hi:
                raise RpcError(
                    ErrorCode.INVALID_PARAMS,
                    f"{method}: {key} must be a number in [{lo:g}, {hi:g}], got {show(item)}",
                )
        else:
            raise RpcError(
                ErrorCode.INVALID_PARAMS,
                f"{method}: unknown setting {show(key)}; known: enabled, {', '.join(sorted(_DRIVE_KEYS))}",
            )
    return value


_Spec = tuple[tuple[str, Callable[[str, object], object], object], ...]

#: Positional params of every documented method: (name, check, default or _REQUIRED).
PARAMS: dict[str, _Spec] = {
    "ping": (),
    "auth": (("token", _string("token"), _REQUIRED),),
    "status": (),
    "get_target": (),
    "set_target": (
        ("target_ns", _integer("target_ns", 1, _MAX_TARGET_NS), _REQUIRED),
        ("direction", _choice("direction", ("on", "off", "both")), "both"),
        ("allow_late", _boolean("allow_late"), False),
    ),
    "stats": (
        ("run", _optional(_integer("run", 1, _MAX_ID)), None),
        ("first_cycle", _optional(_integer("first_cycle", 1, _MAX_ID)), None),
        ("last_cycle", _optional(_integer("last_cycle", 1, _MAX_ID)), None),
        ("label", _optional(_label), None),
    ),
    "history": (
        ("n", _integer("n", 1, MAX_HISTORY), 20),
        ("run", _optional(_integer("run", 1, _MAX_ID)), None),
    ),
    "runs": (("n", _integer("n", 1, MAX_RUNS), 20), ("label", _optional(_label), None)),
    "export": (
        ("run", _optional(_integer("run", 1, _MAX_ID)), None),
        ("first_cycle", _integer("first_cycle", 1, _MAX_ID), 1),
        ("last_cycle", _optional(_integer("last_cycle", 1, _MAX_ID)), None),
        ("max_strokes", _integer("max_strokes", 1, MAX_EXPORT_STROKES), MAX_EXPORT_STROKES),
        ("label", _optional(_label), None),
    ),
    "switch": (("direction", _choice("direction", ("on", "off", "next")), "next"),),
    "start_cycling": (
        ("period_ns", _integer("period_ns", 1, _MAX_PERIOD_NS), _REQUIRED),
        ("count", _integer("count", 0, _MAX_COUNT), 0),
        ("target_ns", _optional(_integer("target_ns", 1, _MAX_TARGET_NS)), None),
        ("allow_late", _boolean("allow_late"), False),
        ("take_over", _boolean("take_over"), False),
        ("owner", _text("owner", 200), ""),
        ("label", _optional(_label), None),
        ("notes", _optional(_notes), None),
    ),
    "annotate_run": (
        ("run", _integer("run", 1, _MAX_ID), _REQUIRED),
        ("notes", _optional(_notes), None),
        ("label", _optional(_label), None),
        ("owner", _text("owner", 200), ""),
        ("operator", _boolean("operator"), False),
    ),
    "submit": (
        ("period_ns", _integer("period_ns", 1, _MAX_PERIOD_NS), _REQUIRED),
        ("count", _integer("count", 0, _MAX_COUNT), 0),
        ("target_ns", _optional(_integer("target_ns", 1, _MAX_TARGET_NS)), None),
        ("allow_late", _boolean("allow_late"), False),
        ("label", _optional(_label), None),
        ("notes", _optional(_notes), None),
        ("priority", _integer("priority", -MAX_PRIORITY, MAX_PRIORITY), 0),
        ("take_over", _boolean("take_over"), False),
        ("owner", _text("owner", 200), ""),
    ),
    "queue_cancel": (
        ("entry", _integer("entry", 1, _MAX_ID), _REQUIRED),
        ("owner", _text("owner", 200), ""),
        ("operator", _boolean("operator"), False),
    ),
    "queue_priority": (
        ("entry", _integer("entry", 1, _MAX_ID), _REQUIRED),
        ("priority", _integer("priority", -MAX_PRIORITY, MAX_PRIORITY), _REQUIRED),
        ("owner", _text("owner", 200), ""),
        ("operator", _boolean("operator"), False),
    ),
    "queue_pause": (("operator", _boolean("operator"), False),),
    "queue_resume": (("operator", _boolean("operator"), False),),
    "stop_cycling": (),
    "set_mode": (
        ("mode", _choice("mode", ("open", "closed")), _REQUIRED),
        ("open_delay_ns", _integer("open_delay_ns", 0, _MAX_TARGET_NS), None),
    ),
    "reset_fault": (),
    "estop": (("source", _text("source", 80), ""),),  # who pressed it, by which path (for people)
    "set_drive": (("settings", _drive, {}),),
    "subscribe": (("topics", _topics, None),),
    "unsubscribe": (("topics", _topics, None),),
}


def check_params(method: str, params: list[Any]) -> list[Any]:
    """Validate a documented method's params and fill the defaults, so handlers get full lists."""
    spec = PARAMS.get(method)
    if spec is None:
        return params
    if len(params) > len(spec):
        names = ", ".join(name for name, _, _ in spec) or "none"
        raise RpcError(
            ErrorCode.INVALID_PARAMS,
            f"{method} takes at most {len(spec)} params ({names}), got {len(params)}",
        )
    out = []
    for i, (name, check, default) in enumerate(spec):
        if i < len(params):
            out.append(check(method, params[i]))
        elif default is _REQUIRED:
            raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: missing param {i} ({name})")
        else:
            out.append(default)
    return out
