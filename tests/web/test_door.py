"""web/door.py on a real aiohttp server under uvloop (the server process's loop), real sockets: a
connection whose request head is complete is never the one a full door sheds, though its handler
starts a step of the event loop after the newcomer's accept (the abuse bench's panel estop under
1,100 half-open connections: "Remote end closed connection without response", 2 of 20)."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import Callable

import pytest
from aiohttp import web

from usmswitch.web.door import DRAIN_S, Door

uvloop = pytest.importorskip("uvloop")


def _connect(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


async def _read_all(s: socket.socket) -> bytes:
    """Everything the server sends until it closes (the loop runs meanwhile)."""
    s.setblocking(False)
    loop = asyncio.get_running_loop()
    out = b""
    while chunk := await asyncio.wait_for(loop.sock_recv(s, 65536), 30):
        out += chunk
    return out


async def _serve(
    door: Door, on_make: Callable[[], None] | None = None
) -> tuple[asyncio.AbstractServer, int, list[int]]:
    """aiohttp behind `door` on a free loopback port, answering "answered" to every request; the
    list's one number counts the aiohttp handlers made (`on_make()` called at each)."""

    async def handler(request: web.BaseRequest) -> web.StreamResponse:
        return await door.handling(request, lambda r: _ok())

    async def _ok() -> web.Response:
        return web.Response(text="answered\n")

    aiohttp_server = web.Server(handler)
    made = [0]

    def make() -> asyncio.BaseProtocol:
        made[0] += 1
        if on_make is not None:
            on_make()
        return aiohttp_server()

    listener = socket.create_server(("127.0.0.1", 0))
    server = await asyncio.get_running_loop().create_server(door.protocol_factory(make), sock=listener)
    return server, listener.getsockname()[1], made


async def _ready_request_survives_a_full_door() -> tuple[bytes, bytes | None]:
    door = Door("test door", 2, head_s=10.0, idle_s=60.0)
    server, port, _ = await _serve(door)
    held: list[socket.socket] = []
    try:
        idle = _connect(port)  # the door's first holder: silent, the one to shed
        await asyncio.sleep(0.2)
        asker = _connect(port)  # the second: the door is now full
        await asyncio.sleep(0.2)
        assert len(door.conns) == 2
        # In one step of the loop: a newcomer's accept, then the asker's complete request. The
        # newcomer is admitted (its connection_made) before the asker's handler starts.
        newcomer = _connect(port)
        held += [idle, asker, newcomer]
        asker.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        answer = await _read_all(asker)
        if not answer:  # the asker was shed: the silent holder is still open
            return answer, None
        return answer, await _read_all(idle)
    finally:
        for s in held:
            s.close()
        server.close()
        door.close()


def test_a_complete_request_is_not_shed_by_a_full_door() -> None:
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        answer, shed = runner.run(_ready_request_survives_a_full_door())
    assert answer.startswith(b"HTTP/1.1 200"), answer[:200]
    assert answer.endswith(b"answered\n")
    assert shed == b""  # the silent holder gave way instead, closed without a word


async def _silent_then_spoken() -> tuple[int, int, bytes, int]:
    door = Door("test door", 64, head_s=10.0, idle_s=60.0)
    server, port, made = await _serve(door)
    silent = [_connect(port) for _ in range(40)]
    try:
        await asyncio.sleep(0.5)
        counted, made_silent = len(door.conns), made[0]
        asker = silent.pop()
        asker.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        answer = await _read_all(asker)
        asker.close()
        return counted, made_silent, answer, made[0]
    finally:
        for s in silent:
            s.close()
        server.close()
        door.close()


def test_a_silent_connection_costs_the_door_no_aiohttp_handler_until_it_speaks() -> None:
    """Issue 35, item 4: 1,100 silent connections renewed as they were shed made an aiohttp handler
    (parser, timers, a task) at each accept, closed unused by the shed; an estop's connection
    waited behind them in the accept queue (panel POST p99 16.8 ms; 10.2 with handlers made at
    the first byte, `BENCH_ABUSE_ONLY=half-open make bench BENCH=abuse`)."""
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        counted, made_silent, answer, made = runner.run(_silent_then_spoken())
    assert counted == 40, "every connection counted against the budget from its accept"
    assert made_silent == 0
    assert answer.startswith(b"HTTP/1.1 200") and answer.endswith(b"answered\n"), answer[:200]
    assert made == 1


_ASK = b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
_URGENT = b"URGENT / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
_URGENT_ANSWER = b"HTTP/1.1 200 OK\r\nContent-Length: 7\r\nConnection: close\r\n\r\nurgent\n"


def _urgent_door(order: list[str]) -> Door:
    """A door whose express lane answers the urgent requests (and notes each in `order`)."""

    def express(transport: asyncio.BaseTransport, data: bytes) -> bytes | None:
        if not data.startswith(b"URGENT"):
            return None
        order.append("urgent")
        return _URGENT_ANSWER

    return Door("test door", 64, 10.0, 60.0, express=express, urgent=lambda data: data.startswith(b"URGENT"))


async def _first_reads_in_one_step(n: int, busy_s: float) -> tuple[list[str], list[bytes]]:
    """`n` requests read in one step of the loop, then an urgent one: sent in the same step
    (`busy_s` 0), or by the first aiohttp handler the door makes (each made `busy_s` long).
    Returns the order the door handled them in, and the answers."""
    order: list[str] = []
    door = _urgent_door(order)
    askers: list[socket.socket] = []
    urgent: socket.socket | None = None

    def on_make() -> None:
        order.append("queued")
        if busy_s and len(order) == 1:
            assert urgent is not None
            urgent.sendall(_URGENT)  # in the kernel before this step of the loop ends
        end = time.perf_counter() + busy_s
        while time.perf_counter() < end:
            pass

    server, port, _ = await _serve(door, on_make)
    try:
        askers = [_connect(port) for _ in range(n)]
        urgent = _connect(port)
        while len(door.conns) < n + 1:
            await asyncio.sleep(0.01)
        # This coroutine holds the loop: every request is in the kernel before it reads one.
        for s in askers:
            s.sendall(_ASK)
        if not busy_s:
            urgent.sendall(_URGENT)
        answers = [await _read_all(s) for s in (urgent, *askers)]
        return order, answers
    finally:
        for s in (*askers, *([urgent] if urgent else [])):
            s.close()
        server.close()
        door.close()


def test_an_urgent_first_read_is_handled_before_those_of_its_step_waiting_their_turn() -> None:
    """Issue 35: a burst of 200 live feeds had each first read handled in the step it came (the
    express lane's 503, aiohttp's handler made), and the panel's estop POST among them waited for
    all (p99 5.5-18 ms, `make bench BENCH=abuse`). The estop's first read is handled as it comes."""
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        order, answers = runner.run(_first_reads_in_one_step(40, 0.0))
    assert order == ["urgent"] + ["queued"] * 40
    assert answers[0] == _URGENT_ANSWER
    assert all(a.startswith(b"HTTP/1.1 200") and a.endswith(b"answered\n") for a in answers[1:])


def test_first_reads_waiting_their_turn_take_at_most_a_budget_of_each_step() -> None:
    """Each step of the loop gives the waiting first reads DRAIN_S, then reads its sockets: an urgent
    request that comes while 20 slow ones wait is handled after the one being handled, not the 20."""
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        order, answers = runner.run(_first_reads_in_one_step(20, 2 * DRAIN_S))
    assert order == ["queued", "urgent"] + ["queued"] * 19
    assert answers[0] == _URGENT_ANSWER
    assert all(a.endswith(b"answered\n") for a in answers[1:])


class _Held:
    """A transport the door holds: whether it was closed, what was written before."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.closed = False
        self.written = b""

    def write(self, data: bytes) -> None:
        self.written += data

    def close(self) -> None:
        self.closed = True


def test_a_full_door_sheds_a_head_begun_first_then_the_longest_idle_oldest_first() -> None:
    """The door keeps its sheddable holders in time order (heads begun, idle) and sheds the front
    of either at once, without scanning its budget at each accept: the order it always had."""
    door = Door("panel", 4, head_s=10, idle_s=60)
    idle_a, idle_b, drip, ready = (_Held(n) for n in ("idle a", "idle b", "drip", "ready"))
    for t in (idle_a, idle_b, drip, ready):
        assert door.admit(t)  # type: ignore[arg-type]
    door.data(drip, b"GET / HT")  # type: ignore[arg-type]  # a head begun, never finished
    door.data(ready, b"GET / HTTP/1.1\r\n\r\n")  # type: ignore[arg-type]  # complete: never shed
    order = []
    for k in range(3):
        newcomer = _Held(f"new {k}")
        assert door.admit(newcomer)  # type: ignore[arg-type]
        shed = [t for t in (idle_a, idle_b, drip, ready) if t.closed and t.name not in order]
        order += [t.name for t in shed]
    assert order == ["drip", "idle a", "idle b"] and not ready.closed
    assert door.shed == 3 and len(door.conns) == 4


def test_the_sweep_closes_late_heads_with_408_and_long_idle_ones_and_no_other() -> None:
    door = Door("metrics", 8, head_s=5, idle_s=120)
    late_head, fresh_head, long_idle, fresh_idle = (_Held(n) for n in ("late", "fresh", "long", "new"))
    for t in (long_idle, late_head):
        door.admit(t)  # type: ignore[arg-type]
    door.data(late_head, b"GET /metrics")  # type: ignore[arg-type]
    for e in door.conns.values():  # as if made long ago
        e.idle_since -= 200
        if e.head_since is not None:
            e.head_since -= 6
    for t in (fresh_idle, fresh_head):
        door.admit(t)  # type: ignore[arg-type]
    door.data(fresh_head, b"GET /")  # type: ignore[arg-type]
    door.sweep()
    assert late_head.closed and b"408 Request Timeout" in late_head.written
    assert long_idle.closed and long_idle.written == b""
    assert not fresh_head.closed and not fresh_idle.closed
    assert door.timed_out == 1 and set(door.conns) == {fresh_head, fresh_idle}
