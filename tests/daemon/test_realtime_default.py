"""Real time by default where permitted (issue 22): `sched_fifo_priority = "auto"` gives the loop
SCHED_FIFO 50 when the process may use it, else SCHED_OTHER with a warning that says what it costs,
and `status` and `stats` say which. Real daemons; the unprivileged one runs as nobody with
RLIMIT_RTPRIO 0 (setpriv, prlimit)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client
from usmswitch.daemon.config import ConfigError, load_config


def test_the_default_is_auto_and_the_setting_takes_auto_0_or_a_priority() -> None:
    assert load_config(None, env={}).realtime.sched_fifo_priority == "auto"
    assert load_config(None, {"realtime.sched_fifo_priority": 0}, env={}).realtime.sched_fifo_priority == 0
    assert load_config(None, {"priority": "70"}, env={}).realtime.sched_fifo_priority == 70
    with pytest.raises(ConfigError, match=r'realtime\.sched_fifo_priority: expected "auto" or an integer'):
        load_config(None, {"realtime.sched_fifo_priority": "high"}, env={})


def run_daemon(tmp: Path, prefix: list[str]) -> tuple[dict, str, list[dict]]:
    args = daemonproc.daemon_args(tmp, "--period", "20ms")
    proc = daemonproc.spawn([*prefix, *args])
    try:
        daemonproc.wait_serving(tmp / "d.sock", proc)
        with Client(str(tmp / "d.sock")) as rig:
            rig.run(count=20, period="20ms").wait()
            status = rig.status()
        ctl = subprocess.run(
            [sys.executable, "-m", "usmswitch.client.ctl", "--socket", str(tmp / "d.sock"), "stats"],
            capture_output=True,
            text=True,
        )
    finally:
        log = daemonproc.stop(proc)
    assert proc.returncode == 0, log.decode()[-2000:]
    return status, ctl.stdout, [json.loads(x) for x in log.decode().splitlines() if x.startswith("{")]


@pytest.mark.skipif(os.geteuid() != 0, reason="the permitted case needs root or CAP_SYS_NICE")
def test_where_permitted_the_loop_runs_sched_fifo_50_by_default(tmp_path: Path) -> None:
    status, table, log = run_daemon(tmp_path, [])
    assert status["scheduling"] == "SCHED_FIFO 50"
    assert not [e for e in log if e["event"] == "loop at SCHED_OTHER"]
    assert "loop SCHED_OTHER" not in table


def test_where_not_permitted_it_says_so_at_start_in_status_and_in_stats(tmp_path: Path) -> None:
    if not shutil.which("setpriv") or not shutil.which("prlimit"):
        pytest.skip("dropping CAP_SYS_NICE and RLIMIT_RTPRIO needs setpriv and prlimit (apt: util-linux)")
    # As a container or a unit without the capability runs it: no CAP_SYS_NICE, RLIMIT_RTPRIO 0.
    drop = ["prlimit", "--rtprio=0", "setpriv", "--inh-caps=-sys_nice", "--bounding-set=-sys_nice", "--"]
    status, table, log = run_daemon(tmp_path, drop)
    assert status["scheduling"].startswith("SCHED_OTHER (SCHED_FIFO not permitted:")
    assert "no CAP_SYS_NICE" in status["scheduling"] or "without CAP_SYS_NICE" in status["scheduling"]
    assert "RLIMIT_RTPRIO 0 < 50" in status["scheduling"]
    (warning,) = [e for e in log if e["event"] == "loop at SCHED_OTHER"]
    assert warning["level"] == "warning" and "late" in warning["cost"]
    assert "loop SCHED_OTHER (SCHED_FIFO not permitted" in table and "strokes late (" in table
