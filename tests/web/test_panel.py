"""The browser panel over plain HTTP (no browser), against a real daemon on the simulated rig: the
token file, refusals without it, bad controls, the live feed, a run's CSV export."""

from __future__ import annotations

import asyncio
import csv
import io
import json
import os
import stat
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from daemonproc import MS, daemon_args, spawn, stop, wait_serving

from usmswitch.client import Client
from usmswitch.protocol.record_csv import CSV_HEADER
from usmswitch.protocol.sockets import web_token_path
from usmswitch.protocol.wire import Limits, estop_socket_path
from usmswitch.web.panel import TOKEN_HEADER


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """One daemon for the module: cycling at 15 ms, the panel on a free loopback port."""
    tmp = tmp_path_factory.mktemp("panel")
    sock = tmp / "run" / "d.sock"
    proc = spawn(daemon_args(tmp, "--web", "127.0.0.1:0", "--period", "15ms", socket=sock))
    try:
        wait_serving(sock, proc)
        with Client(str(sock)) as c:
            url = c.status()["web_url"]
        yield {"sock": sock, "url": url, "token": web_token_path(sock).read_text().strip(), "proc": proc}
    finally:
        stop(proc)


def request(
    url: str, method: str = "GET", body: bytes | None = None, token: str | None = None
) -> tuple[int, bytes, dict[str, str]]:
    """(status, body, headers) of one request; an HTTP error is an answer, not an exception."""
    req = urllib.request.Request(url, data=body, method=method)
    if token is not None:
        req.add_header(TOKEN_HEADER, token)
    if body is not None:
        req.add_header("Content-Type", "application/json")
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, resp.read(), dict(resp.headers)
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read(), dict(exc.headers)


def control(rig: dict[str, Any], name: str, body: object = None, token: str | None = "") -> tuple[int, Any]:
    raw = json.dumps({} if body is None else body).encode()
    status, data, _ = request(
        f"{rig['url']}api/control/{name}", "POST", raw, rig["token"] if token == "" else token
    )
    return status, json.loads(data)


def test_the_token_file_is_for_the_socket_group_only(rig: dict[str, Any]) -> None:
    path = web_token_path(rig["sock"])
    st = os.stat(path)
    assert stat.S_IMODE(st.st_mode) == 0o640
    assert st.st_gid == os.stat(rig["sock"]).st_gid
    assert len(rig["token"]) >= 32


def test_the_page_and_its_assets_are_served_from_the_package(rig: dict[str, Any]) -> None:
    status, page, _ = request(rig["url"])
    assert status == 200 and b"/static/uPlot.iife.min.js" in page and b'id="estop"' in page
    for name, kind in (("uPlot.iife.min.js", "text/javascript"), ("panel.js", "text/javascript"),
                       ("uPlot.min.css", "text/css"), ("uPlot-LICENSE.txt", "text/plain")):  # fmt: skip
        status, body, headers = request(f"{rig['url']}static/{name}")
        assert status == 200 and body and headers["Content-Type"].startswith(kind), name
    assert request(f"{rig['url']}static/..%2Fpanel.py")[0] == 404
    assert request(f"{rig['url']}static/nothing.js")[0] == 404


def test_without_the_token_controls_are_refused_with_a_message(rig: dict[str, Any]) -> None:
    for token in (None, "not-the-token"):
        for name in ("estop", "stop", "target", "nonsense"):
            status, data = control(rig, name, {"target_ns": 12 * MS}, token=token)
            assert status == 403, (name, data)
            assert data["error"].startswith("read-only:") and "usmswitchctl web-url" in data["error"]
            assert str(web_token_path(rig["sock"])) in data["error"]
    with Client(str(rig["sock"])) as c:
        assert c.status()["state"] != "fault"
    status, body, _ = request(f"{rig['url']}api/session")
    assert status == 200 and json.loads(body)["control"] is False
    status, body, _ = request(f"{rig['url']}api/session", token=rig["token"])
    assert json.loads(body) == {"control": True, "message": None}


def test_bad_controls_get_a_clear_400_and_change_nothing(rig: dict[str, Any]) -> None:
    with Client(str(rig["sock"])) as c:
        before = c.get_target()
    url = f"{rig['url']}api/control/target"
    status, data, _ = request(url, "POST", b"{not json", rig["token"])
    assert status == 400 and "not JSON" in json.loads(data)["error"]
    status, data = control(rig, "launch", {})
    assert status == 400 and "unknown control 'launch'" in data["error"] and "estop" in data["error"]
    status, data = control(rig, "target", {"target_ns": 99_000 * MS})
    assert status == 400 and "target_ns must be from 1 ns to 10.000 s, got 99.000 s" in data["error"]
    # Issue 37's bites: the panel's start with a 12 s target said `... 12000000000`.
    status, data = control(rig, "start", {"count": 10, "period_ns": 20 * MS, "target_ns": 12_000 * MS})
    assert status == 400 and data["error"].endswith("target_ns must be from 1 ns to 10.000 s, got 12.000 s")
    assert "12000000000" not in data["error"]
    status, data = control(rig, "target", {"target_ns": "12ms"})
    assert status == 400 and "target_ns" in data["error"]
    status, data = control(rig, "target", {"target": 12 * MS})
    assert status == 400 and "unknown field 'target'" in data["error"]
    status, data = control(rig, "target", [12 * MS])
    assert status == 400 and "JSON object" in data["error"]
    status, data = control(rig, "mode", {"mode": "sideways"})
    assert status == 400 and "mode" in data["error"]
    status, data, _ = request(url, "POST", b"{" + b" " * 10_000 + b"}", rig["token"])
    assert status == 413 and "at most" in json.loads(data)["error"]
    with Client(str(rig["sock"])) as c:
        assert c.get_target() == before


def test_another_sites_page_may_not_read_the_feed_or_act(rig: dict[str, Any]) -> None:
    async def feed(origin: str) -> int:
        async with aiohttp.ClientSession() as http:
            try:
                async with http.ws_connect(f"{rig['url']}api/live", headers={"Origin": origin}):
                    return 101
            except aiohttp.WSServerHandshakeError as exc:
                return exc.status

    assert asyncio.run(feed("http://evil.example")) == 403
    assert asyncio.run(feed(rig["url"].rstrip("/"))) == 101
    req = urllib.request.Request(f"{rig['url']}api/control/estop", data=b"{}", method="POST")
    req.add_header(TOKEN_HEADER, rig["token"])
    req.add_header("Origin", "http://evil.example")
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(req, timeout=10)
    assert info.value.code == 403 and "another site" in json.loads(info.value.read())["error"]
    with Client(str(rig["sock"])) as c:
        assert c.status()["state"] != "fault"


def test_the_live_feed_opens_with_history_and_keeps_up(rig: dict[str, Any]) -> None:
    async def feed() -> tuple[dict[str, Any], int]:
        async with aiohttp.ClientSession() as http, http.ws_connect(f"{rig['url']}api/live") as ws:
            hello = json.loads((await ws.receive(timeout=10)).data)
            got, end = 0, time.monotonic() + 1.5
            while time.monotonic() < end:
                msg = json.loads((await ws.receive(timeout=5)).data)
                got += len(msg["strokes"])
            return hello, got

    with Client(str(rig["sock"])) as c:  # strokes made before the panel opens: its history
        while c.status()["cycle"] < 40:
            time.sleep(0.05)
    hello, got = asyncio.run(feed())
    assert hello["type"] == "hello" and hello["status"]["state"] == "cycling"
    assert hello["status"]["driver"] == "sim" and hello["status"]["rig"]
    assert len(hello["strokes"]) > 20 and hello["stats"]["on"]["count"] > 0
    cycles = [row[0] for row in hello["strokes"]]
    assert cycles == sorted(cycles)
    assert got >= 60  # 1.5 s at 15 ms a stroke: ~100, in ~15 messages


def test_feeds_opened_together_miss_no_stroke_after_their_hello(rig: dict[str, Any]) -> None:
    """A hello is encoded once for the feeds opened within 100 ms (a burst encoded ~1,000 strokes
    once a feed): each feed's cursor is its hello's, so the ticks after it carry every later
    stroke, none twice, however old the shared hello is."""

    async def feed(http: aiohttp.ClientSession) -> list[int]:
        async with http.ws_connect(f"{rig['url']}api/live") as ws:
            cycles = [json.loads((await ws.receive(timeout=10)).data)["strokes"][-1][0]]
            while len(cycles) < 40:
                msg = json.loads((await ws.receive(timeout=10)).data)
                assert not msg["gap"]
                cycles += [row[0] for row in msg["strokes"]]
            return cycles

    async def feeds() -> list[list[int]]:
        async with aiohttp.ClientSession() as http:
            return list(await asyncio.gather(*(feed(http) for _ in range(4))))

    with Client(str(rig["sock"])) as c:
        while c.status()["cycle"] < 40:
            time.sleep(0.05)
    for cycles in asyncio.run(feeds()):
        assert cycles == list(range(cycles[0], cycles[0] + len(cycles))), "a stroke missed or sent twice"


def test_a_run_exports_as_csv_with_every_stroke(rig: dict[str, Any]) -> None:
    status, data = control(rig, "start", {"period_ns": 15 * MS, "count": 30, "take_over": True})
    assert status == 200, data
    run_id = data["result"]["run_id"]
    with Client(str(rig["sock"])) as c:
        end = time.monotonic() + 10
        while c.status()["state"] == "cycling" and time.monotonic() < end:
            time.sleep(0.05)
        records = c.history(100, run=run_id)
    status, body, headers = request(f"{rig['url']}api/runs/{run_id}.csv")
    assert status == 200 and headers["Content-Type"].startswith("text/csv")
    assert f'filename="run-{run_id}.csv"' in headers["Content-Disposition"]
    rows = list(csv.reader(io.StringIO(body.decode())))
    assert tuple(rows[0]) == CSV_HEADER and len(rows) == 31 == len(records) + 1
    col = {name: i for i, name in enumerate(rows[0])}
    for row, rec in zip(rows[1:], records, strict=True):
        assert int(row[col["cycle"]]) == rec["cycle"] and int(row[col["run_id"]]) == run_id
        assert int(row[col["error_ns"]]) == rec["error_ns"]
    status, body, _ = request(f"{rig['url']}api/runs")
    listed = {r["run_id"]: r for r in json.loads(body)["runs"]}
    assert listed[run_id]["end_reason"] == "done" and listed[run_id]["stats"]["on"]["count"] == 15
    status, body, _ = request(f"{rig['url']}api/runs/999999.csv")
    assert status == 404 and "no run 999999" in json.loads(body)["error"]
    assert request(f"{rig['url']}api/runs/x1.csv")[0] in (400, 404)


def test_a_labelled_runs_csv_says_its_label_and_notes_above_the_header(rig: dict[str, Any]) -> None:
    """Issue 38: the panel's export is the same CSV as the others, its run's label and notes in a
    comment line above the header."""
    with Client(str(rig["sock"])) as c:
        run = c.run(count=4, period="15ms", take_over=True, label="panel-csv", notes='a "quoted"\nnote')
        run.wait()
    status, body, _ = request(f"{rig['url']}api/runs/{run.run_id}.csv")
    lines = body.decode().split("\n")
    assert status == 200
    assert lines[0] == f'# run {run.run_id}: {{"label": "panel-csv", "notes": "a \\"quoted\\"\\nnote"}}'
    assert tuple(next(csv.reader([lines[1]]))) == CSV_HEADER and len(lines) == 2 + 4 + 1


def test_usmswitchctl_web_url_prints_the_url_with_the_token(rig: dict[str, Any], tmp_path: Path) -> None:
    from usmswitch.client.ctl import main

    out = tmp_path / "out"
    import contextlib

    with out.open("w") as fh, contextlib.redirect_stdout(fh):
        assert main(["--socket", str(rig["sock"]), "web-url"]) == 0
    assert out.read_text().strip() == f"{rig['url']}?token={rig['token']}"


def test_a_page_presses_the_estop_on_its_live_feed(rig: dict[str, Any]) -> None:
    """Issue 35: the page's estop goes on the feed it holds open (no connection to open, no request
    head to parse, no wait at a full door). Only a feed opened with the token may press it; any
    other message is answered with what the feed takes, and the feed goes on."""

    async def send(message: str, token: str | None) -> dict[str, Any]:
        headers = {TOKEN_HEADER: token} if token else {}
        url = f"{rig['url']}api/live"
        async with aiohttp.ClientSession() as http, http.ws_connect(url, headers=headers) as ws:
            assert json.loads((await ws.receive(timeout=10)).data)["type"] == "hello"
            await ws.send_str(message)
            async with asyncio.timeout(10):  # the feed's own ticks come before and after the answer
                while "strokes" in (answer := json.loads((await ws.receive()).data)):
                    pass
            return answer

    for bad in ("estop", '{"estop": [1]}', '{"estop": 1, "x": 2}', "[" * 2000, '{"stop": 1}'):
        assert "takes only" in asyncio.run(send(bad, rig["token"]))["error"], bad
    readonly = asyncio.run(send('{"estop": 7}', None))["estop"]
    assert readonly["id"] == 7 and "read-only" in readonly["error"]
    with Client(str(rig["sock"])) as c:
        if c.status()["state"] != "cycling":  # a test before ended its run
            c.start_cycling(15 * MS, take_over=True)
        pressed = asyncio.run(send('{"estop": "b1"}', rig["token"]))["estop"]
        assert pressed["id"] == "b1" and "error" not in pressed
        assert pressed["result"]["state"] == "fault"
        # From the HTTP doors' thread by the estop socket, behind nothing on the event loop.
        assert c.status()["fault"] == "estop (panel, live feed, estop socket)"
        c.reset_fault()
        c.start_cycling(15 * MS, take_over=True)
        # The estop socket not there: the same estop goes by the event loop and the urgent channel.
        # The link's kept connection is shed first (a newcomer in each of the socket's slots), so
        # that it has only the path to try.
        estop_sock = estop_socket_path(rig["sock"])
        aside = estop_sock.with_name("aside.sock")
        estop_sock.rename(aside)
        holders = [Client(str(aside), timeout=5, retry=False) for _ in range(Limits().max_urgent_connections)]
        try:
            for holder in holders:
                holder.call("ping")  # answered: newer than the link's connection
            pressed = asyncio.run(send('{"estop": "b2"}', rig["token"]))["estop"]
        finally:
            for holder in holders:
                holder.close()
            aside.rename(estop_sock)
        assert pressed["id"] == "b2" and pressed["result"]["state"] == "fault"
        assert c.status()["fault"] == "estop (panel, live feed)"
        c.reset_fault()
        c.start_cycling(15 * MS, take_over=True)
