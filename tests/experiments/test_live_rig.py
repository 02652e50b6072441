"""Experiments against a live daemon leave the rig as they found it (issue 25): every setting they
change comes back when they end, fail or are interrupted, a run a client started is refused unless
taken over, and the report lists what was put back. With --queue (issue 38) an experiment waits for
the run going in the daemon's queue, never ends it, and holds the rig for its runs once its turn
comes. A real usmswitchd (the simulated rig in real
time, cycling by itself as `make run` starts it) and the real `usmswitch-experiment` subprocess."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client

KEYS = ("state", "mode", "open_delay_ns", "target_on_ns", "target_off_ns")


@pytest.fixture
def live(tmp_path: Path) -> Iterator[Path]:
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, "--target", "13ms", "--period", "30ms"))
    try:
        daemonproc.wait_serving(tmp_path / "d.sock", proc)
        yield tmp_path / "d.sock"
    finally:
        daemonproc.stop(proc)


def settings(sock: Path) -> dict:
    with Client(str(sock)) as c:
        st = c.status()
        drive = c.set_drive()
    return {
        **{k: st[k] for k in KEYS},
        "frequency_hz": drive["frequency_hz"],
        "voltage_vpp": drive["voltage_vpp"],
    }


def experiment(sock: Path, out: Path, *extra: str, name: str = "open-loop") -> subprocess.Popen[str]:
    cmd = [sys.executable, "-m", "usmswitch.experiments", name, "--socket", str(sock), "--out", str(out)]
    return subprocess.Popen(
        [*cmd, "--scale", "0.01", *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def test_an_experiment_puts_back_every_setting_it_changed(live: Path, tmp_path: Path) -> None:
    before = settings(live)
    assert before["state"] == "cycling" and before["target_on_ns"] == 13_000_000
    proc = experiment(live, tmp_path / "x")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert settings(live) == before
    restored = json.loads((tmp_path / "x" / "summary.json").read_text())["meta"]["restored"]
    assert any(r.startswith("mode: open") for r in restored) and any("target on" in r for r in restored)
    assert any(r.startswith("cycling: run 1 (autostart) started again") for r in restored), restored
    report = (tmp_path / "x" / "report.md").read_text()
    assert "put back when they ended" in report and restored[0] in report
    with Client(str(live)) as c:  # the start-up run is the daemon's again: a script may take it over
        assert c.runs(1)[-1]["settings"]["owner"] == "autostart"


def test_interrupted_with_ctrl_c_it_still_puts_everything_back(live: Path, tmp_path: Path) -> None:
    before = settings(live)
    proc = experiment(live, tmp_path / "x")
    with Client(str(live)) as c:  # wait until the experiment's own run is going
        deadline = time.monotonic() + 30
        while c.runs(1)[-1]["settings"].get("owner") == "autostart" or c.status()["mode"] != "open":
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode != 0
    assert settings(live) == before, err


def test_a_run_a_client_started_is_refused_by_name_unless_taken_over(live: Path, tmp_path: Path) -> None:
    with Client(str(live)) as c:
        theirs = c.start_cycling("30ms", 0, target="13ms", take_over=True)
    before = settings(live)
    proc = experiment(live, tmp_path / "x")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 1 and f"run {theirs['run_id']} (" in err and "--take-over" in err
    assert settings(live) == before
    with Client(str(live)) as c:
        assert c.runs(1)[-1]["run_id"] == theirs["run_id"]  # left going, untouched
    proc = experiment(live, tmp_path / "y", "--take-over")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert settings(live) == before
    with Client(str(live)) as c:
        again = c.runs(1)[-1]
    assert again["end_reason"] is None and again["settings"]["owner"] != "autostart"
    assert again["settings"]["period_ns"] == 30_000_000


def test_with_queue_an_experiment_waits_behind_the_run_going_and_never_ends_it(
    live: Path, tmp_path: Path
) -> None:
    with Client(str(live)) as c:
        theirs = c.start_cycling("30ms", 0, target="13ms", take_over=True, owner="lab script")["run_id"]
        before = settings(live)
        proc = experiment(live, tmp_path / "x", "--queue", name="closed-loop")
        deadline = time.monotonic() + 60  # its turn queued: it waits (a condition, not a time claim)
        while not (queued := c.status()["queue"]["queued"]):
            assert time.monotonic() < deadline and proc.poll() is None, proc.stderr
            time.sleep(0.05)
        (turn,) = queued
        assert turn["label"] == "experiment-hold" and turn["owner"] != "lab script"
        going = c.status()["run"]
        assert going["run_id"] == theirs and going["end_reason"] is None  # not ended, not refused
        assert proc.poll() is None
        c.stop_cycling()  # their run ends by their hand: the experiment's turn comes
        # Queued now, behind the experiment's turn: it runs once the experiment gives the rig back.
        after = c.submit_entry("30ms", 5, target="13ms", label="after")["entry"]
        _, err = proc.communicate(timeout=180)
        assert proc.returncode == 0, err
        assert "waiting for the rig" in err and "the rig is the experiment's" in err
        deadline = time.monotonic() + 60
        while not any(r["settings"].get("queue_entry") == after and r["end_reason"] for r in c.runs(50)):
            assert time.monotonic() < deadline, c.status()["queue"]
            time.sleep(0.05)
        runs = c.runs(50)
    by_id = {r["run_id"]: r for r in runs}
    assert by_id[theirs]["end_reason"] == "stopped"  # never "taken over"
    mine = [r for r in runs if r["label"] == "experiment"]
    holds = [r for r in runs if r["label"] == "experiment-hold"]
    (later,) = [r for r in runs if r["settings"].get("queue_entry") == after]
    assert [r["notes"] for r in mine] == ["closed-loop 12 ms", "closed-loop 24 ms"]
    assert all(r["end_reason"] == "done" for r in mine)
    ours = sorted(mine + holds, key=lambda r: r["run_id"])
    # One stretch of the experiment's runs, hold - run - hold - run - hold, nothing of another's
    # between them; the run queued meanwhile after it, the one going before it.
    assert [r["label"] for r in ours] == ["experiment-hold", "experiment"] * 2 + ["experiment-hold"]
    assert [r["run_id"] for r in ours] == list(range(ours[0]["run_id"], ours[-1]["run_id"] + 1))
    assert ours[0]["first_cycle"] > by_id[theirs]["last_cycle"]
    assert later["first_cycle"] > ours[-1]["last_cycle"] and later["end_reason"] == "done"
    now = settings(live)
    assert {k: now[k] for k in now if k != "state"} == {k: before[k] for k in before if k != "state"}
    restored = json.loads((tmp_path / "x" / "summary.json").read_text())["meta"]["restored"]
    assert any("hold on the rig ended" in r for r in restored), restored
