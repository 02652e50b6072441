"""Runs from a lab script's side, against a real usmswitchd subprocess on the simulated rig.

The issue's own acceptance: a short script sweeping T over three targets gets, per target, exactly
its own strokes and statistics, ends by itself and never writes a nanosecond literal; a target the
rig cannot reach is refused before a single stroke, saying what to write instead.
"""

from __future__ import annotations

import asyncio
import csv
import statistics
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import (
    AsyncClient,
    Client,
    ErrorCode,
    Listener,
    Notification,
    Notifier,
    RecordsFile,
    RpcError,
    RunLost,
    TargetUnreachable,
)
from usmswitch.client.run import RunTracker

PERIOD = "25ms"


class Rig:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.sock = tmp / "d.sock"
        self.proc = daemonproc.spawn(daemonproc.daemon_args(tmp, "--no-autostart"))
        daemonproc.wait_serving(self.sock, self.proc)

    def client(self) -> Client:
        return Client(self.sock, timeout=10)

    def ctl(self, *args: str) -> subprocess.CompletedProcess[str]:
        cmd = [sys.executable, "-m", "usmswitch.client.ctl", "--socket", str(self.sock), *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60)


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    r = Rig(tmp_path_factory.mktemp("runs"))
    yield r
    daemonproc.stop(r.proc)
    assert r.proc.returncode == 0


def test_a_sweep_gets_each_targets_own_strokes_and_statistics(rig: Rig) -> None:
    results = {}
    with rig.client() as lab:
        for target in ("12ms", "13ms", "14ms"):
            run = lab.run(count=20, period=PERIOD, target=target)
            strokes = list(run)  # ends by itself when the run does
            results[target] = (run, strokes, run.stats())
    seen_runs = set()
    for target, (run, strokes, stats) in results.items():
        target_ns = {"12ms": 12_000_000, "13ms": 13_000_000, "14ms": 14_000_000}[target]
        assert run.info is not None and run.info["end_reason"] == "done"
        assert [r["cycle"] for r in strokes] == list(
            range(run.info["first_cycle"], run.info["last_cycle"] + 1)
        )
        assert len(strokes) == 20 and {r["run_id"] for r in strokes} == {run.run_id}
        assert {r["target_ns"] for r in strokes} == {target_ns}
        errors = [r["error_ns"] for r in strokes]
        assert stats["run"]["run_id"] == run.run_id and stats["all"]["strokes"] == 20
        assert stats["run"]["end_reason"] == "done"  # told of the end, stats already shows it
        assert stats["all"]["error_std_ns"] == pytest.approx(statistics.stdev(errors), abs=0.1)
        assert stats["all"]["error_max_abs_ns"] == max(abs(e) for e in errors)
        seen_runs.add(run.run_id)
    assert len(seen_runs) == 3


def test_a_target_in_the_wrong_unit_is_refused_before_a_stroke(rig: Rig) -> None:
    with rig.client() as lab:
        before = lab.status()["cycle"]
        with pytest.raises(ValueError, match=r"'12': needs a unit .*'12ms'"):
            lab.run(count=5, period=PERIOD, target="12")
        with pytest.raises(TargetUnreachable) as err:  # a subclass of RpcError per code
            lab.set_target(12)  # an int is nanoseconds: 12 ns
        assert err.value.code == ErrorCode.UNREACHABLE
        assert "bare number is nanoseconds" in err.value.message and "'12ms'" in err.value.message
        with pytest.raises(TargetUnreachable) as err:
            lab.run(count=5, period=PERIOD, target="5ms")  # below the ~10.5 ms stroke
        assert err.value.code == ErrorCode.UNREACHABLE and isinstance(err.value, RpcError)
        assert "shortest the rig reaches" in err.value.message and "allow late" in err.value.message
        assert lab.status()["cycle"] == before and lab.status()["state"] == "idle"
        assert lab.get_target()["target_on_ns"] != 5_000_000  # a refused run changed nothing
        # Said plainly, late strokes are allowed.
        run = lab.run(count=2, period=PERIOD, target="5ms", allow_late=True)
        assert all(r["flags"] & 1 for r in run)  # LATE
        lab.set_target("12ms")


def test_start_while_cycling_is_refused_and_the_run_goes_on(rig: Rig) -> None:
    with rig.client() as lab:
        run = lab.run(count=10, period=PERIOD, target="12ms")
        with pytest.raises(RpcError) as err:
            lab.start_cycling(PERIOD, 5)
        assert err.value.code == ErrorCode.STATE
        assert len(list(run)) == 10 and run.info["end_reason"] == "done"


def test_past_runs_history_and_statistics_come_from_the_records(rig: Rig) -> None:
    with rig.client() as lab:
        first = lab.run(count=8, period=PERIOD, target="12ms")
        first_strokes = list(first)
        live = first.stats()
        lab.run(count=4, period=PERIOD, target="13ms").wait()
        # The first run is now a past one: read from the records file, it is the same run.
        past = lab.stats(first.run_id)
        assert past["run"]["run_id"] == first.run_id and past["all"]["strokes"] == 8
        for key in ("error_mean_ns", "error_std_ns", "error_max_abs_ns", "late", "stalls"):
            assert past["all"][key] == pytest.approx(live["all"][key], abs=0.1), key
        assert past["on"]["target_ns"] == 12_000_000
        assert [r["cycle"] for r in lab.history(100, run=first.run_id)] == [r["cycle"] for r in first_strokes]
        c0 = first_strokes[0]["cycle"]
        ranged = lab.stats(cycles=(c0, c0 + 3))
        assert (ranged["first_cycle"], ranged["last_cycle"], ranged["all"]["strokes"]) == (c0, c0 + 3, 4)
        runs = lab.runs()
        assert runs[-2]["run_id"] == first.run_id and runs[-2]["last_cycle"] == first_strokes[-1]["cycle"]
        assert runs[-2]["settings"]["target_on_ns"] == 12_000_000
        with pytest.raises(RpcError) as err:
            lab.stats(9999)
        assert err.value.code == ErrorCode.INVALID_PARAMS and "no run 9999" in err.value.message


def test_a_notifier_calls_back_for_every_stroke(rig: Rig) -> None:
    got: list[int] = []
    errors: list[Exception] = []
    done = threading.Event()

    class Errors(Listener):
        def on_error(self, exc: Exception) -> None:
            errors.append(exc)

    def on_stroke(note: Notification) -> None:
        got.append(note.payload["cycle"])
        if len(got) == 6:
            done.set()

    with rig.client() as lab, Notifier(lab, [on_stroke, Errors()], topics=["stroke"]):
        lab.start_cycling(PERIOD, 6, target="12ms")
        assert done.wait(10)
    assert got == list(range(got[0], got[0] + 6)) and not errors


def test_the_asyncio_client_runs_and_reads_statistics(rig: Rig) -> None:
    async def main() -> tuple[list[int], dict, str]:
        async with AsyncClient(rig.sock, timeout=10) as lab:
            status, run = await asyncio.gather(lab.status(), lab.run(count=6, period=PERIOD, target="12ms"))
            cycles = [rec["cycle"] async for rec in run]
            return cycles, await run.stats(), status["state"]

    cycles, stats, state = asyncio.run(main())
    assert len(cycles) == 6 and stats["all"]["strokes"] == 6 and state == "idle"


def test_usmswitchctl_on_runs(rig: Rig, tmp_path: Path) -> None:
    r = rig.ctl("cycle", "--count", "5", "--period", PERIOD, "--target", "12ms", "--wait")
    assert r.returncode == 0, r.stderr
    assert "ended: done, 5 strokes" in r.stdout
    run_id = int(r.stdout.split()[1].rstrip(":"))
    r = rig.ctl("stats", "--run", str(run_id))
    assert r.returncode == 0 and f"run {run_id} (cycling, ended: done)" in r.stdout, r.stdout
    r = rig.ctl("runs")
    assert r.returncode == 0 and any(line.split()[0] == str(run_id) for line in r.stdout.splitlines()[1:])
    r = rig.ctl("history", "--run", str(run_id), "--json")
    assert r.returncode == 0 and r.stdout.count('"cycle"') == 5
    out = tmp_path / "run.csv"
    r = rig.ctl("export", "--state-dir", str(rig.tmp / "state"), "--run", str(run_id), "--csv", str(out))
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 5 and {row["run_id"] for row in rows} == {str(run_id)}
    r = rig.ctl("export", "--state-dir", str(rig.tmp / "state"), "--run", "9999", "--csv", str(out))
    assert r.returncode == 2 and "no run 9999" in r.stderr
    r = rig.ctl("cycle", "--count", "5", "--target", "5ms")
    assert r.returncode == 1 and "shortest the rig reaches" in r.stderr
    with RecordsFile(rig.tmp / "state") as f:
        assert f.run(run_id)["end_reason"] == "done"
        assert len(list(f.records(run=run_id))) == 5


def _stroke(run_id: int, cycle: int) -> Notification:
    return Notification("stroke", {"run_id": run_id, "cycle": cycle})


def test_the_tracker_fills_dropped_strokes_from_history_and_says_when_it_cannot() -> None:
    t = RunTracker({"run_id": 3, "first_cycle": 10})  # type: ignore[typeddict-item]
    rec, missing = t.accept(_stroke(3, 10))
    assert (rec["cycle"], missing) == (10, 0)
    t.took(rec)
    assert t.accept(_stroke(2, 11)) == (None, 0)  # another run's stroke
    rec, missing = t.accept(_stroke(3, 13))  # 11 and 12 were dropped by the server
    assert missing == 2
    history = [{"run_id": 3, "cycle": c} for c in range(9, 14)]
    assert [r["cycle"] for r in t.fill(history, 13)] == [11, 12]  # type: ignore[arg-type]
    for r in t.fill(history, 13):  # type: ignore[arg-type]
        t.took(r)
    t.took(rec)
    end = {"run_id": 3, "end_reason": "done", "last_cycle": 15}
    assert t.accept(Notification("run", end)) == (None, 2) and t.ended  # 14 and 15 still to read
    with pytest.raises(RunLost, match=r"strokes 14\.\.15"):
        t.fill([{"run_id": 3, "cycle": 15}], 16)  # type: ignore[list-item]
