"""The panel's express lane (web/express.py, `Panel.express`) on the real panel under uvloop, real
sockets, a stand-in backend: an estop POST with the token and a live feed past the cap are answered at
the door, with aiohttp's status and body; everything else, and every request the lane's checks would
refuse, is aiohttp's as before."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from typing import Any

import aiohttp
import pytest
from aiohttp.test_utils import make_mocked_request

from usmswitch.protocol.wire import ErrorCode, RpcError
from usmswitch.web.express import parse
from usmswitch.web.panel import MAX_PANELS, MAX_READONLY_PANELS, OWNER, serve_panel

uvloop = pytest.importorskip("uvloop")

TOKEN = "t" * 43


class Backend:
    """The daemon as the panel sees it: every call recorded; the estop answers at once, after
    `delay_s`, or is refused with `refuse`."""

    def __init__(self, delay_s: float = 0.0, refuse: RpcError | None = None, cancel: bool = False) -> None:
        self.calls: list[tuple[str, list[Any]]] = []
        self.delay_s = delay_s
        self.refuse = refuse
        self.cancel = cancel  # the call's future cancelled (the server process closing)

    def call(self, method: str, params: list[Any]) -> asyncio.Future[Any]:
        self.calls.append((method, params))
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[Any] = loop.create_future()
        result = {"state": "fault", "fault": "estop (panel)"} if method == "estop" else {}

        def settle() -> None:
            if self.cancel and method == "estop":
                fut.cancel()
            elif self.refuse is not None:
                fut.set_exception(self.refuse)
            else:
                fut.set_result([] if method == "history" else result)

        if self.delay_s:
            loop.call_later(self.delay_s, settle)
        else:
            settle()
        return fut

    def listen(self, listener: Any) -> None:
        pass

    async def export_csv(self, run_id: int, write: Any) -> int:
        return 0


def _estop(port: int, *extra: str, body: bytes = b"{}", host: str | None = None) -> bytes:
    head = [
        "POST /api/control/estop HTTP/1.1",
        f"Host: {host or f'127.0.0.1:{port}'}",
        f"Content-Length: {len(body)}",
        *extra,
    ]
    return ("\r\n".join(head) + "\r\n\r\n").encode() + body


def _feed(port: int, *extra: str) -> bytes:
    head = [
        "GET /api/live HTTP/1.1",
        f"Host: 127.0.0.1:{port}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
        "Sec-WebSocket-Version: 13",
        *extra,
    ]
    return ("\r\n".join(head) + "\r\n\r\n").encode()


async def _exchange(port: int, *parts: bytes) -> tuple[int, Any]:
    """Send `parts` as separate writes (a pause between them: separate reads at the server), read
    the answer whole; (status, its JSON body, or its bytes when it is not JSON)."""
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    s.setblocking(False)
    loop = asyncio.get_running_loop()
    try:
        for i, part in enumerate(parts):
            if i:
                await asyncio.sleep(0.05)
            await loop.sock_sendall(s, part)
        out = b""
        while chunk := await asyncio.wait_for(loop.sock_recv(s, 65536), 30):
            out += chunk
            if b"\r\n\r\n" in out:
                head, _, body = out.partition(b"\r\n\r\n")
                length = [ln for ln in head.split(b"\r\n") if ln.lower().startswith(b"content-length:")]
                if length and len(body) >= int(length[0].split(b":")[1]):
                    break
    finally:
        s.close()
    head, _, body = out.partition(b"\r\n\r\n")
    json_body = b"application/json" in head.lower()
    return int(head.split()[1]), json.loads(body) if json_body else body


def _split(request: bytes) -> tuple[bytes, bytes]:
    """The same request in two reads: the lane takes only a whole first read, so aiohttp answers."""
    return request[:20], request[20:]


def panel_at(backend: Backend, body: Any) -> Any:
    """`body(the running panel, its port)` in a uvloop of its own, the panel on a free port."""

    async def main() -> Any:
        listener = socket.create_server(("127.0.0.1", 0))
        served = await serve_panel(listener, backend, TOKEN)
        try:
            return await body(served, listener.getsockname()[1])
        finally:
            served.close()
            await asyncio.sleep(0.05)

    return uvloop.run(main())


def test_an_estop_post_is_answered_at_the_door_as_aiohttp_answers_it() -> None:
    backend = Backend()

    async def body(served: Any, port: int) -> list[Any]:
        seen = []
        for auth in (f"X-Usmswitch-Token: {TOKEN}", f"Cookie: other=1; usmswitch_token={TOKEN}"):
            request = _estop(port, auth)
            before = served.door.expressed
            seen.append((await _exchange(port, request), served.door.expressed - before))
            seen.append((await _exchange(port, *_split(request)), served.door.expressed - before - 1))
        return seen

    seen = panel_at(backend, body)
    answers = [answer for answer, _ in seen]
    assert [taken for _, taken in seen] == [1, 0, 1, 0]  # whole: the lane; split: aiohttp
    assert answers == [(200, {"ok": True, "result": {"state": "fault", "fault": "estop (panel)"}})] * 4
    assert [c for c in backend.calls if c[0] == "estop"] == [("estop", [OWNER])] * 4


def test_the_daemons_refusal_and_a_late_answer_read_as_aiohttps() -> None:
    refused = Backend(refuse=RpcError(ErrorCode.UNREACHABLE, "the daemon is not reachable"))
    late = Backend(delay_s=0.2)

    async def body(served: Any, port: int) -> list[Any]:
        request = _estop(port, f"X-Usmswitch-Token: {TOKEN}")
        return [
            await _exchange(port, request),
            await _exchange(port, *_split(request)),
            served.door.expressed,
        ]

    express, aiohttp_, taken = panel_at(refused, body)
    assert (
        express == aiohttp_ == (409, {"error": "the daemon is not reachable", "code": ErrorCode.UNREACHABLE})
    )
    assert taken == 1

    async def timed(served: Any, port: int) -> tuple[Any, float, int]:
        t0 = time.monotonic()
        answer = await _exchange(port, _estop(port, f"X-Usmswitch-Token: {TOKEN}"))
        return answer, time.monotonic() - t0, served.door.expressed

    answer, took_s, taken = panel_at(late, timed)
    assert answer == (200, {"ok": True, "result": {"state": "fault", "fault": "estop (panel)"}})
    assert took_s >= 0.2 and taken == 1

    async def cancelled(served: Any, port: int) -> tuple[Any, int]:
        return await _exchange(port, _estop(port, f"X-Usmswitch-Token: {TOKEN}")), served.door.expressed

    (status, body), taken = panel_at(Backend(delay_s=0.1, cancel=True), cancelled)
    assert (status, taken) == (500, 1) and body["error"].startswith("estop: ")  # answered, not left open


def test_what_the_lane_does_not_take_is_aiohttps_and_judged_as_before() -> None:
    backend = Backend()
    token = f"X-Usmswitch-Token: {TOKEN}"

    async def body(served: Any, port: int) -> list[tuple[str, int, int]]:
        cases = {
            "no token": (_estop(port), 403),
            "a wrong token": (_estop(port, "X-Usmswitch-Token: " + "u" * 43), 403),
            "another host": (_estop(port, token, host="evil.example"), 403),
            "another site's origin": (_estop(port, token, "Origin: http://evil.example"), 403),
            "an origin of another scheme": (_estop(port, token, f"Origin: ftp://127.0.0.1:{port}"), 403),
            "a field the estop has not": (_estop(port, token, body=b'{"x": 1}'), 400),
            "a body nested deep": (_estop(port, token, body=b"[" * 50), 400),
            "a body that is not JSON": (_estop(port, token, body=b"{no"), 400),
            "a body past the limit": (_estop(port, token, body=b" " * 5000), 413),
            "a query": (_estop(port, token).replace(b"estop ", b"estop?x=1 "), 200),
            "HTTP/1.0": (_estop(port, token).replace(b"HTTP/1.1", b"HTTP/1.0"), 200),
            "Host twice": (_estop(port, token, f"Host: 127.0.0.1:{port}"), 400),
            "another control": (_estop(port, token).replace(b"estop", b"reset"), 200),
            "the session": (f"GET /api/session HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode(), 200),
        }
        seen = []
        for name, (request, want) in cases.items():
            before = served.door.expressed
            status, _ = await _exchange(port, request)
            seen.append(((name, status, served.door.expressed - before), (name, want, 0)))
        return seen

    for got, want in panel_at(backend, body):
        assert got == want  # aiohttp's status; not taken by the lane
    estops = [c for c in backend.calls if c[0] == "estop"]
    assert len(estops) == 2  # the query's and HTTP/1.0's, by aiohttp's route


def test_a_live_feed_past_the_cap_is_refused_at_the_door_with_aiohttps_answer() -> None:
    async def body(served: Any, port: int) -> list[Any]:
        served.panel.feeds = MAX_PANELS  # the feeds full, none of them read-only: nothing to shed
        seen = []
        for auth in ((), (f"Cookie: usmswitch_token={TOKEN}",)):
            before = served.door.expressed
            seen.append((await _exchange(port, _feed(port, *auth)), served.door.expressed - before))
            seen.append(
                (await _exchange(port, *_split(_feed(port, *auth))), served.door.expressed - before - 1)
            )
        served.panel.feeds = 0
        return seen

    seen = panel_at(Backend(), body)
    refused = (503, {"error": f"too many open panels (max {MAX_PANELS}); close one", "code": None})
    assert seen == [(refused, 1), (refused, 0), (refused, 1), (refused, 0)]


def test_read_only_feeds_past_their_cap_are_refused_at_the_door_and_the_operator_still_gets_in() -> None:
    """Real feeds: the read-only ones past MAX_READONLY_PANELS are the lane's 503s (a burst's
    refusals cost no aiohttp request); an operator's feed, whatever else its Cookie header holds,
    is aiohttp's and opens."""

    async def body(served: Any, port: int) -> tuple[int, int, int, int, bool]:
        url = f"ws://127.0.0.1:{port}/api/live"
        async with aiohttp.ClientSession() as http:

            async def one(cookie: str | None = None) -> Any:
                headers = {"Cookie": cookie} if cookie else {}
                try:
                    return await http.ws_connect(url, headers=headers, heartbeat=None)
                except aiohttp.WSServerHandshakeError as exc:
                    assert exc.status == 503, exc
                    return None

            before = served.door.expressed
            feeds = [await one() for _ in range(MAX_READONLY_PANELS + 6)]
            taken = served.door.expressed - before
            stale_first = f"usmswitch_token={'s' * 43}; usmswitch_token={TOKEN}"
            operator = await one(stale_first)
            hello = json.loads((await operator.receive(timeout=10)).data) if operator is not None else {}
            opened = sum(ws is not None for ws in feeds)
            for ws in [*feeds, operator]:
                if ws is not None:
                    await ws.close()
            return (
                opened,
                len(feeds) - opened,
                taken,
                served.door.expressed - before - taken,
                hello.get("type") == "hello",
            )

    opened, refused, taken, operator_taken, operator_in = panel_at(Backend(), body)
    assert (opened, refused, taken) == (MAX_READONLY_PANELS, 6, 6)
    assert operator_taken == 0 and operator_in


def test_a_burst_of_feeds_is_refused_past_the_caps_at_the_door() -> None:
    """200 read-only feeds asked for at once: each is asked before any handler has counted one, so
    the lane counts those it lets through; the caps hold and every refusal is the lane's."""

    async def body(served: Any, port: int) -> tuple[int, int, int, int]:
        url = f"ws://127.0.0.1:{port}/api/live"
        async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=0)) as http:

            async def one() -> Any:
                try:
                    return await http.ws_connect(url, heartbeat=None)
                except aiohttp.WSServerHandshakeError as exc:
                    assert exc.status == 503, exc
                    return None

            feeds = await asyncio.gather(*(one() for _ in range(200)))
            opened = sum(ws is not None for ws in feeds)
            counted = served.panel.feeds
            for ws in feeds:
                if ws is not None:
                    await ws.close()
            return opened, served.door.expressed, counted, len(served.panel.feeds_asked)

    opened, taken, counted, asked = panel_at(Backend(), body)
    assert (opened, taken, counted, asked) == (MAX_READONLY_PANELS, 200 - MAX_READONLY_PANELS, opened, 0)


def test_only_one_whole_plain_request_is_parsed() -> None:
    whole = b"POST /api/control/estop HTTP/1.1\r\nHost: h\r\nContent-Length: 2\r\n\r\n{}"
    request = parse(whole, 4096)
    assert request is not None
    assert (request.method, request.path, request.body, request.headers["host"]) == (
        "POST",
        "/api/control/estop",
        b"{}",
        "h",
    )
    chunked = b"POST /a HTTP/1.1\r\nHost: h\r\nTransfer-Encoding: chunked\r\n\r\n2\r\n{}\r\n0\r\n\r\n"
    for other in (
        whole[:-1],  # the body not all here
        whole + whole,  # pipelined
        whole + b"GET",  # a second request begun
        chunked,
        whole.replace(b"/api/control/estop", b"http://h/api/control/estop"),  # absolute form
        whole.replace(b"Host: h", b"Host: h\r\nContent-Length: 2"),
        b"\x16\x03\x01\x02\x00",  # TLS's hello
        whole + b" " * 9000,
    ):
        assert parse(other, 4096) is None, other
    assert parse(whole, 1) is None  # the body past the limit given
    # Cookies as browsers send them, other applications' on the same host among them: read pair by
    # pair as aiohttp's request.cookies reads them (the last of a name, a bare name empty).
    for header in ('a=1; usmswitch_token="xy"; b; c={"k": [1, 2]}; a=2', "", "x", ";;", "t=1;t=2 ; u= v "):
        cookie = parse(whole.replace(b"Host: h", b"Host: h\r\nCookie: " + header.encode()), 4096)
        assert cookie is not None
        assert dict(cookie.cookies) == dict(
            make_mocked_request("GET", "/", headers={"Cookie": header}).cookies
        )
