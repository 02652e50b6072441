"""Issue 35, items 4-6, 9, 10, 11 and 14 over plain HTTP against a real daemon (subprocess, sim):
the panel's and /metrics' doors keep their budgets, refuse a Host they were not configured for, check
the Origin's scheme, trade the URL's token for a cookie, and answer bad input with a short 400."""

from __future__ import annotations

import asyncio
import json
import resource
import socket
from collections.abc import Iterator
from typing import Any
from urllib.parse import urlsplit

import aiohttp
import pytest
from daemonproc import daemon_args, spawn, stop, wait_serving

from usmswitch.client import Client
from usmswitch.daemon.config import WebConfig
from usmswitch.protocol.sockets import web_token_path


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """One daemon: cycling, the panel and /metrics on free loopback ports, one extra allowed host."""
    tmp = tmp_path_factory.mktemp("doors")
    sock = tmp / "run" / "d.sock"
    cfg = tmp / "d.toml"
    # allowed_hosts only where this version has it: the same tests run on 7f3fa01, and fail there.
    hosts = 'allowed_hosts = ["rig-a.lab.example"]\n' if hasattr(WebConfig, "allowed_hosts") else ""
    cfg.write_text(f'[web]\n{hosts}[metrics]\nlisten = "127.0.0.1:0"\n')
    args = daemon_args(tmp, "--web", "127.0.0.1:0", "--period", "15ms", "--config", str(cfg), socket=sock)
    # The descriptors a unit without LimitNOFILE gives (1024): the server must live within them.
    proc = spawn(args, preexec_fn=_nofile_1024)
    try:
        wait_serving(sock, proc)
        with Client(str(sock)) as c:
            st = c.status()
        web = urlsplit(st["web_url"])
        metrics = urlsplit(st["metrics_url"])
        yield {
            "sock": sock,
            "url": st["web_url"],
            "port": web.port,
            "metrics_port": metrics.port,
            "token": web_token_path(sock).read_text().strip(),
            "proc": proc,
        }
    finally:
        stop(proc)


def _nofile_1024() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (1024, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))


def raw_http(port: int, data: bytes, timeout_s: float = 20.0) -> bytes:
    """Send bytes as they are (any Host, any header) and read the answer until the server closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as s:
        s.sendall(data)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
            if b"\r\n\r\n" in out and b"Connection: close" not in out and b"connection: close" not in out:
                head, _, body = out.partition(b"\r\n\r\n")
                length = [line for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:")]
                if length and len(body) >= int(length[0].split(b":")[1]):
                    break
        return out


def get(port: int, path: str, host: str, *headers: str) -> bytes:
    extra = "".join(f"{h}\r\n" for h in headers)
    return raw_http(port, f"GET {path} HTTP/1.1\r\nHost: {host}\r\n{extra}Connection: close\r\n\r\n".encode())


def status_of(answer: bytes) -> int:
    return int(answer.split(b" ", 2)[1])


def test_a_host_it_was_not_configured_for_is_refused(rig: dict[str, Any]) -> None:
    """Item 10: `Host: evil.example:PORT` with a matching Origin read /api/runs (200), a run's CSV
    and opened /api/live (101)."""
    port = rig["port"]
    evil = f"evil.example:{port}"
    for path in ("/api/runs", "/api/runs/1.csv", "/", "/api/session"):
        answer = get(port, path, evil, f"Origin: http://{evil}")
        assert status_of(answer) == 403, (path, answer[:200])
        assert b"allowed_hosts" in answer
    upgrade = get(
        port,
        "/api/live",
        evil,
        f"Origin: http://{evil}",
        "Upgrade: websocket",
        "Sec-WebSocket-Version: 13",
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
    ).replace(b"Connection: close", b"")
    assert status_of(upgrade) == 403
    # Loopback names and the configured one are served.
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"rig-a.lab.example:{port}"):
        assert status_of(get(port, "/api/runs", host)) == 200, host


def test_the_origin_scheme_is_checked(rig: dict[str, Any]) -> None:
    """Item 10: only the Origin's host was compared: `evil://127.0.0.1:PORT` passed."""
    port = rig["port"]
    host = f"127.0.0.1:{port}"
    body = b"{}"
    for origin, want in ((f"evil://{host}", 403), (f"null://{host}", 403), (f"http://{host}", 200)):
        answer = raw_http(
            port,
            (
                f"POST /api/control/stop HTTP/1.1\r\nHost: {host}\r\nOrigin: {origin}\r\n"
                f"X-Usmswitch-Token: {rig['token']}\r\nContent-Type: application/json\r\n"
                f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
            ).encode()
            + body,
        )
        assert status_of(answer) == want, (origin, answer[:300])


def test_the_urls_token_is_traded_for_a_cookie_and_a_clean_url(rig: dict[str, Any]) -> None:
    """Item 11: the token rode in the URL (Referer of 4 asset requests, the history, a proxy's log)."""
    port = rig["port"]
    host = f"127.0.0.1:{port}"
    answer = get(port, f"/?token={rig['token']}&view=runs", host)
    head = answer.partition(b"\r\n\r\n")[0].decode()
    assert status_of(answer) == 303, head
    assert "\r\nLocation: /?view=runs\r\n" in head
    cookie = next(line for line in head.split("\r\n") if line.lower().startswith("set-cookie:"))
    assert f"usmswitch_token={rig['token']}" in cookie
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and "Path=/" in cookie
    # The cookie acts; a wrong token in the URL sets none (and is dropped from the URL all the same).
    session = json.loads(
        get(port, "/api/session", host, f"Cookie: usmswitch_token={rig['token']}").split(b"\r\n\r\n")[1]
    )
    assert session["control"] is True
    wrong = get(port, "/?token=not-the-token", host)
    assert status_of(wrong) == 303 and b"Set-Cookie" not in wrong and b"Location: /\r\n" in wrong
    page = get(port, "/", host)
    assert b"Referrer-Policy: no-referrer" in page


def test_a_nested_control_body_is_a_400(rig: dict[str, Any]) -> None:
    """Item 14: 2,000 nested `[` answered 500 with a RecursionError traceback."""
    port = rig["port"]
    host = f"127.0.0.1:{port}"
    for body in (b"[" * 2000, b'{"target_ns": ' + b"[" * 2000 + b"]" * 2000 + b"}"):
        answer = raw_http(
            port,
            (
                f"POST /api/control/target HTTP/1.1\r\nHost: {host}\r\nX-Usmswitch-Token: {rig['token']}\r\n"
                f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\nConnection: close\r\n\r\n"
            ).encode()
            + body,
        )
        assert status_of(answer) == 400, answer[:300]
        assert b"nests deeper" in answer


def test_half_open_connections_do_not_take_the_panel_or_the_sockets(rig: dict[str, Any]) -> None:
    """Item 4: 1,100 half-open connections to the panel's port ran the server process out of
    descriptors (Unix calls 21 of 21 failed, reset_fault could not get through)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 1200 <= hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (1200, hard))  # this test's own 1,100 ends
    held = []
    try:
        for _ in range(1100):
            s = socket.create_connection(("127.0.0.1", rig["port"]), timeout=10)
            held.append(s)
        # The Unix socket, /metrics and the panel itself still answer; the process keeps its fds.
        with Client(str(rig["sock"]), timeout=10) as c:
            for _ in range(5):
                assert c.status()["state"] in ("cycling", "idle", "fault")
        assert status_of(get(rig["metrics_port"], "/metrics", "127.0.0.1")) == 200
        assert status_of(get(rig["port"], "/api/runs", f"127.0.0.1:{rig['port']}")) == 200
    finally:
        for s in held:
            s.close()


async def _drip(port: int, n: int, every_s: float, rounds: int) -> list[bool]:
    """`n` connections each dripping a byte of a request head every `every_s`; whether each was closed."""
    conns = [await asyncio.open_connection("127.0.0.1", port) for _ in range(n)]
    closed = [False] * n
    for _ in range(rounds):
        for i, (_, writer) in enumerate(conns):
            if closed[i]:
                continue
            try:
                writer.write(b"G")
                await writer.drain()
            except ConnectionError:
                closed[i] = True
        await asyncio.sleep(every_s)
        for i, (reader, _) in enumerate(conns):
            if not closed[i] and reader.at_eof():
                closed[i] = True
    for _, writer in conns:
        writer.close()
    return closed


def test_slowloris_on_either_door_is_closed_and_scrapes_go_on(rig: dict[str, Any]) -> None:
    """Items 4 and 6: 10 connections dripping a byte every 10 s were never closed in 200 s (panel);
    16 dripping every 3 s took every scrape for 120 s (metrics), and the 17th hit an assert."""

    async def main() -> tuple[list[bool], list[bool], list[int]]:
        metrics = asyncio.create_task(_drip(rig["metrics_port"], 17, 1.0, 12))
        panel = asyncio.create_task(_drip(rig["port"], 10, 1.0, 15))
        await asyncio.sleep(0.5)
        scrapes = []
        async with aiohttp.ClientSession() as http:
            for _ in range(5):
                async with http.get(f"http://127.0.0.1:{rig['metrics_port']}/metrics") as resp:
                    scrapes.append(resp.status)
        return await metrics, await panel, scrapes

    metrics_closed, panel_closed, scrapes = asyncio.run(main())
    assert scrapes == [200] * 5
    assert all(metrics_closed) and all(panel_closed)


def test_bad_http_requests_are_one_log_line_without_a_traceback(rig: dict[str, Any]) -> None:
    """Item 9: each malformed HTTP request logged a traceback (25.7 MB in 29 s)."""
    for port in (rig["port"], rig["metrics_port"]):
        for i in range(200):
            bad = (
                b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nno colon here\r\n\r\n",
                b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: -1\r\n\r\n",
                b"GET /\x00 HTTP/1.1\r\n\r\n",
            )[i % 3]
            answer = raw_http(port, bad)
            assert answer == b"" or status_of(answer) == 400
    # The daemon's log (the server process's stderr is the daemon's) is read at its stop.
    rig["bad_requests_sent"] = True


async def _open_feeds(url: str, n: int, cookie: str | None = None) -> tuple[list[Any], int, int]:
    """Open `n` live feeds at once; (the open ones, how many opened, how many were refused)."""
    ws_url = url.replace("http://", "ws://") + "api/live"
    headers = {"Cookie": f"usmswitch_token={cookie}"} if cookie else {}
    session = aiohttp.ClientSession()

    async def one() -> Any:
        try:
            return await session.ws_connect(ws_url, headers=headers, heartbeat=None)
        except aiohttp.WSServerHandshakeError as exc:
            assert exc.status == 503, exc
            return None

    got = await asyncio.gather(*(one() for _ in range(n)))
    opened = [ws for ws in got if ws is not None]
    return [session, *opened], len(opened), n - len(opened)


async def _close_all(held: list[Any]) -> None:
    session, *feeds = held
    for ws in feeds:
        await ws.close()
    await session.close()


def test_the_live_feed_cap_is_atomic_and_never_keeps_the_operator_out(rig: dict[str, Any]) -> None:
    """Item 5: the cap of 32 was checked before an await and counted after: bursts of 200 opened
    64, 96, 79; and 32 held feeds (answering pings) kept the operator's feed at 503 for 75 s."""

    async def main() -> tuple[list[int], bool]:
        opened_per_burst = []
        for _ in range(3):
            held, opened, _ = await _open_feeds(rig["url"], 200)
            opened_per_burst.append(opened)
            await _close_all(held)
            await asyncio.sleep(0.3)  # the server sees the closes
        readonly, _, _ = await _open_feeds(rig["url"], 40)
        operator, opened, _ = await _open_feeds(rig["url"], 1, cookie=rig["token"])
        hello = json.loads((await operator[1].receive(timeout=10)).data) if opened else None
        await _close_all(operator)
        await _close_all(readonly)
        return opened_per_burst, bool(hello and hello["type"] == "hello")

    bursts, operator_served = asyncio.run(main())
    assert all(n <= 32 for n in bursts), bursts
    assert operator_served


def test_zz_the_log_holds_no_traceback(rig: dict[str, Any]) -> None:
    """Items 6 and 9, read last: stop the daemon and look at what it logged under the loads above."""
    if not rig.get("bad_requests_sent"):
        pytest.skip("runs after the bad requests")
    err = stop(rig["proc"]).decode(errors="replace")
    assert "Traceback" not in err, err[-3000:]
    assert "AssertionError" not in err
    lines = [line for line in err.splitlines() if "Error handling request" in line or "BadStatusLine" in line]
    assert len(lines) <= 6, lines[:10]
