"""The examples/ lab scripts as subprocesses against a real usmswitchd on the simulated rig.

The daemon starts with the sim's default, cycling on its own, so the script's "stop what is running
first" path is exercised; the script runs a small stroke count to stay fast.
"""

from __future__ import annotations

import json
import os
import re
import signal
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


def run_example(
    sock: Path, *args: str, script: str = "run_500_strokes.py"
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={**os.environ, "USMSWITCH_SOCKET": str(sock)},
    )


def test_run_strokes_json_is_the_runs_own_statistics(daemon_socket: Path) -> None:
    r = run_example(daemon_socket, "--strokes", "40", "--period", "20ms", "--target", "13ms", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    run = out["run"]
    assert run["settings"]["target_on_ns"] == 13 * MS and run["end_reason"] == "done"
    assert run["last_cycle"] - run["first_cycle"] == 39
    s = out
    assert s["all"]["strokes"] == 40 and s["on"]["strokes"] == s["off"]["strokes"] == 20
    with Client(str(daemon_socket)) as c:
        recs = c.history(200, run=run["run_id"])
        status = c.status()
    assert status["state"] == "idle" and status["target_on_ns"] == 13 * MS  # the script set T and finished
    assert [x["cycle"] for x in recs] == list(range(run["first_cycle"], run["last_cycle"] + 1))
    assert {x["target_ns"] for x in recs} == {13 * MS}
    errors = [x["error_ns"] for x in recs if x["error_ns"] is not None]
    assert s["all"]["error_std_ns"] == pytest.approx(statistics.stdev(errors), abs=0.1)
    assert s["all"]["error_max_abs_ns"] == max(abs(e) for e in errors)
    ranked = sorted(abs(e) for e in errors)
    assert s["all"]["abs_error_p50_ns"] == ranked[19] and s["all"]["abs_error_p99_ns"] == ranked[39]
    assert s["all"]["abs_error_p95_ns"] == ranked[37]  # nearest rank: ceil(0.95 * 40) = 38th
    on_errors = [x["error_ns"] for x in recs if x["direction"] == 0 and x["error_ns"] is not None]
    assert s["on"]["error_mean_ns"] == pytest.approx(statistics.fmean(on_errors), abs=0.1)
    assert s["on"]["order"] >= 1 and len(s["on"]["coefficients"]) >= 1


def test_run_strokes_prints_the_table(daemon_socket: Path) -> None:
    r = run_example(daemon_socket, "--strokes", "10", "--period", "20ms", "--progress", "5")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].strip().startswith("5/10 strokes") and lines[1].strip().startswith("10/10 strokes")
    assert lines[2].startswith("run ") and lines[2].endswith(": 10 strokes, mode closed, T = 12.000 ms, done")
    assert lines[3].split() == ["on", "off", "all"]
    for label in ("error std", "max |error| % of T", "|error| p99", "model order"):
        assert any(line.startswith(label) for line in lines), label
    assert lines[-1].startswith("paper, closed loop at T = 12.000 ms: error std 95.3 us")


def test_the_sweep_gets_each_targets_own_run(daemon_socket: Path) -> None:
    r = run_example(daemon_socket, script="sweep_targets.py")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert [line.split(":")[0] for line in lines] == ["T = 12ms", "T = 13ms", "T = 14ms"]
    runs = [int(line.split("run ")[1].split(",")[0]) for line in lines]
    assert all(", 100 strokes, error std " in line for line in lines)
    with Client(str(daemon_socket)) as c:
        for run_id, target_ns in zip(runs, (12 * MS, 13 * MS, 14 * MS), strict=True):
            recs = c.history(1000, run=run_id)
            assert len(recs) == 100 and {x["target_ns"] for x in recs} == {target_ns}


def test_bad_arguments_and_no_daemon(tmp_path: Path) -> None:
    r = run_example(tmp_path / "none.sock", "--period", "10ms", "--target", "12ms")
    assert r.returncode == 2 and "--period" in r.stderr
    r = run_example(tmp_path / "none.sock", "--strokes", "5", "--socket", str(tmp_path / "none.sock"))
    assert r.returncode == 1 and "none.sock" in r.stderr and "Traceback" not in r.stderr


def test_the_readmes_lab_script_stopped_by_ctrl_c_leaves_the_rig_stopped(
    daemon_socket: Path, tmp_path: Path
) -> None:
    """Issue 37's bites: README's lab script, Ctrl-C'd, left the rig cycling its 100 strokes: its
    run had no `with`. The README's block itself, interrupted at its first stroke."""
    readme = (EXAMPLES.parent / "README.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "with Client() as rig" in b)
    script = tmp_path / "lab.py"
    script.write_text(block)
    env = {**os.environ, "USMSWITCH_SOCKET": str(daemon_socket)}
    proc = subprocess.Popen(
        [sys.executable, "-u", str(script)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()  # a stroke of the script's first run: it is cycling
        assert first.strip(), proc.stderr.read() if proc.stderr else ""
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "KeyboardInterrupt" in err
    cycle = int(first.split()[0])
    with Client(str(daemon_socket)) as c:
        (run,) = [r for r in c.runs(10) if r["first_cycle"] <= cycle and (r["last_cycle"] or cycle) >= cycle]
        while c.status()["state"] == "cycling":  # the stroke in progress finishes first
            time.sleep(0.02)
        (run,) = [r for r in c.runs(10) if r["run_id"] == run["run_id"]]
    assert run["end_reason"] == "stopped", run
    assert run["last_cycle"] - run["first_cycle"] + 1 < 100
