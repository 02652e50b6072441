"""The daemon's log as the service writes it: journald priorities, and no summary repeated while idle."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import time
from pathlib import Path

import daemonproc

from usmswitch.client import Client


def _read_until(fd: int, needle: bytes, timeout_s: float) -> bytes:
    out = b""
    end = time.monotonic() + timeout_s
    while needle not in out and time.monotonic() < end:
        ready, _, _ = select.select([fd], [], [], 0.1)
        if ready:
            chunk = os.read(fd, 65536)
            if not chunk:
                break
            out += chunk
    return out


def test_under_journald_every_line_carries_its_syslog_priority(tmp_path: Path) -> None:
    # The journal's stream is the daemon's stderr: systemd names it in JOURNAL_STREAM (device:inode).
    conf = tmp_path / "faults.toml"
    conf.write_text('[sim.faults]\nschedule = { 3 = "stall" }\n')
    r, w = os.pipe()
    st = os.fstat(w)
    env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
    args = daemonproc.daemon_args(tmp_path, "--config", str(conf), "--sim-clock", "virtual", "--autostart")
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=w, env=env)
    os.close(w)
    try:
        out = _read_until(r, b'"stroke fault"', 30)
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)
        out += _read_until(r, b"\x00", 2)  # the rest, to EOF
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(r)
    lines = out.decode().splitlines()
    assert lines and all(line[:1] == "<" and line[2:4] == ">{" for line in lines), lines[:5]
    entries = [(int(line[1]), json.loads(line[3:])) for line in lines]
    assert all(prefix == e["priority"] for prefix, e in entries)
    by_event = {e["event"]: prefix for prefix, e in entries}
    assert by_event["started"] == 6  # info
    assert by_event["stroke fault"] == 4  # warning: `journalctl -p warning` finds it


def test_an_idle_daemon_does_not_repeat_its_summary(tmp_path: Path) -> None:
    conf = tmp_path / "quick.toml"
    conf.write_text('[daemon]\nsummary_interval = "100ms"\n')
    sock = tmp_path / "d.sock"
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, "--config", str(conf), "--no-autostart"))
    try:
        daemonproc.wait_serving(sock, proc)
        time.sleep(1.5)  # 15 summary intervals with nothing happening
        with Client(str(sock)) as c:
            c.switch("on")
        time.sleep(0.5)
    finally:
        err = daemonproc.stop(proc)
    assert proc.returncode == 0, err.decode()[-2000:]
    summaries = [e for e in map(json.loads, err.decode().splitlines()) if e["event"] == "summary"]
    # One when idle (nothing changes after it), one after the stroke; the old daemon printed ~20.
    assert [s["count"] for s in summaries] == [0, 1], summaries
    assert isinstance(summaries[1]["error_std_ns"], int)  # raw integer ns in the JSON log
    assert isinstance(summaries[1]["error_mean_ns"], int)
