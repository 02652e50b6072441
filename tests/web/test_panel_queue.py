"""The panel's queue of runs and a run's notes over plain HTTP (issue 38), against a real daemon on
the simulated rig (test_panel.py's): a run queued from the panel waits for the run going and never
ends it; reorder and cancel, another's entry only as an operator; the live feed carries the queue;
notes edited from the panel are what `usmswitchctl runs` shows; after a restart the panel resumes
the paused queue; without the token every one of these is refused (403) and changes nothing."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp

sys.path.insert(0, str(Path(__file__).parent))
import test_panel
from daemonproc import MS, daemon_args, spawn, stop, wait_serving
from test_panel import control

from usmswitch.client import Client
from usmswitch.protocol.sockets import web_token_path

#: test_panel.py's fixture: a daemon of this module's own, cycling at 15 ms, its panel on loopback.
rig = test_panel.rig
BOB = "bob@elsewhere pid 1 (bob.py)"
QUEUE_CONTROLS = ("submit", "queue_cancel", "queue_priority", "queue_pause", "queue_resume", "notes")


def until(what: str, check: Callable[[], Any], timeout_s: float = 60.0) -> Any:
    """Wait on a condition (the machine may be busy: a generous bound, never a timed claim)."""
    end = time.monotonic() + timeout_s
    while not (got := check()):
        assert time.monotonic() < end, f"not within {timeout_s:g} s: {what}"
        time.sleep(0.05)
    return got


def queued_runs(c: Client, *entries: int) -> list[dict[str, Any]]:
    """The runs the queue started for `entries`, in the order they ran."""
    runs = [r for r in c.runs(100) if (r["settings"] or {}).get("queue_entry") in entries]
    return sorted(runs, key=lambda r: r["run_id"])


async def feed_until(
    url: str, want: Callable[[dict[str, Any]], bool], act: Callable[[], Any]
) -> dict[str, Any]:
    """Open the live feed, check its hello, do `act`, then the first queue the feed sends that
    `want` accepts."""
    async with aiohttp.ClientSession() as http, http.ws_connect(f"{url}api/live") as ws:
        hello = json.loads((await ws.receive(timeout=10)).data)
        assert hello["type"] == "hello" and "queue" in hello
        await asyncio.get_running_loop().run_in_executor(None, act)
        while True:
            msg = json.loads((await ws.receive(timeout=30)).data)
            if msg.get("queue") is not None and want(msg["queue"]):
                return msg["queue"]


def test_a_run_queued_from_the_panel_waits_for_the_run_going_and_never_ends_it(rig: dict[str, Any]) -> None:
    with Client(str(rig["sock"])) as c:
        theirs = c.start_cycling("15ms", 0, take_over=True, owner="lab script")["run_id"]
        body = {"period_ns": 15 * MS, "count": 5, "label": "panel-q", "notes": "from the page", "priority": 0}
        status, data = control(rig, "submit", body)
        assert status == 200, data
        first = data["result"]
        assert first["position"] == 1 and first["owner"] == "panel" and first["label"] == "panel-q"
        status, data = control(rig, "submit", {**body, "label": "panel-q2", "notes": None})
        second = data["result"]
        assert status == 200 and second["position"] == 2, data
        bobs = c.call("submit", 15 * MS, 3, None, False, "bobs", None, 0, False, BOB)["entry"]
        going = c.status()
        assert going["run"]["run_id"] == theirs and going["state"] == "cycling"  # not ended

        # Reordered from the panel: the second goes first.
        status, data = control(rig, "queue_priority", {"entry": second["entry"], "priority": 5})
        assert status == 200 and data["result"]["position"] == 1, data
        # Another's entry: refused naming whose, then done as an operator.
        status, data = control(rig, "queue_cancel", {"entry": bobs})
        assert status == 409 and "bob@elsewhere's: its submitter cancels it" in data["error"], data
        status, data = control(rig, "queue_priority", {"entry": bobs, "priority": 9})
        assert status == 409 and "bob@elsewhere's" in data["error"], data
        status, data = control(rig, "queue_cancel", {"entry": bobs, "operator": True})
        assert status == 200 and data["result"]["state"] == "cancelled", data
        status, data = control(rig, "queue_priority", {"entry": first["entry"], "priority": "high"})
        assert status == 400 and "priority must be an integer" in data["error"], data

        # The live feed carries the queue: the run going, what waits in order, paused or not.
        def paused(q: dict[str, Any]) -> bool:
            return q["paused"] is True

        shown = asyncio.run(feed_until(rig["url"], paused, lambda: control(rig, "queue_pause")))
        assert shown["run"]["run_id"] == theirs and shown["run"]["end_reason"] is None
        assert [e["entry"] for e in shown["queued"]] == [second["entry"], first["entry"]]
        assert [e["label"] for e in shown["queued"]] == ["panel-q2", "panel-q"]
        shown = asyncio.run(
            feed_until(rig["url"], lambda q: q["paused"] is False, lambda: control(rig, "queue_resume"))
        )
        assert shown["run"]["run_id"] == theirs  # resumed: the run going still goes

        c.stop_cycling()  # the run going ends by its owner's hand: now the queue goes on
        ids = (first["entry"], second["entry"])
        until(
            "both queued runs done", lambda: [r["end_reason"] for r in queued_runs(c, *ids)] == ["done"] * 2
        )
        ran = queued_runs(c, *ids)
        (ended,) = [r for r in c.runs(10) if r["run_id"] == theirs]
    assert ended["end_reason"] == "stopped"  # never "taken over"
    assert [r["settings"]["queue_entry"] for r in ran] == [second["entry"], first["entry"]]
    assert all(r["settings"]["owner"] == "panel" for r in ran)
    assert ran[1]["label"] == "panel-q" and ran[1]["notes"] == "from the page"
    assert ran[0]["first_cycle"] > ended["last_cycle"] and ran[0]["last_cycle"] < ran[1]["first_cycle"]


def test_without_the_token_the_queue_and_notes_controls_are_refused(rig: dict[str, Any]) -> None:
    with Client(str(rig["sock"])) as c:
        c.start_cycling("15ms", 0, take_over=True, owner="lab script")
        entry = c.call("submit", 15 * MS, 3, None, False, "waits", None, 0, False, BOB)["entry"]
        run = c.runs(1)[-1]
        bodies = {
            "submit": {"period_ns": 15 * MS, "count": 3},
            "queue_cancel": {"entry": entry, "operator": True},
            "queue_priority": {"entry": entry, "priority": 7, "operator": True},
            "notes": {"run": run["run_id"], "notes": "not from here", "operator": True},
        }
        for token in (None, "not-the-token"):
            for name in QUEUE_CONTROLS:
                status, data = control(rig, name, bodies.get(name, {}), token=token)
                assert status == 403 and data["error"].startswith("read-only:"), (name, data)
        queue = c.status()["queue"]
        assert not queue["paused"] and [(e["entry"], e["priority"]) for e in queue["queued"]] == [(entry, 0)]
        assert c.runs(1)[-1]["notes"] == run["notes"]
        # The same bodies with the token are controls the panel has: the 403 was the token's.
        status, data = control(rig, "queue_priority", bodies["queue_priority"])
        assert status == 200 and data["result"]["priority"] == 7, data
        status, data = control(rig, "queue_cancel", bodies["queue_cancel"])
        assert status == 200 and data["result"]["state"] == "cancelled", data


def test_notes_edited_from_the_panel_show_in_usmswitchctl_runs(rig: dict[str, Any]) -> None:
    status, data = control(
        rig, "start", {"period_ns": 15 * MS, "count": 4, "take_over": True, "label": "p-run"}
    )
    assert status == 200, data
    mine = data["result"]["run_id"]
    with Client(str(rig["sock"])) as c:
        until("the page's run done", lambda: c.runs(1)[-1]["end_reason"] == "done")
        theirs = c.start_cycling("15ms", 3, take_over=True, owner="lab script", label="theirs")["run_id"]
        until("their run done", lambda: c.runs(1)[-1]["end_reason"] == "done")
    status, data = control(rig, "notes", {"run": mine, "notes": "seen from the page\nsecond line"})
    assert status == 200 and data["result"]["notes"] == "seen from the page\nsecond line", data
    assert data["result"]["label"] == "p-run"  # absent: unchanged
    status, data = control(rig, "notes", {"run": theirs, "notes": "a look"})
    assert status == 409 and f"run {theirs} is lab script's: its owner edits" in data["error"], data
    status, data = control(rig, "notes", {"run": theirs, "notes": "a look", "label": "", "operator": True})
    assert status == 200 and data["result"]["label"] is None, data  # "" clears it
    cmd = [sys.executable, "-m", "usmswitch.client.ctl", "--socket", str(rig["sock"]), "runs", "-n", "5"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=True).stdout
    assert f"run {mine} notes: seen from the page / second line" in out, out
    assert f"run {theirs} notes: a look" in out, out


def test_after_a_restart_the_panel_resumes_the_paused_queue(tmp_path: Path) -> None:
    sock = tmp_path / "run" / "d.sock"
    args = daemon_args(tmp_path, "--web", "127.0.0.1:0", "--no-autostart", socket=sock)
    proc = spawn(args)
    try:
        wait_serving(sock, proc)
        with Client(str(sock)) as c:
            c.start_cycling("15ms", 0, owner="lab script")
            entries = [c.submit_entry("15ms", 3, label=f"after-{i}")["entry"] for i in range(2)]
        stop(proc)
        proc = spawn(args)
        wait_serving(sock, proc)
        with Client(str(sock)) as c:
            url = c.status()["web_url"]
        r = {"url": url, "token": web_token_path(sock).read_text().strip()}

        async def hello() -> dict[str, Any]:
            async with aiohttp.ClientSession() as http, http.ws_connect(f"{url}api/live") as ws:
                return dict(json.loads((await ws.receive(timeout=10)).data)["queue"])

        shown = asyncio.run(hello())
        assert shown["paused"] is True and [e["entry"] for e in shown["queued"]] == entries
        assert shown["run"] is None
        assert control(r, "queue_resume", token=None)[0] == 403
        status, data = control(r, "queue_resume")
        assert status == 200 and data["result"]["paused"] is False, data
        with Client(str(sock)) as c:
            until("both ran", lambda: [x["end_reason"] for x in queued_runs(c, *entries)] == ["done"] * 2)
            assert [x["label"] for x in queued_runs(c, *entries)] == ["after-0", "after-1"]
    finally:
        if proc.poll() is None:
            stop(proc)
