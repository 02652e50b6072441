"""The examples/ lab scripts as subprocesses against a real usmswitchd on the simulated rig.

The daemon starts with the sim's default, cycling on its own, so the script's "stop what is running
first" path is exercised; the script runs a small stroke count to stay fast.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client

MS = 1_000_000
EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.fixture(scope="module")
def daemon_socket(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    tmp = tmp_path_factory.mktemp("examples")
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp, "--log-level", "warning", "--period", "20ms"))
    try:
        daemonproc.wait_serving(tmp / "d.sock", proc)
        yield tmp / "d.sock"
    finally:
        daemonproc.stop(proc)


def run_example(sock: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(EXAMPLES / "run_500_strokes.py"), "--socket", str(sock), *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_run_strokes_json_matches_the_records(daemon_socket: Path) -> None:
    r = run_example(daemon_socket, "--strokes", "40", "--period", "20ms", "--target", "13ms", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["target_ns"] == 13 * MS and out["last_cycle"] - out["first_cycle"] == 39
    s = out["summary"]
    assert s["all"]["strokes"] == 40 and s["on"]["strokes"] == s["off"]["strokes"] == 20
    with Client(str(daemon_socket)) as c:
        recs = [x for x in c.history(200) if out["first_cycle"] <= x["cycle"] <= out["last_cycle"]]
        status = c.status()
        end = time.monotonic() + 5
        while status["state"] == "cycling" and time.monotonic() < end:  # the loop idles after the last
            time.sleep(0.02)
            status = c.status()
    assert status["state"] == "idle" and status["target_on_ns"] == 13 * MS  # the script set T and finished
    assert {x["target_ns"] for x in recs} == {13 * MS}
    errors = [x["error_ns"] for x in recs if x["error_ns"] is not None]
    assert s["all"]["error_std_ns"] == pytest.approx(statistics.stdev(errors))
    assert s["all"]["error_max_abs_ns"] == max(abs(e) for e in errors)
    ranked = sorted(abs(e) for e in errors)
    assert s["all"]["abs_error_p50_ns"] == ranked[19] and s["all"]["abs_error_p99_ns"] == ranked[39]
    assert s["all"]["abs_error_p95_ns"] == ranked[37]  # nearest rank: ceil(0.95 * 40) = 38th
    on_errors = [x["error_ns"] for x in recs if x["direction"] == 0 and x["error_ns"] is not None]
    assert s["on"]["error_mean_ns"] == pytest.approx(statistics.fmean(on_errors))
    assert out["order"]["on"] >= 1 and len(out["coefficients"]["on"]) >= 1


def test_run_strokes_prints_the_table(daemon_socket: Path) -> None:
    r = run_example(daemon_socket, "--strokes", "10", "--period", "20ms", "--progress", "5")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].strip().startswith("5/10 strokes") and lines[1].strip().startswith("10/10 strokes")
    assert lines[2] == "10 strokes, mode closed, T = 12.000 ms"
    assert lines[3].split() == ["on", "off", "all"]
    for label in ("error std", "max |error| % of T", "|error| p99", "model order"):
        assert any(line.startswith(label) for line in lines), label
    assert lines[-1].startswith("paper, closed loop at T = 12.000 ms: error std 95.3 us")


def test_bad_arguments_and_no_daemon(tmp_path: Path) -> None:
    r = run_example(tmp_path / "none.sock", "--period", "10ms", "--target", "12ms")
    assert r.returncode == 2 and "--period" in r.stderr
    r = run_example(tmp_path / "none.sock", "--strokes", "5")
    assert r.returncode == 1 and "none.sock" in r.stderr and "Traceback" not in r.stderr
