"""The simulated rig remembers its friction and warmth across daemon restarts, and each start draws
a new seed (logged and recorded) unless one is given."""

from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client
from usmswitch.drivers import Direction
from usmswitch.sim.model import UsmSwitchModel


def test_a_model_takes_up_where_another_left_off() -> None:
    a = UsmSwitchModel(seed=4)
    now = 0
    for i in range(40):  # warm it and move its friction
        a.next_stroke(Direction(i % 2), now)
        now += 25_000_000
    state = json.loads(json.dumps(a.state(now)))  # through JSON, as the daemon keeps it
    b = UsmSwitchModel(seed=99)
    b.restore(state, t_ns=0, idle_ns=0)
    assert b._friction == a._friction and b.strokes == a.strokes
    assert b.temperature_c(0) == pytest.approx(a.temperature_c(now))
    tau = a.params.thermal_tau_ns
    c = UsmSwitchModel(seed=99)
    c.restore(state, t_ns=0, idle_ns=tau)  # away one time constant: cooled by 1/e
    assert c.temperature_c(0) - c.params.ambient_c == pytest.approx(state["theta_c"] * math.exp(-1))
    with pytest.raises(ValueError, match="friction"):
        UsmSwitchModel().restore({**state, "friction": [0.1]}, t_ns=0)
    with pytest.raises(ValueError, match="format"):
        UsmSwitchModel().restore({**state, "format": 9}, t_ns=0)


def _start_events(db: Path) -> list[dict]:
    con = sqlite3.connect(db)
    rows = [json.loads(d) for (d,) in con.execute("SELECT data FROM events WHERE kind = 'start' ORDER BY id")]
    con.close()
    return rows


def test_a_restarted_daemon_faces_the_rig_it_left(tmp_path: Path) -> None:
    args = daemonproc.daemon_args(tmp_path, "--sim-clock", "virtual", "--no-autostart", "--log-level", "info")
    logs = []
    for _ in range(2):
        proc = daemonproc.spawn(args)
        try:
            daemonproc.wait_serving(tmp_path / "d.sock", proc)
            with Client(tmp_path / "d.sock", timeout=30) as c:
                c.run(count=60, period="25ms", target="12ms").wait()
        finally:
            logs.append(daemonproc.stop(proc).decode())
        assert proc.returncode == 0
        saved = json.loads((tmp_path / "state" / "rig.json").read_text())
        assert oct((tmp_path / "state" / "rig.json").stat().st_mode & 0o777) == "0o600"
    assert saved["rig"]["strokes"] == [60, 60]  # 120 strokes over two runs of the daemon, not 60
    assert "rig state not restored" not in logs[1] and "rig state restored" in logs[1]
    starts = _start_events(tmp_path / "state" / "records.sqlite")
    assert len(starts) == 2 and starts[0]["seed"] != starts[1]["seed"]  # a new seed each start, recorded
    assert f'"seed": {starts[1]["seed"]}' in logs[1]


def test_a_broken_rig_file_starts_a_fresh_rig_and_says_so(tmp_path: Path) -> None:
    (tmp_path / "state").mkdir(mode=0o700)
    (tmp_path / "state" / "rig.json").write_text("{not json")
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, "--sim-clock", "virtual", "--no-autostart"))
    try:
        daemonproc.wait_serving(tmp_path / "d.sock", proc)
    finally:
        err = daemonproc.stop(proc).decode()
    assert proc.returncode == 0 and "rig state not restored" in err
    assert json.loads((tmp_path / "state" / "rig.json").read_text())["rig"]["strokes"] == [0, 0]
