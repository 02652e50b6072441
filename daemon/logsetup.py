"""Logging, configured once at start-up: JSON lines for the service, a readable form in a terminal.

structlog's processor chain renders; `make_filtering_bound_logger` makes a call below the level a
no-op method: the loop should hold a concrete logger (`structlog.get_logger("usmswitch.loop").bind()`
after `configure_logging`) so its per-stroke `log.debug(...)` costs one call at info. The
standard library's `logging` (pymodbus, pyusb) is routed through the same renderer, so the journal
gets one format. Modules take `structlog.get_logger("usmswitch.<part>")`; the name appears as
`logger` in each line.
"""

from __future__ import annotations

import logging
import sys
from typing import Any, TextIO

import structlog
from structlog.typing import EventDict, Processor, WrappedLogger

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


def configure_logging(log_format: str = "auto", level: str = "info", stream: TextIO | None = None) -> str:
    """Set up structlog and stdlib logging for the whole process; returns the format chosen."""
    if level not in LEVELS:
        raise ValueError(f"log level must be one of {tuple(LEVELS)}, got {level!r}")
    stream = sys.stderr if stream is None else stream
    fmt = resolve_format(log_format, stream)
    number = LEVELS[level]
    if fmt == "json":
        timestamper = structlog.processors.TimeStamper(fmt="iso", utc=True)
        renderer: Processor = structlog.processors.JSONRenderer()
        tail: list[Processor] = [structlog.processors.format_exc_info]
    else:
        timestamper = structlog.processors.TimeStamper(fmt="%H:%M:%S.%f", utc=False)
        colors = _isatty(stream)
        renderer = structlog.dev.ConsoleRenderer(colors=colors)
        tail = []
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
