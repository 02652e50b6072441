"""Logging set-up: JSON lines off a terminal, readable lines on a real pty, cheap level filtering."""

from __future__ import annotations

import io
import json
import logging
import os

import pytest
import structlog

from usmswitch.daemon.logsetup import configure_logging, resolve_format


@pytest.fixture(autouse=True)
def restore_logging():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    structlog.reset_defaults()
    root.handlers[:] = handlers
    root.setLevel(level)


def lines(buf: io.StringIO) -> list[dict]:
    return [json.loads(line) for line in buf.getvalue().splitlines()]


def test_json_lines_for_the_service():
    buf = io.StringIO()
    assert configure_logging("auto", "info", stream=buf) == "json"  # not a terminal
    log = structlog.get_logger("usmswitch.loop").bind()
    log.debug("stroke", cycle=1)
    log.info("summary", count=100, error_std_ns=95_300)
    (line,) = lines(buf)
    assert line["event"] == "summary" and line["level"] == "info" and line["logger"] == "usmswitch.loop"
    assert line["count"] == 100 and line["error_std_ns"] == 95_300
    assert line["timestamp"].endswith("Z") and "T" in line["timestamp"]


def test_debug_level_shows_the_per_stroke_lines():
    buf = io.StringIO()
    configure_logging("json", "debug", stream=buf)
    structlog.get_logger("usmswitch.loop").debug("stroke", cycle=1, error_ns=-12)
    assert lines(buf)[0]["error_ns"] == -12


def test_exceptions_are_one_json_line():
    buf = io.StringIO()
    configure_logging("json", "info", stream=buf)
    try:
        raise RuntimeError("drive board gone")
    except RuntimeError:
        structlog.get_logger().exception("fault")
    (line,) = lines(buf)
    assert "RuntimeError: drive board gone" in line["exception"]


def test_stdlib_logging_goes_through_the_same_renderer():
    buf = io.StringIO()
    configure_logging("json", "debug", stream=buf)
    logging.getLogger("pymodbus.client").warning("no response from unit %d", 1)
    logging.getLogger("pymodbus.client").info("frame sent")  # libraries stay quiet below warning
    logging.getLogger("usmswitch.drivers").debug("ours are not muted")
    got = lines(buf)
    assert [(g["logger"], g["event"], g["level"]) for g in got] == [
        ("pymodbus.client", "no response from unit 1", "warning"),
        ("usmswitch.drivers", "ours are not muted", "debug"),
    ]
    configure_logging("json", "debug", stream=buf)  # a second set-up replaces, not doubles, the handler
    logging.getLogger("x").warning("once")
    assert [g["event"] for g in lines(buf)].count("once") == 1


def test_console_on_a_real_terminal():
    master, slave = os.openpty()
    stream = os.fdopen(slave, "w")
    try:
        assert resolve_format("auto", stream) == "console"
        assert configure_logging("auto", "info", stream=stream) == "console"
        structlog.get_logger("usmswitch.loop").info("cycling", target_ns=12_000_000)
        stream.flush()
        out = os.read(master, 65536).decode()
    finally:
        stream.close()
        os.close(master)
    assert "cycling" in out and "target_ns" in out and not out.lstrip().startswith("{")


def test_bad_level_or_format_is_named():
    with pytest.raises(ValueError, match="'loud'"):
        configure_logging("json", "loud", stream=io.StringIO())
    with pytest.raises(ValueError, match="'xml'"):
        configure_logging("xml", "info", stream=io.StringIO())
