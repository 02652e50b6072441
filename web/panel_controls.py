"""The panel's controls: what a control's JSON body becomes as a socket method's params.

Each control is one socket method, called by the panel's server process as a socket client's request
(web/panel.py, `Backend.call`), so the server's parameter checks judge every value the page sends.
The body names the fields a person fills in; what the page never decides is filled here: the owner
(`panel`: a run or queue entry from any page is the panel's), the estop's path, `allow_late`.

`operator` is the page's answer to the daemon's guard: another's queue entry or run is refused
(STATE, naming whose it is) until the page, asked, sends it again with `operator: true`, as
`usmswitchctl ... --operator` does. Pausing and resuming the queue are an operator's by nature:
the page sends them as such.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from usmswitch.protocol.wire import ErrorCode, RpcError

#: The owner of what the panel starts or queues: any page with the token acts as one submitter.
OWNER = "panel"

_Params = Callable[[dict[str, Any]], list[Any]]


def _or(value: Any, default: Any) -> Any:
    return default if value is None else value


def _target(b: dict[str, Any]) -> list[Any]:
    # allow_late: never from the panel's target box
    return [b.get("target_ns"), _or(b.get("direction"), "both"), False]


def _mode(b: dict[str, Any]) -> list[Any]:
    params = [b.get("mode"), b.get("open_delay_ns")]
    return params if params[-1] is not None else params[:1]


#: name -> (socket method, the JSON fields it takes, body -> the method's params).
CONTROLS: dict[str, tuple[str, tuple[str, ...], _Params]] = {
    "start": (
        "start_cycling",
        ("period_ns", "count", "target_ns", "allow_late", "take_over", "label", "notes"),
        lambda b: [
            b.get("period_ns"),
            _or(b.get("count"), 0),
            b.get("target_ns"),
            _or(b.get("allow_late"), False),
            _or(b.get("take_over"), False),
            OWNER,
            b.get("label") or None,
            b.get("notes") or None,
        ],
    ),
    "stop": ("stop_cycling", (), lambda b: []),
    "target": ("set_target", ("target_ns", "direction"), _target),
    "mode": ("set_mode", ("mode", "open_delay_ns"), _mode),
    "reset": ("reset_fault", (), lambda b: []),
    "estop": ("estop", (), lambda b: [OWNER]),  # the fault names the path that pressed it
    "submit": (
        "submit",
        ("period_ns", "count", "target_ns", "label", "notes", "priority"),
        lambda b: [
            b.get("period_ns"),
            _or(b.get("count"), 0),
            b.get("target_ns"),
            False,
            b.get("label") or None,
            b.get("notes") or None,
            _or(b.get("priority"), 0),
            False,  # take_over: the page's Start does that, asked first
            OWNER,
        ],
    ),
    "queue_cancel": (
        "queue_cancel",
        ("entry", "operator"),
        lambda b: [b.get("entry"), OWNER, _or(b.get("operator"), False)],
    ),
    "queue_priority": (
        "queue_priority",
        ("entry", "priority", "operator"),
        lambda b: [b.get("entry"), b.get("priority"), OWNER, _or(b.get("operator"), False)],
    ),
    "queue_pause": ("queue_pause", (), lambda b: [True]),
    "queue_resume": ("queue_resume", (), lambda b: [True]),
    # notes or label: "" clears it, absent (null) leaves it as it is
    "notes": (
        "annotate_run",
        ("run", "notes", "label", "operator"),
        lambda b: [b.get("run"), b.get("notes"), b.get("label"), OWNER, _or(b.get("operator"), False)],
    ),
}


def control_params(name: str, body: Any) -> tuple[str, list[Any]]:
    """A control's JSON body -> (socket method, params); RpcError(INVALID_PARAMS) when malformed.
    The values are the server's to check, as any socket client's."""
    method, names, params = CONTROLS[name]
    if not isinstance(body, dict):
        raise RpcError(
            ErrorCode.INVALID_PARAMS, f"{name}: the body must be a JSON object, got {type(body).__name__}"
        )
    unknown = sorted(set(body) - set(names))
    if unknown:
        known = ", ".join(names) or "none"
        raise RpcError(ErrorCode.INVALID_PARAMS, f"{name}: unknown field {unknown[0]!r} (known: {known})")
    return method, params(body)
