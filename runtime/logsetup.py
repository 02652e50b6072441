"""Logging, configured once at start-up: JSON lines for the service, a readable form in a terminal.

structlog's processor chain renders; `make_filtering_bound_logger` makes a call below the level a
no-op method: the loop should hold a concrete logger (`structlog.get_logger("usmswitch.loop").bind()`
after `configure_logging`) so its per-stroke `log.debug(...)` costs one call at info. The
standard library's `logging` (pymodbus, pyusb) is routed through the same renderer, so the journal
gets one format. Modules take `structlog.get_logger("usmswitch.<part>")`; the name appears as
`logger` in each line.

Units: the JSON lines carry the raw numbers (`error_std_ns: 95300`, integers of ns) for machines;
the console renderer shows the same fields in units (`error_std=95.3 us`).

Priorities: every JSON line has `priority`, the syslog number of its level (sd-daemon(3): 3 error,
4 warning, 6 info, 7 debug). Under systemd with stderr connected to the journal ($JOURNAL_STREAM
names our stream), each line also starts with `<N>`, which journald reads as the entry's PRIORITY
(SyslogLevelPrefix=yes, the default), so `journalctl -p warning` finds faults.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from collections.abc import Mapping
from typing import Any, TextIO

import structlog
from structlog.typing import EventDict, Processor, WrappedLogger

from usmswitch.protocol.units import format_ns, is_instant_field

LEVELS = {
    "debug": logging.DEBUG,
    "info": logging.INFO,
    "warning": logging.WARNING,
    "error": logging.ERROR,
    "critical": logging.CRITICAL,
}
FORMATS = ("auto", "json", "console")

# Libraries that narrate every frame at debug: only their warnings, unless we are debugging.
_CHATTY = ("pymodbus", "usb", "asyncio")

#: syslog priority of each level name (structlog's and the standard library's), sd-daemon(3).
PRIORITIES = {
    "critical": 2,
    "fatal": 2,
    "error": 3,
    "exception": 3,
    "warning": 4,
    "warn": 4,
    "notice": 5,
    "info": 6,
    "debug": 7,
    "notset": 7,
}


def priority_of(level: str) -> int:
    """The syslog priority of a level name (info for one we do not know)."""
    return PRIORITIES.get(level.lower(), 6)


def journal_stream(stream: TextIO, env: Mapping[str, str] | None = None) -> bool:
    """Whether `stream` is the journal: $JOURNAL_STREAM ("device:inode", set by systemd for a
    service whose stdout/stderr go to journald) names the file `stream` writes to."""
    env = os.environ if env is None else env
    dev, sep, ino = env.get("JOURNAL_STREAM", "").partition(":")
    if not sep or not dev.isdigit() or not ino.isdigit():
        return False
    try:
        st = os.fstat(stream.fileno())
    except (AttributeError, OSError, ValueError):
        return False  # not a file (a StringIO in a test): not the journal
    return (st.st_dev, st.st_ino) == (int(dev), int(ino))


def _add_priority(logger: WrappedLogger, method_name: str, event_dict: EventDict) -> EventDict:
    event_dict["priority"] = priority_of(str(event_dict.get("level", method_name)))
    return event_dict


class Shown(str):
    """Text the console renderer prints as it is (it quotes plain strings that hold a space)."""

    def __repr__(self) -> str:
        return str(self)


def human_units(logger: WrappedLogger, method_name: str, event_dict: EventDict) -> EventDict:
    """Console only: `x_ns` durations as `x=12.000 ms`, `x_pct` as `x=0.412 %` (instants stay raw)."""
    out: EventDict = {}
    for key, value in event_dict.items():
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if number and key.endswith("_ns") and not is_instant_field(key) and math.isfinite(value):
            out[key[: -len("_ns")]] = Shown(format_ns(round(value)))
        elif number and key.endswith("_pct") and math.isfinite(value):
            out[key[: -len("_pct")]] = Shown(f"{value:.3f} %")
        else:
            out[key] = value
    return out


class _JournalPrefix:
    """Wraps the renderer: the line starts with `<N>`, its syslog priority, for journald to read."""

    def __init__(self, renderer: Processor) -> None:
        self.renderer = renderer

    def __call__(self, logger: WrappedLogger, method_name: str, event_dict: EventDict) -> Any:
        prefix = f"<{priority_of(str(event_dict.get('level', method_name)))}>"
        return prefix + str(self.renderer(logger, method_name, event_dict))


class _NamedWriteLogger(structlog.WriteLogger):
    """A WriteLogger that remembers the name it was asked for (WriteLoggerFactory drops it)."""

    def __init__(self, file: TextIO, name: str) -> None:
        super().__init__(file)
        self.name = name


class _NamedWriteLoggerFactory:
    def __init__(self, file: TextIO) -> None:
        self._file = file

    def __call__(self, *args: Any) -> _NamedWriteLogger:
        return _NamedWriteLogger(self._file, str(args[0]) if args else "")


def _add_logger_name(logger: WrappedLogger, method_name: str, event_dict: EventDict) -> EventDict:
    name = getattr(logger, "name", "")
    if name:
        event_dict.setdefault("logger", name)
    return event_dict


class _OurHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """The root handler this module installs (so a second configure replaces it, not adds one)."""


def resolve_format(log_format: str, stream: TextIO) -> str:
    """ "auto" -> "console" on a terminal, "json" otherwise (journald, files, pipes)."""
    if log_format not in FORMATS:
        raise ValueError(f"log format must be one of {FORMATS}, got {log_format!r}")
    if log_format != "auto":
        return log_format
    try:
        return "console" if stream.isatty() else "json"
    except (AttributeError, ValueError):
        return "json"


def configure_logging(
    log_format: str = "auto",
    level: str = "info",
    stream: TextIO | None = None,
    env: Mapping[str, str] | None = None,
) -> str:
    """Set up structlog and stdlib logging for the whole process; returns the format chosen.

    `env` (default os.environ) says whether `stream` is the journal ($JOURNAL_STREAM).
    """
    if level not in LEVELS:
        raise ValueError(f"log level must be one of {tuple(LEVELS)}, got {level!r}")
    stream = sys.stderr if stream is None else stream
    fmt = resolve_format(log_format, stream)
    number = LEVELS[level]
    if fmt == "json":
        timestamper = structlog.processors.TimeStamper(fmt="iso", utc=True)
        renderer: Processor = structlog.processors.JSONRenderer()
        tail: list[Processor] = [_add_priority, structlog.processors.format_exc_info]
    else:
        timestamper = structlog.processors.TimeStamper(fmt="%H:%M:%S.%f", utc=False)
        colors = _isatty(stream)
        renderer = structlog.dev.ConsoleRenderer(colors=colors)
        tail = [human_units]
    if journal_stream(stream, env):
        renderer = _JournalPrefix(renderer)
    shared: list[Processor] = [
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        timestamper,
    ]
    structlog.reset_defaults()
    structlog.configure(
        processors=[*shared, _add_logger_name, structlog.processors.StackInfoRenderer(), *tail, renderer],
        wrapper_class=structlog.make_filtering_bound_logger(number),
        logger_factory=_NamedWriteLoggerFactory(stream),
        # Not cached: module-level proxies made before this call must follow it (tests reconfigure).
        # The hot path binds a concrete logger once instead.
        cache_logger_on_first_use=False,
    )
    handler = _OurHandler(stream)
    handler.setFormatter(
        structlog.stdlib.ProcessorFormatter(
            foreign_pre_chain=[*shared, structlog.stdlib.add_logger_name],
            processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, *tail, renderer],
        )
    )
    root = logging.getLogger()
    for old in [h for h in root.handlers if isinstance(h, _OurHandler)]:
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(number)
    for name in _CHATTY:
        logging.getLogger(name).setLevel(max(number, logging.WARNING))
    return fmt


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False
