"""How a client's run meets a run already going (issue 22): the daemon's own start-up run (what
`make run` starts) gives way with a log line; a run another client started is refused naming it,
unless taken over deliberately. A real usmswitchd subprocess on the simulated rig."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client, WrongState
from usmswitch.client.api import run_owner


@pytest.fixture
def cycling_daemon(tmp_path: Path) -> Iterator[tuple[Path, subprocess.Popen[bytes]]]:
    """`usmswitchd --sim` as `make run` starts it: cycling on its own from the start."""
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, "--period", "20ms"))
    try:
        daemonproc.wait_serving(tmp_path / "d.sock", proc)
        with Client(str(tmp_path / "d.sock")) as rig:  # the start-up run is queued just after the socket
            deadline = time.monotonic() + 10
            while rig.status()["state"] != "cycling":
                assert time.monotonic() < deadline
                time.sleep(0.01)
        yield tmp_path / "d.sock", proc
    finally:
        if proc.poll() is None:
            daemonproc.stop(proc)


def test_a_clients_run_takes_over_the_start_up_run_and_says_so(
    cycling_daemon: tuple[Path, subprocess.Popen[bytes]],
) -> None:
    sock, proc = cycling_daemon
    with Client(str(sock)) as rig:
        assert rig.status()["state"] == "cycling"
        (startup,) = rig.runs()
        assert startup["settings"]["owner"] == "autostart" and startup["end_reason"] is None
        run = rig.run(count=10, period="20ms", target="12ms")
        assert run.started["took_over"] == startup["run_id"]
        assert len(list(run)) == 10
        ended = {r["run_id"]: r for r in rig.runs()}
        assert ended[startup["run_id"]]["end_reason"] == f"taken over by {run_owner()}"
        assert ended[run.run_id]["settings"]["owner"] == run_owner()
    log = [json.loads(line) for line in daemonproc.stop(proc).decode().splitlines() if line.startswith("{")]
    taken = [e for e in log if e["event"] == "run taken over"]
    assert taken and taken[0]["run"] == startup["run_id"] and taken[0]["by"] == run_owner()


def test_a_run_another_client_started_is_refused_naming_it_unless_taken_over(
    cycling_daemon: tuple[Path, subprocess.Popen[bytes]],
) -> None:
    sock, _ = cycling_daemon
    with Client(str(sock)) as first, Client(str(sock)) as second:
        theirs = first.start_cycling("20ms", 0, target="12ms")
        with pytest.raises(WrongState) as refused:
            second.run(count=5, period="20ms")
        message = refused.value.message
        assert f"run {theirs['run_id']} ({run_owner()}" in message
        assert "take_over=True" in message and "--take-over" in message
        assert first.status()["state"] == "cycling" and first.runs()[-1]["run_id"] == theirs["run_id"]
        mine = second.run(count=5, period="20ms", take_over=True)
        assert mine.started["took_over"] == theirs["run_id"] and len(list(mine)) == 5


def test_usmswitchctl_cycle_names_the_run_going_and_takes_it_over_when_told(
    cycling_daemon: tuple[Path, subprocess.Popen[bytes]],
) -> None:
    sock, _ = cycling_daemon
    ctl = [sys.executable, "-m", "usmswitch.client.ctl", "--socket", str(sock)]
    first = subprocess.run(
        [*ctl, "cycle", "--count", "0", "--period", "20ms"], capture_output=True, text=True
    )
    assert first.returncode == 0, first.stderr  # the start-up run gave way
    second = subprocess.run(
        [*ctl, "cycle", "--count", "5", "--period", "20ms"], capture_output=True, text=True
    )
    assert (
        second.returncode != 0
        and "already cycling: run 2 (" in second.stderr
        and "--take-over" in second.stderr
    )
    third = subprocess.run(
        [*ctl, "cycle", "--count", "5", "--period", "20ms", "--take-over", "--wait"],
        capture_output=True,
        text=True,
    )
    assert third.returncode == 0, third.stderr
