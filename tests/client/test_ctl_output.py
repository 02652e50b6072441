"""What usmswitchctl prints for people: names and units, the watch view's alignment and its live
footer on a real terminal, the cycle progress bar, CSV names beside numbers."""

from __future__ import annotations

import io
import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client.ctl import output as out
from usmswitch.protocol.record import FIELDS, Flag

MS = 1_000_000
BIN = Path(sys.executable).parent / "usmswitchctl"
CTL = [str(BIN)] if BIN.exists() else [sys.executable, "-m", "usmswitch.client.ctl"]


def record(cycle: int, error_ns: int, flags: int = 0, direction: int = 0) -> dict:
    rec = dict.fromkeys(FIELDS)
    rec.update(
        cycle=cycle,
        direction=direction,
        mode="closed",
        target_ns=12 * MS,
        order=1,
        coefficients=[0.99],
        t_hat_ns=10_500_000,
        delay_ns=1_500_000,
        t_cmd_ns=10**12,
        operating_ns=10_500_000 + error_ns,
        total_ns=12 * MS + error_ns,
        error_ns=error_ns,
        lateness_ns=1_200,
        flags=flags,
        wall_ns=1_700_000_000 * 10**9,
    )
    return rec


def test_watch_header_lines_up_with_every_row() -> None:
    buf = io.StringIO()
    with out.WatchView(buf, live=False) as view:
        view.stroke(record(7, 5))  # the header is printed with the first, short values
        view.stroke(record(8, -999_999, int(Flag.LATE | Flag.CLAMPED | Flag.WARMUP)))
        view.stroke(record(123_456_789, 1_234_567, direction=1))
        view.state({"state": "fault", "fault": "stall"})
    lines = buf.getvalue().splitlines()
    header, rows = lines[0], lines[1:4]
    assert header.split()[:3] == ["cycle", "dir", "mode"] and lines[4] == "# state fault (stall)"
    end = 0
    for name, width, left in out.WATCH_COLUMNS[:-1]:  # every column but the last (flags)
        start, end = end, end + width
        if not left:  # right-aligned: the header and every value end in the same place
            for line in (header, *rows):
                assert line[end - 1] != " " and line[start - 2 : start] in ("", "  "), (name, line)
        end += 2
    assert all(
        line[end:].split()[0] == line_flags
        for line, line_flags in zip(rows, ["-", "LATE|CLAMPED|WARMUP", "-"], strict=True)
    )


def test_names_and_units_for_people() -> None:
    rows = dict(out.record_rows(record(3, -2_500)))  # type: ignore[arg-type]
    assert rows["target"] == "12.000 ms" and rows["error"] == "-2.5 us" and rows["direction"] == "on"
    assert rows["command at"] == f"{10**12} ns (clock)" and rows["model order"] == "1"
    assert not any(label.endswith("_ns") for label in rows)
    status = {
        "state": "idle",
        "fault": None,
        "mode": "closed",
        "target_on_ns": 12 * MS,
        "target_off_ns": 12 * MS,
        "cycle": 5,
        "driver": "sim",
        "driver_ok": True,
        "version": "0.1.0",
        "protocol_version": 1,
        "uptime_ns": 14_514_742_000,
    }
    text = out.status_table(status)
    assert re.search(r"^uptime +14\.5 s$", text, re.M) and "14.514742" not in text
    assert "2 h 03 min" in out.status_table({**status, "uptime_ns": 7_380 * 10**9})
    drive = out.drive_table(
        {"frequency_hz": 39_600.0, "voltage_vpp": 500.0, "enabled": True, "temperature_c": None}
    )
    assert [line.split(None, 1) for line in drive.splitlines()] == [
        ["frequency", "39.6000 kHz"],
        ["voltage", "500 Vpp"],
        ["drive", "on"],
        ["temperature", "-"],
    ]


def test_csv_has_names_beside_the_numbers() -> None:
    buf = io.StringIO()
    out.write_csv([record(1, 5, int(Flag.LATE | Flag.CLAMPED), direction=1), record(2, 5)], buf)
    import csv

    rows = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert [(r["direction"], r["direction_name"], r["flags"], r["flag_names"]) for r in rows] == [
        ("1", "off", "3", "LATE|CLAMPED"),
        ("0", "on", "0", ""),
    ]


def test_the_daemon_and_a_pipe_run_without_rich(tmp_path: Path) -> None:
    # rich is for usmswitchctl's live views only. With it made unimportable, a daemon runs strokes
    # and stops cleanly, and the views for a pipe work (structlog uses rich only when it is there).
    code = (
        "import io, os, signal, sys, threading\n"
        "sys.modules['rich'] = None  # any import of rich now fails\n"
        "from usmswitch.client.ctl import output\n"
        "with output.WatchView(io.StringIO()) as v: pass\n"
        "with output.CycleProgress(1, 10, io.StringIO()) as p: p.update(5)\n"
        "from usmswitch.daemon.cli import main\n"
        "threading.Timer(1.5, os.kill, (os.getpid(), signal.SIGTERM)).start()\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    args = daemonproc.daemon_args(tmp_path, "--sim-clock", "virtual", "--autostart", "--count", "20")[3:]
    r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    assert '"final summary"' in r.stderr and '"count": 20' in r.stderr


# -- on a real terminal ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sock(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    tmp = tmp_path_factory.mktemp("tty")
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp, "--no-autostart", "--log-level", "warning"))
    try:
        daemonproc.wait_serving(tmp / "d.sock", proc)
        yield tmp / "d.sock"
    finally:
        daemonproc.stop(proc)


def on_a_terminal(*args: str, timeout_s: float = 30) -> tuple[int, str]:
    """usmswitchctl ARGS with stdout on a pty (a person's terminal); returns the exit code and the text."""
    master, slave = os.openpty()
    env = {**os.environ, "COLUMNS": "200", "TERM": "xterm"}
    proc = subprocess.Popen([*CTL, *args], stdout=slave, stderr=subprocess.PIPE, env=env)
    os.close(slave)
    text = b""
    end = time.monotonic() + timeout_s
    try:
        while time.monotonic() < end:
            ready, _, _ = select.select([master], [], [], 0.1)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # the pty's other end closed
                    break
                if not chunk:
                    break
                text += chunk
            elif proc.poll() is not None:
                break
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
    return proc.returncode, text.decode(errors="replace")


def test_live_views_on_a_terminal(sock: Path) -> None:
    code, text = on_a_terminal("--socket", str(sock), "cycle", "--period", "20ms", "--count", "15", "--wait")
    assert code == 0, text
    assert "15/15" in text and "ended: done, 15 strokes" in text  # rich's progress bar, drawn on the terminal
    assert (
        subprocess.run([*CTL, "--socket", str(sock), "cycle", "--period", "20ms"], timeout=30).returncode == 0
    )
    try:
        code, text = on_a_terminal("--socket", str(sock), "watch", "--count", "25")
    finally:
        subprocess.run([*CTL, "--socket", str(sock), "stop"], timeout=30, check=False)
    assert code == 0, text
    assert re.search(r"strokes \d+ \| error mean", text)  # the live footer under the stroke lines
    assert "watched 25 strokes" in text and text.count("closed") >= 25


def test_ctrl_c_during_cycle_wait_exits_130(sock: Path) -> None:
    proc = subprocess.Popen(
        [*CTL, "--socket", str(sock), "cycle", "--period", "20ms", "--wait"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None and "every 20.000 ms" in proc.stdout.readline()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        subprocess.run([*CTL, "--socket", str(sock), "stop"], timeout=30, check=False)
    assert proc.returncode == 130 and "interrupted; the daemon keeps cycling" in err
