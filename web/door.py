"""A budget for one HTTP door (the panel, /metrics), as nginx's `limit_conn` and
`client_header_timeout`: connections at once, and time to a complete request head.

aiohttp keeps neither: it takes every connection the kernel hands it, and its keep-alive timer
restarts on every byte, so a client dripping a byte every few seconds held a slot for ever. Here each
connection is tracked from the accept: a request head must be complete within `head_s` of its first
byte, an idle connection (no byte since its last answer) is closed after `idle_s`, and a door at its
budget sheds its holder that is furthest from being useful (a head begun and not finished, then the
longest idle) for the newcomer; a request head complete and waiting for its handler is never shed.
With none to shed, the newcomer gets a short 503 and is closed before anything is read. Each is
enforced before any work, and said in one log line per 10 s at most.

A connection's first read waits its turn: the reads that came in one step of the event loop are
handled (the express lane's answer, or aiohttp's handler made) at most DRAIN_S of them a step,
the loop's sockets read between, but an urgent one (the panel's estop) is answered as it comes.
A burst of 200 live feeds had each of its first reads handled in the step it arrived (the lane's
503 0.13 ms apiece, aiohttp's request 0.28: some 30 ms a burst), and the panel's estop POST, a
connection among them, waited for them all (up to 25 ms, `make bench BENCH=abuse`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any, cast

from aiohttp import web

log = logging.getLogger("usmswitch.web")

_LOG_EVERY_NS = 10_000_000_000
_SWEEP_S = 0.25
#: The time a step of the event loop gives to first reads waiting their turn (one more may overrun it).
DRAIN_S = 0.0005

#: (A connection, its first read) -> its whole answer (bytes, or a future of them), or None: aiohttp's.
Express = Callable[[asyncio.BaseTransport, bytes], "bytes | asyncio.Future[bytes] | None"]


class _Entry:
    __slots__ = ("active", "head_since", "idle_since", "ready", "tail", "transport")

    def __init__(self, transport: asyncio.BaseTransport, now: float) -> None:
        self.transport = transport
        self.active = 0  # requests being handled (a live feed is one for its whole life)
        self.head_since: float | None = None  # first byte of a request not yet handled
        self.idle_since = now
        # A request head complete, its handler not started yet (a step of the event loop later):
        # never shed. Under a connection flood the accepts of one step came before that handler,
        # and its connection, "a head begun", was the first shed: an estop closed unanswered.
        self.ready = False
        self.tail = b""  # the last bytes seen of a head begun: its end may be split across reads


class Door:
    """Connections and time-to-request budgets for one aiohttp server."""

    def __init__(
        self,
        name: str,
        max_connections: int,
        head_s: float,
        idle_s: float,
        express: Express | None = None,
        urgent: Callable[[bytes], bool] | None = None,
    ) -> None:
        self.name = name
        self.express = express  # web/express.py
        self.urgent = urgent  # a first read handled as it comes, not in its turn
        self.expressed = 0  # requests the express lane answered
        self.max_connections = max_connections
        self.head_s = head_s
        self.idle_s = idle_s
        self.conns: dict[asyncio.BaseTransport, _Entry] = {}
        # The sheddable, oldest first (insertion order is time order): heads begun (and complete,
        # waiting a step for their handler), and idle connections. A full door sheds the first
        # of either at once, and the sweep reads each from its front only as far as the late ones
        # go: no scan of the budget at each accept (1,100 silent connections renewed: ~10 % of
        # the HTTP thread was that scan).
        self._heads: dict[_Entry, None] = {}
        self._idle: dict[_Entry, None] = {}
        self.refused = self.shed = self.timed_out = 0
        self._logged_ns = 0
        self._sweeper: asyncio.Task[None] | None = None
        # Connections whose first read waits its turn; a `_drain` is due while it is not empty.
        self._turns: deque[_Tracked] = deque()

    # -- wiring ------------------------------------------------------------------------------------
    def protocol_factory(
        self, make: Callable[[], asyncio.BaseProtocol]
    ) -> Callable[[], asyncio.BaseProtocol]:
        """Wrap aiohttp's protocol factory (a web.Server) with this door's budget."""

        def factory() -> asyncio.BaseProtocol:
            if self._sweeper is None:
                self._sweeper = asyncio.get_running_loop().create_task(self._sweep_forever())
            return _Tracked(self, make)

        return factory

    def middleware(self) -> Any:
        """An aiohttp middleware marking a connection busy while its request is handled."""

        @web.middleware
        async def tracked(request: web.Request, handler: Callable[[web.Request], Awaitable[Any]]) -> Any:
            return await self.handling(request, handler)

        return tracked

    async def handling(self, request: web.BaseRequest, handler: Callable[[Any], Awaitable[Any]]) -> Any:
        """Run `handler(request)` with its connection counted as busy (not shed, not timed out)."""
        entry = self._busy(request.transport) if request.transport is not None else None
        try:
            return await handler(request)
        finally:
            if entry is not None:
                entry.active -= 1
                entry.idle_since = time.monotonic()
                if not entry.active and entry.transport in self.conns:
                    self._idle[entry] = None

    def _busy(self, transport: asyncio.BaseTransport) -> _Entry | None:
        entry = self.conns.get(transport)
        if entry is not None:
            entry.active += 1
            entry.head_since = None
            entry.ready = False
            entry.tail = b""
            self._heads.pop(entry, None)
            self._idle.pop(entry, None)
        return entry

    def take(self, transport: asyncio.BaseTransport, data: bytes) -> bool:
        """Whether the express lane answers `data`, a connection's first read: then the connection
        is busy until its answer is written, and closed after it."""
        if self.express is None:
            return False
        try:
            answer = self.express(transport, data)
        except Exception as exc:  # a bug of the lane: aiohttp judges the request as it would any other
            self._say(f"the express lane failed ({exc!r}): the request went to aiohttp")
            return False
        if answer is None:
            return False
        self.expressed += 1
        self._busy(transport)
        if isinstance(answer, bytes):
            _send_close(transport, answer)
        else:
            answer.add_done_callback(lambda done: _send_close(transport, done.result()))
        return True

    def wait_turn(self, tracked: _Tracked) -> None:
        """`tracked`'s first read is handled in its turn, after those before it (`_drain`)."""
        self._turns.append(tracked)
        if len(self._turns) == 1:
            asyncio.get_running_loop().call_soon(self._drain)

    def _drain(self) -> None:
        # Each step takes up to DRAIN_S of turns, then hands the loop back to read its sockets.
        end = time.perf_counter() + DRAIN_S
        while self._turns:
            self._turns.popleft().begin()
            if time.perf_counter() > end:
                break
        if self._turns:
            asyncio.get_running_loop().call_soon(self._drain)

    def close(self) -> None:
        """Stop the sweeper (the server is closing)."""
        if self._sweeper is not None:
            self._sweeper.cancel()

    # -- the budget -------------------------------------------------------------------------------
    def admit(self, transport: asyncio.BaseTransport) -> bool:
        """Count a new connection, shedding a holder when full; False: refuse it."""
        if len(self.conns) >= self.max_connections and not self._shed_one():
            self.refused += 1
            self._say(f"full (max {self.max_connections} connections): newcomers refused with 503")
            return False
        entry = self.conns[transport] = _Entry(transport, time.monotonic())
        self._idle[entry] = None
        return True

    def _shed_one(self) -> bool:
        # A head begun and never finished first (slowloris), then the longest idle.
        # A head complete and waiting for its handler is never shed: skipped (a step's worth).
        victim = next((e for e in self._heads if not e.ready), None) or next(iter(self._idle), None)
        if victim is None:
            return False
        self.shed += 1
        self._say(f"full (max {self.max_connections} connections): idle holders shed for newcomers")
        self._drop(victim)
        return True

    def _drop(self, entry: _Entry) -> None:
        self._forget(entry)
        entry.transport.close()

    def _forget(self, entry: _Entry) -> None:
        self.conns.pop(entry.transport, None)
        self._heads.pop(entry, None)
        self._idle.pop(entry, None)

    def data(self, transport: asyncio.BaseTransport, data: bytes) -> None:
        """Bytes arrived on `transport`: a head begun, or complete (its handler comes next)."""
        entry = self.conns.get(transport)
        if entry is None or entry.active or entry.ready:
            return
        if entry.head_since is None:
            entry.head_since = time.monotonic()
            self._idle.pop(entry, None)
            self._heads[entry] = None
        seen = entry.tail + data
        if b"\r\n\r\n" in seen:
            entry.ready = True
            entry.tail = b""
        else:
            entry.tail = seen[-3:]

    def lost(self, transport: asyncio.BaseTransport) -> None:
        entry = self.conns.get(transport)
        if entry is not None:
            self._forget(entry)

    def sweep(self) -> None:
        """Close connections past their head or idle time (each byte restarts nothing)."""
        now = time.monotonic()
        while self._heads:
            entry = next(iter(self._heads))
            if entry.head_since is None or now - entry.head_since <= self.head_s:
                break
            self.timed_out += 1
            self._say(f"a request head not complete within {self.head_s:g} s: closed")
            _write_close(entry.transport, 408, "Request Timeout", "request head not complete in time\n")
            self._forget(entry)
        while self._idle:
            entry = next(iter(self._idle))
            if now - entry.idle_since <= self.idle_s:
                break
            self._drop(entry)

    async def _sweep_forever(self) -> None:
        while True:
            await asyncio.sleep(_SWEEP_S)
            self.sweep()

    def _say(self, what: str) -> None:
        now = time.monotonic_ns()
        if now - self._logged_ns >= _LOG_EVERY_NS:
            self._logged_ns = now
            log.warning(
                "%s: %s (refused %d, shed %d, timed out %d so far)",
                self.name,
                what,
                self.refused,
                self.shed,
                self.timed_out,
            )


class _Tracked(asyncio.Protocol):
    """aiohttp's protocol behind the door: counted at connection_made, made at the first byte.

    A connection that has sent nothing costs the door its entry and no more: aiohttp's handler (its
    parser, its timers and a task for each connection) is made when a request begins. Under 1,100
    silent connections renewed as they were shed, each accept made one and the shed closed it, and
    an estop's connection waited behind them in the kernel's accept queue.
    """

    def __init__(self, door: Door, make: Callable[[], asyncio.BaseProtocol]) -> None:
        self.door = door
        self.make = make
        self.inner: asyncio.Protocol | None = None
        self.transport: asyncio.BaseTransport | None = None
        self.admitted = False
        self.expressed = False
        self.waiting: bytes | None = None  # its first read, waiting its turn at the door

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport
        if not self.door.admit(transport):
            _write_close(
                transport, 503, "Service Unavailable", f"too many connections to the {self.door.name}\n"
            )
            return
        self.admitted = True

    def data_received(self, data: bytes) -> None:
        if not self.admitted or self.expressed:
            return
        assert self.transport is not None
        self.door.data(self.transport, data)
        if self.inner is not None:
            self.inner.data_received(data)
        elif self.waiting is not None:  # more of it before its turn came
            self.waiting += data
        elif self.door.urgent is not None and self.door.urgent(data):
            self._hand_on(data)
        else:
            self.waiting = data
            self.door.wait_turn(self)

    def begin(self) -> None:
        """Its turn: its first read handed on, unless the connection went meanwhile."""
        data, self.waiting = self.waiting, None
        if data is not None and self.transport is not None and not self.transport.is_closing():
            self._hand_on(data)  # else gone (or shed) while it waited

    def _hand_on(self, data: bytes) -> None:
        """The first read to the express lane, else to aiohttp's handler, made now."""
        assert self.transport is not None
        if self.door.take(self.transport, data):
            self.expressed = True  # answered at the door; anything after it is not read
            return
        inner = self.inner = cast(asyncio.Protocol, self.make())
        inner.connection_made(self.transport)
        inner.data_received(data)

    def eof_received(self) -> bool | None:
        # Before its turn: closed, as aiohttp closes on a half-close (its eof_received says so).
        return self.inner.eof_received() if self.inner is not None else None

    def pause_writing(self) -> None:
        if self.inner is not None:  # nothing is written before aiohttp's handler exists
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.inner is not None:
            self.inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.transport is not None:
            self.door.lost(self.transport)
        if self.inner is not None:
            self.inner.connection_lost(exc)


def _write_close(transport: asyncio.BaseTransport, status: int, reason: str, body: str) -> None:
    """A short text answer and a close."""
    data = body.encode()
    _send_close(
        transport,
        b"HTTP/1.1 %d %s\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: %d\r\n"
        b"Connection: close\r\n\r\n%s" % (status, reason.encode(), len(data), data),
    )


def _send_close(transport: asyncio.BaseTransport, answer: bytes) -> None:
    """A whole answer, then a close (after the bytes are out). uvloop's transports are not
    asyncio.Transport subclasses: duck-typed."""
    with contextlib.suppress(RuntimeError, OSError):
        cast(asyncio.WriteTransport, transport).write(answer)
    transport.close()


class QuietLog:
    """aiohttp's server logger: a bad request is one line, no traceback, at most one per 10 s
    (40,000 malformed requests logged 25.7 MB of tracebacks in 29 s)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.count = 0
        self._logged_ns = 0

    def _one(self, msg: str, args: tuple[Any, ...], exc: BaseException | None) -> None:
        self.count += 1
        now = time.monotonic_ns()
        if now - self._logged_ns < _LOG_EVERY_NS:
            return
        self._logged_ns = now
        text = msg % args if args else msg
        why = f": {type(exc).__name__}: {str(exc)[:200]}" if exc is not None else ""
        log.warning("%s: %s%s (%d such so far)", self.name, text, why, self.count)

    def exception(self, msg: str, *args: Any, exc_info: Any = None, **kw: Any) -> None:
        exc = exc_info if isinstance(exc_info, BaseException) else None
        self._one(msg, args, exc)

    def error(self, msg: str, *args: Any, exc_info: Any = None, **kw: Any) -> None:
        self.exception(msg, *args, exc_info=exc_info)

    def warning(self, msg: str, *args: Any, exc_info: Any = None, **kw: Any) -> None:
        self.exception(msg, *args, exc_info=exc_info)

    def info(self, msg: str, *args: Any, **kw: Any) -> None:
        pass

    def debug(self, msg: str, *args: Any, **kw: Any) -> None:
        pass

    def isEnabledFor(self, level: int) -> bool:
        return level >= logging.WARNING
