"""A fresh run's first strokes (issue 22): predicted from what is known, else commissioning strokes.

The simulated rig knows its own stroke, so a fresh `usmswitchd --sim` predicts its first strokes from
the rig model; a serial MCU (the Python emulator on a pty) tells nothing, so with no records and no
configured nominal the first completed stroke of each direction is flagged COMMISSIONING, kept in
the records and listed apart in `stats`, outside the error figures. Real daemons, real sockets.
"""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client
from usmswitch.protocol.record import Flag

MS = 1_000_000


def warm_start_lines(log: bytes) -> list[dict]:
    lines = [json.loads(line) for line in log.decode().splitlines() if line.startswith("{")]
    return [e for e in lines if e["event"] == "warm start"]


def test_a_fresh_sim_run_is_within_5_percent_of_t_from_its_first_stroke(tmp_path: Path) -> None:
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, "--period", "25ms"))
    try:
        daemonproc.wait_serving(tmp_path / "d.sock", proc)
        with Client(str(tmp_path / "d.sock")) as rig:
            run = rig.run(count=200, period="25ms", target="12ms")
            recs = list(run)
            stats = run.stats()
    finally:
        log = daemonproc.stop(proc)
    assert not any(r["flags"] & Flag.COMMISSIONING for r in recs)
    assert stats["all"]["strokes"] == 200 and stats["all"]["commissioning"] == []
    # What the prediction put into each stroke's error: the error less the start's lateness. A
    # virtual machine's vCPU descheduled by its host starts a stroke late even at SCHED_FIFO
    # (cyclictest here: max 5.9 ms), which the LATE flag and `late` count name; a full make test
    # once read 17.6 % so.
    worst = [
        {
            k: r[k]
            for k in ("cycle", "direction", "flags", "error_ns", "lateness_ns", "t_hat_ns", "operating_ns")
        }
        for r in sorted(recs, key=lambda r: -abs(r["error_ns"] - (r["lateness_ns"] or 0)))[:3]
    ]
    assert all(abs(r["error_ns"] - (r["lateness_ns"] or 0)) <= 0.05 * 12 * MS for r in recs), worst
    on_time = [r for r in recs if not r["flags"] & Flag.LATE]
    assert all(abs(r["error_ns"]) <= 0.05 * 12 * MS for r in on_time), worst
    if stats["all"]["late"] == 0:
        assert stats["all"]["max_abs_error_pct"] <= 5.0, (stats["all"], worst)
    warm = warm_start_lines(log)
    assert [w["first_prediction"] for w in warm] == ["rig model", "rig model"]
    # The start-up run, the first strokes the daemon ever made, is as good: its prediction, the
    # error less the start's lateness as above (a start is as exposed to the host there as later;
    # a make test read a second stroke's error 6.1 % of T, its lateness not kept).
    with _records(tmp_path) as db:
        first = db.execute("SELECT error_ns, lateness_ns, target_ns FROM cycles WHERE cycle <= 2").fetchall()
    assert all(abs(e - (late or 0)) <= 0.05 * t for e, late, t in first), first
    late = [r["lateness_ns"] for r in recs if r["flags"] & Flag.LATE]
    if len(late) > 5:
        # How many strokes start on time is the host's scheduling, not the prediction: on a busy
        # VM (7f3fa01 too: 2-24 of 200 late here) it cannot be judged; the prediction was, above.
        pytest.xfail(
            f"{len(late)} of 200 strokes started late (worst {max(late) / 1e6:.3f} ms): the host is too"
            " busy now to judge how many start on time"
        )


def _records(tmp: Path) -> sqlite3.Connection:
    return sqlite3.connect(tmp / "state" / "records.sqlite")


@pytest.fixture
def mcu_link(tmp_path: Path) -> Iterator[Path]:
    link = tmp_path / "usmswitch"
    emu = subprocess.Popen(
        [sys.executable, "-m", "usmswitch.sim.mcu_emulator", "--link", str(link), "--seed", "5"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        assert emu.stdout is not None and emu.stdout.readline().startswith(b"mcu emulator on")
        yield link
    finally:
        emu.send_signal(signal.SIGTERM)
        emu.communicate(timeout=10)


def serial_run(tmp: Path, link: Path, strokes: int) -> tuple[list[dict], dict, bytes]:
    args = ["--driver", "serial", "--port", str(link), "--target", "12ms", *daemonproc.slow_link(tmp)]
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp, *args, sim=False))
    try:
        daemonproc.wait_serving(tmp / "d.sock", proc)
        with Client(str(tmp / "d.sock"), timeout=10) as rig:
            run = rig.run(count=strokes, period="30ms", target="12ms", timeout=10)
            recs = list(run)
            stats = run.stats()
    finally:
        log = daemonproc.stop(proc)
    assert proc.returncode == 0, log.decode()[-3000:]
    return recs, stats, log


def test_a_rig_nothing_is_known_of_commissions_each_direction_once(tmp_path: Path, mcu_link: Path) -> None:
    recs, stats, log = serial_run(tmp_path, mcu_link, 40)
    warm = warm_start_lines(log)
    assert [w["first_prediction"] for w in warm] == ["guess", "guess"]
    flagged = [r for r in recs if r["flags"] & Flag.COMMISSIONING]
    assert [r["direction"] for r in flagged] == sorted({r["direction"] for r in recs})
    assert all(r["cycle"] in (recs[0]["cycle"], recs[1]["cycle"]) for r in flagged)
    shown = stats["all"]["commissioning"]
    assert [(c["cycle"], c["error_ns"]) for c in shown] == [(r["cycle"], r["error_ns"]) for r in flagged], [
        (r["cycle"], Flag(r["flags"])) for r in flagged
    ]
    # Apart: the error figures are those of the other strokes, and every stroke is still counted.
    others = [abs(r["error_ns"]) for r in recs if not r["flags"] & Flag.COMMISSIONING]
    assert stats["all"]["error_max_abs_ns"] == max(others)
    assert stats["all"]["strokes"] == 40
    # The guessed strokes are the outliers the figures keep apart: against the others' prediction
    # error (a start the busy host made late is its lateness, not the prediction's).
    predicted = [
        abs(r["error_ns"] - (r["lateness_ns"] or 0)) for r in recs if not r["flags"] & Flag.COMMISSIONING
    ]
    assert max(abs(r["error_ns"]) for r in flagged) > max(predicted)
    with _records(tmp_path) as db:
        kept = db.execute(
            "SELECT count(*) FROM cycles WHERE flags & ? != 0", (int(Flag.COMMISSIONING),)
        ).fetchone()
    assert kept == (len(flagged),)

    # Restarted, the records are what is known: no commissioning again.
    recs2, stats2, log2 = serial_run(tmp_path, mcu_link, 10)
    assert [w["first_prediction"] for w in warm_start_lines(log2)] == ["records", "records"]
    assert not any(r["flags"] & Flag.COMMISSIONING for r in recs2) and stats2["all"]["commissioning"] == []
