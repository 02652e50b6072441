"""End to end in real time: usmswitchd --driver serial on the MCU emulator's pty, closed loop."""

from __future__ import annotations

import re
import signal
import sqlite3
import statistics
import subprocess
import sys
import time
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client, RpcError
from usmswitch.runtime.realtime import AUTO_PRIORITY, fifo_refusal

MS = 1_000_000
STROKES = 320

pytestmark = pytest.mark.realtime


def test_closed_loop_over_serial_records_every_stroke(tmp_path: Path) -> None:
    link = tmp_path / "usmswitch"
    # The device is a chip of its own, which the host's other work never deschedules: its stand-in
    # runs at the daemon's SCHED_FIFO priority where this process may use it. At SCHED_OTHER beside
    # a busy machine the emulator read COMMANDs the daemon had sent 4 ms ahead after their instant
    # (112 of 320 strokes LATE), the harness's lateness, not the daemon's.
    refused = fifo_refusal(AUTO_PRIORITY)
    emu = subprocess.Popen(
        [sys.executable, "-m", "usmswitch.sim.mcu_emulator", "--link", str(link), "--seed", "3",
         "--clock-start-us", str(2**32 - 3_000_000),  # the device clock wraps during the run
         "--sched-fifo", str(0 if refused else AUTO_PRIORITY)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )  # fmt: skip
    daemon = None
    try:
        ready = emu.stdout.readline()
        assert ready.startswith(b"mcu emulator on"), ready or emu.stderr.read()
        assert refused or ready.rstrip().endswith(f"SCHED_FIFO {AUTO_PRIORITY}".encode()), ready
        sock = tmp_path / "d.sock"
        args = ["--driver", "serial", "--port", str(link), "--target", "12ms", "--period", "24ms"]
        daemon = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args, sim=False))
        daemonproc.wait_serving(sock, daemon)
        with Client(str(sock), timeout=5) as c:
            st = c.status()
        # On hardware the daemon starts idle: a motor never moves unasked.
        assert st["state"] == "idle" and st["driver"] == "serial"
        with Client(str(sock), timeout=30) as c:
            c.start_cycling(24 * MS, STROKES)
            with c.subscribe("stroke", timeout=5) as sub:
                for rec in (note.payload for note in sub):
                    if rec["cycle"] >= STROKES:
                        break
            stats = c.stats()
    finally:
        if daemon is not None:
            daemon.send_signal(signal.SIGTERM)
            _, err = daemon.communicate(timeout=20)
            assert daemon.returncode == 0, err.decode()[-3000:]
        emu.send_signal(signal.SIGTERM)
        emu.communicate(timeout=10)
    con = sqlite3.connect(tmp_path / "state" / "records.sqlite")
    rows = list(con.execute("SELECT cycle, error_ns, flags, lateness_ns FROM cycles ORDER BY cycle"))
    con.close()
    assert [r[0] for r in rows] == list(range(1, STROKES + 1))
    assert all(r[1] is not None for r in rows)  # every stroke arrived and was stamped
    assert stats["all"]["stalls"] == 0
    # The error of the strokes started on time: a start late (a COMMAND sent late, or read late by
    # an emulator the host descheduled) is flagged LATE and counted below, not spread into the std
    # (361 us with the suite beside it, where the on-time strokes read ~90 us).
    errs = [r[1] for r in rows[100:] if not r[2] & 1]
    std = statistics.pstdev(errs)
    late = sum(1 for r in rows if r[2] & 1)
    print(f"\nserial e2e: {len(rows)} strokes, error std {std / 1e3:.1f} us, late {late}")
    # As on the sim driver (~90 us): the device times the start, the host only arms ahead.
    assert std < 200_000
    if refused:
        pytest.skip(
            f"every stroke recorded, error std {std / 1e3:.1f} us; {late} LATE not judged: the emulator"
            f" ran at SCHED_OTHER ({refused}), so a start late may be the harness's, not the daemon's"
        )
    assert late <= STROKES // 20


def test_unplug_mid_run_faults_reconnects_and_loses_no_record(tmp_path: Path) -> None:
    """Unplug the MCU while cycling: FAULT, drive off, every attempt recorded; replug, reset, go on."""
    from usmswitch.sim.mcu_emulator import McuEmulator, PtyLink

    emu = McuEmulator(seed=5).start()
    link = PtyLink(emu, tmp_path / "usmswitch").plug()
    sock = tmp_path / "d.sock"
    args = ["--driver", "serial", "--port", str(tmp_path / "usmswitch"), "--period", "24ms"]
    daemon = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args, sim=False))
    try:
        daemonproc.wait_serving(sock, daemon)
        with Client(str(sock), timeout=30) as c:
            c.start_cycling(24 * MS, 0)
            with c.subscribe("stroke", timeout=5) as sub:
                for rec in (note.payload for note in sub):
                    if rec["cycle"] >= 30:
                        break
            link.unplug()
            end = time.monotonic() + 10
            while c.status()["state"] != "fault":
                assert time.monotonic() < end
                time.sleep(0.05)
            assert re.search(r"disconnect|link lost", c.status()["fault"])
            link.replug()
            end = time.monotonic() + 15
            while True:  # the driver reconnects with backoff and re-handshakes on its own
                try:
                    c.reset_fault()
                    c.start_cycling(24 * MS, 20)
                    break
                except RpcError:
                    assert time.monotonic() < end
                    time.sleep(0.2)
            while c.status()["state"] == "cycling":
                time.sleep(0.1)
            st = c.status()
    except Exception as exc:
        failure: Exception | None = exc
    else:
        failure = None
    finally:
        daemon.send_signal(signal.SIGTERM)
        _, err = daemon.communicate(timeout=20)
        link.close()
        emu.stop()
    if failure is not None:  # with the daemon's own account of it
        raise AssertionError(err.decode()[-4000:]) from failure
    assert daemon.returncode == 0, err.decode()[-3000:]
    assert st["state"] in ("idle", "fault")
    con = sqlite3.connect(tmp_path / "state" / "records.sqlite")
    rows = list(con.execute("SELECT cycle, flags, t_arrive_ns FROM cycles ORDER BY cycle"))
    con.close()
    assert [r[0] for r in rows] == list(range(1, len(rows) + 1))  # no hole: every attempt has its row
    faulted = [r for r in rows if r[1] & 16]
    assert faulted, "the stroke the unplug interrupted is recorded as a fault"
    after = rows[rows.index(faulted[0]) + 1 :]
    assert sum(1 for r in after if r[2] is not None) >= 15
