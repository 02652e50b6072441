"""Logging set-up: JSON lines off a terminal, readable lines on a real pty, cheap level filtering."""

from __future__ import annotations

import io
import json
import logging
import os
import re

import pytest
import structlog

from usmswitch.runtime.logsetup import configure_logging, human_units, journal_stream, resolve_format


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
    assert line["priority"] == 6  # syslog's info, for journald and log shippers


def test_json_priority_follows_the_level():
    buf = io.StringIO()
    configure_logging("json", "debug", stream=buf)
    log = structlog.get_logger("usmswitch.daemon")
    log.debug("d")
    log.info("i")
    log.warning("w")
    log.error("e")
    log.critical("c")
    try:
        raise ValueError("x")
    except ValueError:
        log.exception("x")
    logging.getLogger("pymodbus").error("stdlib error")
    got = [(line["event"], line["priority"]) for line in lines(buf)]
    assert got == [("d", 7), ("i", 6), ("w", 4), ("e", 3), ("c", 2), ("x", 3), ("stdlib error", 3)]


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
    assert "cycling" in out and not out.lstrip().startswith("{")
    plain = re.sub(r"\x1b\[[0-9;]*m", "", out)  # colours off
    assert "target=12.000 ms" in plain and "target_ns" not in plain  # units for people, not raw ns


def test_console_shows_units_and_the_json_raw_numbers():
    ed = human_units(
        None,
        "info",
        {
            "event": "summary",
            "error_std_ns": 118374.2,
            "count": 3,
            "t_cmd_ns": 5,
            "max_abs_error_pct": 0.4123,
        },
    )
    assert ed == {
        "event": "summary",
        "error_std": "118.4 us",
        "count": 3,
        "t_cmd_ns": 5,
        "max_abs_error": "0.412 %",
    }
    buf = io.StringIO()
    configure_logging("console", "info", stream=buf)
    structlog.get_logger("usmswitch.daemon").info("summary", error_std_ns=118_374, late=0, wall_ns=17)
    out = buf.getvalue()
    assert "error_std=118.4 us" in out and "wall_ns=17" in out and "priority" not in out
    buf = io.StringIO()
    configure_logging("json", "info", stream=buf)
    structlog.get_logger("usmswitch.daemon").info("summary", error_std_ns=118_374)
    assert lines(buf)[0]["error_std_ns"] == 118_374


def test_journal_stream_gets_syslog_prefixes(tmp_path):
    # systemd sets JOURNAL_STREAM to the device:inode of the stream it gave the service.
    path = tmp_path / "journal"
    with open(path, "w") as stream:
        st = os.fstat(stream.fileno())
        env = {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        assert journal_stream(stream, env)
        assert not journal_stream(stream, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"})
        assert not journal_stream(stream, {})
        assert not journal_stream(io.StringIO(), env)
        configure_logging("json", "info", stream=stream, env=env)
        log = structlog.get_logger("usmswitch.daemon")
        log.info("started")
        log.warning("stroke fault", cycle=3)
        logging.getLogger("pymodbus").error("no answer")
    got = path.read_text().splitlines()
    assert [line[:3] for line in got] == ["<6>", "<4>", "<3>"]
    assert [json.loads(line[3:])["priority"] for line in got] == [6, 4, 3]
    # Not the journal (a file of its own): no prefix, the lines stay plain JSON.
    buf = io.StringIO()
    configure_logging("json", "info", stream=buf, env=env)
    structlog.get_logger().warning("w")
    assert buf.getvalue().startswith("{")


def test_bad_level_or_format_is_named():
    with pytest.raises(ValueError, match="'loud'"):
        configure_logging("json", "loud", stream=io.StringIO())
    with pytest.raises(ValueError, match="'xml'"):
        configure_logging("xml", "info", stream=io.StringIO())
