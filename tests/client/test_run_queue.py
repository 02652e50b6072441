"""Issue 38: the queue of runs, through a real usmswitchd subprocess and its Unix socket.

Two scripts submitting at once both get their run, one after the other, none refused, none ended;
priorities order the queue and never end a run going; a submitter cancels its own entries, an
operator anyone's; after a FAULT the next run waits for a person's reset; a kill -9 keeps the
queue, paused until an operator resumes it, and no entry runs twice.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from usmswitch.client import Client, InvalidParams, Notification, QueuedRunNotStarted, WrongState

sys.path.insert(0, str(Path(__file__).parent))
import daemonproc
from test_runs import PERIOD, Rig

BOB = "bob@elsewhere pid 1 (bob.py)"


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    r = Rig(tmp_path)
    yield r
    if r.proc.poll() is None:
        daemonproc.stop(r.proc)


def _until(lab: Client, want: Any, timeout: float = 30.0) -> Notification:
    """The next notification `want(note)` accepts."""
    while True:
        note = lab.next_notification(timeout)
        if want(note):
            return note


def _queue_note(change: str, entry: int | None = None) -> Any:
    def want(note: Notification) -> bool:
        p = note.payload
        return (
            note.topic == "queue"
            and p["change"] == change
            and (entry is None or (p["entry"] or {}).get("entry") == entry)
        )

    return want


def _run_end(run_id: int) -> Any:
    return lambda n: (
        n.topic == "run" and n.payload["run_id"] == run_id and n.payload["end_reason"] is not None
    )


SCRIPT = textwrap.dedent(
    """
    import json, sys, time
    from pathlib import Path
    from usmswitch.client import Client

    sock, go, label = sys.argv[1:4]
    with Client(sock, timeout=30) as rig:
        print("ready", flush=True)
        while not Path(go).exists():
            time.sleep(0.005)
        run = rig.submit(count=30, period="25ms", label=label)
        strokes = [rec["cycle"] for rec in run]
        info = run.info
        print(json.dumps({"entry": run.entry["entry"], "run": info, "strokes": strokes}), flush=True)
    """
)


def test_two_scripts_submitting_at_once_get_two_runs_in_order(rig: Rig) -> None:
    go = rig.tmp / "go"
    scripts = [
        subprocess.Popen(
            [sys.executable, "-c", SCRIPT, str(rig.sock), str(go), f"script-{i}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in (1, 2)
    ]
    for p in scripts:
        assert p.stdout is not None and p.stdout.readline().strip() == "ready"
    go.touch()  # both submit now
    said = []
    for p in scripts:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        said.append(json.loads(out.strip().splitlines()[-1]))
    said.sort(key=lambda s: s["entry"])
    first, second = said
    for s in said:
        run = s["run"]
        assert run["end_reason"] == "done" and run["settings"]["queue_entry"] == s["entry"]  # none ended
        assert (
            s["strokes"] == list(range(run["first_cycle"], run["last_cycle"] + 1)) and len(s["strokes"]) == 30
        )
    assert first["run"]["last_cycle"] < second["run"]["first_cycle"]  # one after the other, in order
    assert first["run"]["run_id"] + 1 == second["run"]["run_id"]


def test_priorities_order_the_queue_and_never_end_the_run_going(rig: Rig) -> None:
    with rig.client() as lab:
        going = lab.submit(count=0, period=PERIOD, label="long")
        started = _until(lab, _queue_note("started", going.entry["entry"]))
        low = lab.submit(count=4, period=PERIOD, priority=0, label="low")
        high = lab.submit(count=4, period=PERIOD, priority=5, label="high")
        also_low = lab.submit(count=4, period=PERIOD, label="low-2")
        status = lab.status()
        assert status["run"]["run_id"] == started.payload["entry"]["run_id"]  # still going
        order = [e["entry"] for e in status["queue"]["queued"]]
        assert order == [high.entry["entry"], low.entry["entry"], also_low.entry["entry"]]
        assert status["queue"]["current"]["entry"] == going.entry["entry"]
        lab.stop_cycling()  # the run going ends: the queue goes on, in its order
        infos = [run.wait() for run in (high, low, also_low)]
        assert [i["label"] for i in infos] == ["high", "low", "low-2"]
        assert infos[0]["first_cycle"] > going.wait()["last_cycle"]
        assert (
            infos[0]["last_cycle"] < infos[1]["first_cycle"]
            and infos[1]["last_cycle"] < infos[2]["first_cycle"]
        )
        assert going.info["end_reason"] == "stopped"
        # take_over: at once, ending the run going, ahead of the queue.
        endless = lab.submit(count=0, period=PERIOD)
        _until(lab, _queue_note("started", endless.entry["entry"]))
        waiting = lab.submit(count=3, period=PERIOD)
        now = lab.submit(count=3, period=PERIOD, take_over=True)
        assert now.wait()["end_reason"] == "done"
        assert endless.wait()["end_reason"].startswith("taken over by")
        assert waiting.wait()["first_cycle"] > now.info["last_cycle"]


def test_a_submitter_cancels_its_own_an_operator_anyones(rig: Rig) -> None:
    with rig.client() as lab:
        going = lab.submit(count=0, period=PERIOD)
        _until(lab, _queue_note("started", going.entry["entry"]))
        mine = lab.submit(count=3, period=PERIOD)
        bobs = lab.call("submit", 25_000_000, 3, None, False, None, None, 0, False, BOB)
        assert mine.cancel()["state"] == "cancelled"
        with pytest.raises(QueuedRunNotStarted, match="was cancelled"):
            mine.wait()
        with pytest.raises(WrongState, match="bob@elsewhere's: its submitter cancels it, or an operator"):
            lab.queue_cancel(bobs["entry"])
        assert lab.queue_cancel(bobs["entry"], operator=True)["reason"].startswith("cancelled by")
        assert lab.status()["queue"]["queued"] == []
        with pytest.raises(WrongState, match="an operator resumes it"):
            lab.queue_resume()
        lab.stop_cycling()
        assert going.wait()["end_reason"] == "stopped"


def test_a_queued_entrys_priority_moves_it_its_submitters_or_an_operators(rig: Rig) -> None:
    """queue_priority (the panel's reorder): the entry moves at once, the change is in the records
    file when answered (a restart keeps it), another's entry only with operator, and the queue then
    runs in the new order."""
    import sqlite3

    with rig.client() as lab:
        going = lab.submit(count=0, period=PERIOD)
        _until(lab, _queue_note("started", going.entry["entry"]))
        first = lab.submit(count=3, period=PERIOD, label="first")
        second = lab.submit(count=3, period=PERIOD, label="second")
        bobs = lab.call("submit", 25_000_000, 3, None, False, "bobs", None, 0, False, BOB)["entry"]
        ids = [first.entry["entry"], second.entry["entry"]]
        moved = lab.queue_priority(ids[1], 5)
        assert (moved["entry"], moved["priority"], moved["position"]) == (ids[1], 5, 1)
        note = _until(lab, _queue_note("reordered", ids[1]))
        assert [e["entry"] for e in note.payload["queued"]] == [ids[1], ids[0], bobs]
        db = sqlite3.connect(f"file:{rig.tmp / 'state' / 'records.sqlite'}?mode=ro", uri=True)
        try:
            kept = dict(db.execute("SELECT entry, priority FROM run_queue WHERE entry = ?", (ids[1],)))
        finally:
            db.close()
        assert kept == {ids[1]: 5}
        with pytest.raises(WrongState, match="bob@elsewhere's: its submitter reorders it, or an operator"):
            lab.queue_priority(bobs, 9)
        assert lab.queue_priority(bobs, 9, operator=True)["position"] == 1
        queued = lab.status()["queue"]["queued"]
        assert [(e["entry"], e["priority"]) for e in queued] == [(bobs, 9), (ids[1], 5), (ids[0], 0)]
        lab.queue_cancel(bobs, operator=True)
        with pytest.raises(InvalidParams, match=f"entry {bobs} is not queued"):
            lab.queue_priority(bobs, 1, operator=True)
        lab.stop_cycling()
        infos = [second.wait(), first.wait()]
        assert [i["label"] for i in infos] == ["second", "first"]
        assert infos[0]["last_cycle"] < infos[1]["first_cycle"]
        assert infos[0]["settings"]["priority"] == 5


def test_a_queued_run_after_a_fault_waits_for_a_reset(rig: Rig) -> None:
    with rig.client() as lab:
        going = lab.submit(count=0, period=PERIOD)
        _until(lab, _queue_note("started", going.entry["entry"]))
        after = lab.submit(count=3, period=PERIOD)
        lab.estop()
        assert going.wait()["end_reason"].startswith("fault")
        status = lab.status()
        assert status["state"] == "fault"
        assert [e["entry"] for e in status["queue"]["queued"]] == [after.entry["entry"]]  # waits
        lab.reset_fault()  # a person's reset: now it starts
        info = after.wait()
        assert info["end_reason"] == "done" and info["first_cycle"] > going.info["last_cycle"]


def test_kill_9_keeps_the_queue_paused_and_nothing_runs_twice(tmp_path: Path) -> None:
    args = daemonproc.daemon_args(tmp_path, "--no-autostart")
    sock = tmp_path / "d.sock"
    proc = daemonproc.spawn(args)
    try:
        daemonproc.wait_serving(sock, proc)
        with Client(sock, timeout=10) as lab:
            going = lab.submit(count=0, period=PERIOD)
            _until(lab, _queue_note("started", going.entry["entry"]))
            queued = [lab.submit(count=3, period=PERIOD, label=f"after-{i}").entry["entry"] for i in range(3)]
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        proc = daemonproc.spawn(args)
        daemonproc.wait_serving(sock, proc)
        with Client(sock, timeout=10) as lab:
            queue = lab.status()["queue"]
            assert queue["paused"] and [e["entry"] for e in queue["queued"]] == queued
            assert lab.status()["state"] == "idle"  # paused: nothing started by itself
            lab.subscribe("queue", "run")
            with pytest.raises(WrongState):
                lab.queue_resume()
            assert lab.queue_resume(operator=True)["paused"] is False
            for entry in queued:
                note = _until(lab, _queue_note("started", entry))
                _until(lab, _run_end(note.payload["entry"]["run_id"]))
            runs = lab.runs(100)
        ran = [r["settings"].get("queue_entry") for r in runs if r["settings"].get("queue_entry")]
        assert ran == [going.entry["entry"], *queued]  # each once, in order; the killed one not again
        assert [r["end_reason"] for r in runs[-3:]] == ["done"] * 3
    finally:
        if proc.poll() is None:
            daemonproc.stop(proc)


def test_asyncclient_submits_and_follows_queued_runs(rig: Rig) -> None:
    import asyncio

    from usmswitch.client import AsyncClient

    async def main() -> list[dict[str, Any]]:
        async with AsyncClient(str(rig.sock)) as lab:
            first = await lab.submit(count=5, period=PERIOD, label="async-1")
            second = await lab.submit(count=5, period=PERIOD, label="async-2")
            strokes = [rec["cycle"] async for rec in second]  # the later one first: both followed
            infos = [await first.wait(), second.info]
            assert strokes == list(range(infos[1]["first_cycle"], infos[1]["last_cycle"] + 1))
            return infos

    first, second = asyncio.run(main())
    assert (first["label"], second["label"]) == ("async-1", "async-2")
    assert first["end_reason"] == second["end_reason"] == "done"
    assert first["last_cycle"] < second["first_cycle"]


def test_usmswitchctl_queues_lists_cancels_and_resumes(rig: Rig) -> None:
    with rig.client() as lab:
        going = lab.submit(count=0, period=PERIOD)
        _until(lab, _queue_note("started", going.entry["entry"]))
        queued = rig.ctl(
            "cycle", "--queue", "--count", "3", "--period", PERIOD, "--label", "cli-q", "--priority", "2"
        )
        assert queued.returncode == 0 and queued.stdout.startswith("queued as entry"), queued.stderr
        entry = int(queued.stdout.split()[3].rstrip(","))
        listed = rig.ctl("queue")
        assert listed.returncode == 0 and "going on; running: entry" in listed.stdout, listed.stderr
        assert "cli-q" in listed.stdout
        assert rig.ctl("queue", "pause").returncode == 1  # refused without --operator
        assert rig.ctl("queue", "pause", "--operator").stdout.startswith("paused")
        moved = rig.ctl("queue", "priority", str(entry), "7")
        assert moved.returncode == 0 and f"entry {entry}: priority 7, position 1" in moved.stdout, moved
        assert rig.ctl("queue", "priority", str(entry)).returncode == 2  # no priority given
        cancelled = rig.ctl("queue", "cancel", str(entry))
        assert cancelled.returncode == 0 and f"entry {entry} cancelled by" in cancelled.stdout
        assert rig.ctl("queue", "resume", "--operator").stdout.startswith("going on")
        cmd = [sys.executable, "-m", "usmswitch.client.ctl", "--socket", str(rig.sock), "--json"]
        cmd += ["cycle", "--queue", "--count", "3", "--period", PERIOD, "--wait"]
        waiting = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        _until(lab, lambda n: _queue_note("submitted")(n) and n.payload["entry"]["entry"] > entry)
        lab.stop_cycling()  # the run going ends: the queued one runs, and the CLI follows it
        assert going.wait()["end_reason"] == "stopped"
        out, err = waiting.communicate(timeout=60)
    assert waiting.returncode == 0, err
    assert json.loads(out)["end_reason"] == "done"
