"""The browser panel, served over HTTP by the socket's server process (server/rpc_process.py).

The panel is a client of the server process like any socket client: its reads and controls are
socket methods dispatched by the same code (`Backend.call`: the same parameter checks, calls
forwarded to the daemon over the channel, estop over the urgent channel, history and runs read from
the records file), and its live feed is one subscription to the `stroke`, `state`, `run` and `queue`
notifications, shared by every open panel. The loop's process never sees a browser.

What a browser may do: read without a token (the page, the live feed, the queue of runs, the runs,
their notes and CSV); act (start, stop, targets, mode, reset, estop; submit to the queue, reorder,
cancel, pause and resume it; a run's notes: web/panel_controls.py) with the token the daemon writes
beside its socket,
mode 0640 and the socket's group (docs/panel.md). A control without it is refused with 403 and a
message the page shows; a bad control is refused with 400 and what was wrong.

Live updates: one ticker sends every open panel, at most TICK_S apart, the strokes it has not seen
(JSON, one message per tick however many strokes landed), with the state and the run's statistics
when they changed. A panel that does not read is skipped, never waited for, and catches up from the
buffer of the last HISTORY_STROKES strokes (or is told it missed some).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import itertools
import json
import logging
import socket
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from importlib import resources
from typing import Any, Protocol

from aiohttp import WSMsgType, web

from usmswitch.protocol.wire import ErrorCode, RpcError
from usmswitch.web.budgets import HTTP_BACKLOG, PANEL_CONNECTIONS, PANEL_HEAD_S, PANEL_IDLE_S
from usmswitch.web.door import Door, QuietLog
from usmswitch.web.express import json_answer, parse
from usmswitch.web.panel_controls import CONTROLS, OWNER, control_params

log = logging.getLogger("usmswitch.web")

TOKEN_HEADER = "X-Usmswitch-Token"
#: The cookie the URL's token is traded for on first load (HttpOnly, SameSite=Strict), as Jupyter does.
TOKEN_COOKIE = "usmswitch_token"
#: Host names the panel answers to besides `[web] allowed_hosts`: a page asked for as another name
#: (DNS rebinding: `evil.example` resolving to 127.0.0.1) is refused before anything is read.
LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1", "[::1]"})
#: Connections at once to the panel's port (web/door.py): a page and its assets take a few, a live
#: feed one; past it the longest idle is shed for a newcomer, else 503. A request head begun must be
#: complete within HEAD_TIMEOUT_S (408, closed; each byte restarts nothing); a connection silent
#: IDLE_TIMEOUT_S at its start or between requests is closed.
MAX_CONNECTIONS = PANEL_CONNECTIONS
HEAD_TIMEOUT_S = PANEL_HEAD_S
IDLE_TIMEOUT_S = PANEL_IDLE_S
#: Live feeds kept for pages without the token: an operator's feed (the token's cookie) sheds the
#: oldest of them when the feeds are full, so read-only holders never keep the operator out.
MAX_READONLY_PANELS = 24
#: The estop's source when a page pressed it on its live feed (the fault reads `estop (panel, live feed)`).
FEED_OWNER = f"{OWNER}, live feed"
FEED_TAKES = 'the live feed takes only {"estop": ID} (ID an integer or a string of at most 64 characters)'
#: JSON nesting a control's body may have (a control takes a flat object).
MAX_JSON_DEPTH = 8
#: Strokes kept for a panel that opens (a few seconds of history) or falls behind: ~10 s at 100/s.
HISTORY_STROKES = 1000
#: Live updates go out at most this often: 100 strokes a second are 10 per message.
TICK_S = 0.1
#: The daemon's status is asked at most this often (and at once when the state changes).
STATUS_EVERY_S = 2.0
#: Open live feeds at most; more are answered 503.
MAX_PANELS = 32
#: A panel whose unsent bytes exceed this is skipped until it reads (it catches up from the buffer).
BEHIND_BYTES = 256 * 1024
#: Runs the runs list shows, newest last; each ended run's statistics are kept (they never change).
RUNS_SHOWN = 12
MAX_BODY_BYTES = 4096

#: The HTTP answer to a refused call, by the protocol's error code.
_HTTP_OF_CODE = {
    ErrorCode.INVALID_PARAMS: 400,
    ErrorCode.UNKNOWN_METHOD: 400,
    ErrorCode.FAULT: 409,
    ErrorCode.STATE: 409,
    ErrorCode.UNREACHABLE: 409,
    ErrorCode.BUSY: 503,
    ErrorCode.UNAVAILABLE: 503,
    ErrorCode.TIMEOUT: 504,
}
_STATIC_TYPES = {".js": "text/javascript", ".css": "text/css", ".html": "text/html", ".txt": "text/plain"}


class Asked(Protocol):
    """What the checks read of a request: aiohttp's, or the express lane's (web/express.py)."""

    @property
    def headers(self) -> Mapping[str, str]: ...

    @property
    def cookies(self) -> Mapping[str, str]: ...


class BadBody(ValueError):
    """A control's body that is not a flat JSON object's text (400, no error code)."""


class Backend(Protocol):
    """What the panel needs of the server process (server/rpc_process.py provides it)."""

    def call(self, method: str, params: list[Any]) -> Awaitable[Any]:
        """A socket method, dispatched as a socket client's request; raises RpcError when refused."""
        ...

    def listen(self, listener: Callable[[str, Any], None]) -> None:
        """Call `listener(topic, payload)` for every stroke, state, run and queue notification."""
        ...

    def export_csv(self, run_id: int, write: Callable[[bytes], Awaitable[None]]) -> Awaitable[int]:
        """Write a run's records as CSV (protocol/record_csv.py) in chunks; returns how many."""
        ...


def compact(rec: dict[str, Any]) -> list[Any]:
    """A stroke as the page plots it: [cycle, direction, operating, error, total, target, t_hat,
    flags, run_id] (ns integers; None where the stroke has none, a stall's)."""
    return [
        rec["cycle"],
        rec["direction"],
        rec["operating_ns"],
        rec["error_ns"],
        rec["total_ns"],
        rec["target_ns"],
        rec["t_hat_ns"],
        rec["flags"],
        rec.get("run_id"),
    ]


class _Viewer:
    """One open live feed."""

    def __init__(
        self, ws: web.WebSocketResponse, transport: asyncio.Transport | None, operator: bool = False
    ) -> None:
        self.ws = ws
        self.operator = operator  # opened with the token (its cookie): never shed for a read-only one
        self.opened = time.monotonic()
        self.transport = transport
        self.seq = 0  # the last stroke sent
        self.sending: asyncio.Task[None] | None = None
        self.stats_sent: object = None
        self.status_sent: object = None
        self.queue_sent: object = None

    def busy(self) -> bool:
        if self.sending is not None and not self.sending.done():
            return True
        return self.transport is not None and self.transport.get_write_buffer_size() > BEHIND_BYTES


class Panel:
    """The panel's state in the server process: the live buffer, the viewers, the latest figures."""

    def __init__(
        self,
        backend: Backend,
        token: str | None,
        token_file: str | None,
        allowed_hosts: frozenset[str] = frozenset(),
    ) -> None:
        self.backend = backend
        self.token = token
        self.token_file = token_file
        self.allowed_hosts = LOOPBACK_HOSTS | {h.lower() for h in allowed_hosts}
        self.feeds = 0  # live feeds open or opening: counted before any await (the cap is atomic)
        self.readonly_feeds = 0  # of them, opened without the token
        #: Live feeds the express lane let through to aiohttp, their handler not begun (-> whether
        #: with the token): counted against the caps from the door on, so that of a burst's 200,
        #: those past the caps are the lane's short answers, not 176 aiohttp requests.
        self.feeds_asked: dict[asyncio.BaseTransport, bool] = {}
        self.closing: set[asyncio.Task[Any]] = set()  # feeds being closed for an operator's
        self.strokes: deque[tuple[int, list[Any]]] = deque(maxlen=HISTORY_STROKES)
        self.seq = 0
        self.viewers: set[_Viewer] = set()
        self.status: dict[str, Any] | None = None
        self.status_at = 0.0
        self.status_stale = True
        self.figures = 0  # bumped whenever `status` or `stats` changes (the hello's cache)
        self._hello: tuple[Any, ...] | None = None  # hello_text's: (figures, when, JSON, as of)
        self.stats: dict[str, Any] | None = None
        #: The queue as the page shows it: the daemon's Queue (paused, current, queued) and the run
        #: going ("run"), kept from `status` and the `queue` and `run` notifications.
        self.queue: dict[str, Any] | None = None
        self.queue_heard = 0  # queue and run notifications heard
        self.runs_version = 0
        self.dropped = 0
        self.run_stats: dict[int, Any] = {}  # ended runs' statistics: they never change
        self._status_task: asyncio.Task[None] | None = None
        self.seeding: asyncio.Task[None] | None = None
        backend.listen(self.on_note)

    # -- the feed ----------------------------------------------------------------------------------
    def on_note(self, topic: str, payload: Any) -> None:
        """A notification from the daemon (on the server process's event loop)."""
        if topic == "stroke":
            self.seq += 1
            self.strokes.append((self.seq, compact(payload)))
        elif topic == "state":
            if self.status is not None:
                self.status.update(payload)
                self.figures += 1
            self.status_stale = True
        elif topic == "run":
            self.runs_version += 1
            self.queue_heard += 1
            if isinstance(payload, dict) and self.queue is not None:
                going = self.queue.get("run")
                if payload.get("end_reason") is None:
                    self.set_queue(self.queue, payload)  # opened, or its notes edited
                elif going is not None and going.get("run_id") == payload.get("run_id"):
                    self.set_queue(self.queue, None)
        elif topic == "queue":
            self.queue_heard += 1
            if isinstance(payload, dict):
                going = None if self.queue is None else self.queue.get("run")
                self.set_queue(payload, going)
        elif topic == "dropped":
            self.dropped += int(payload.get("count", 0)) if isinstance(payload, dict) else 0

    async def seed(self) -> None:
        """The buffer filled from the records file at start: a panel opened at once (or after the
        server process restarted) still shows the last seconds."""
        try:
            records = await self.backend.call("history", [HISTORY_STROKES])
        except RpcError as exc:
            log.warning("panel: history: %s", exc.message)
            return
        first = self.strokes[0][1][0] if self.strokes else None
        older = [compact(r) for r in records if first is None or r["cycle"] < first]
        older = older[-(HISTORY_STROKES - len(self.strokes)) :] if len(self.strokes) < HISTORY_STROKES else []
        # Sequence numbers below the live ones: a viewer's cursor (0 at open) is before them all.
        base = (self.strokes[0][0] if self.strokes else self.seq + 1) - len(older)
        rows = [(base + i, row) for i, row in enumerate(older)]
        if base < 1:  # renumber everything so that sequence numbers stay positive
            shift = 1 - base
            self.strokes = deque(((s + shift, r) for s, r in (*rows, *self.strokes)), maxlen=HISTORY_STROKES)
            self.seq += shift
        else:
            self.strokes.extendleft(reversed(rows))
        self.figures += 1

    async def refresh_status(self) -> None:
        """The daemon's status, asked at most every STATUS_EVERY_S (at once after a state change)."""
        heard = self.queue_heard
        try:
            status = await self.backend.call("status", [])
        except RpcError as exc:
            log.warning("panel: status: %s", exc.message)
            return
        self.status = {k: status.get(k) for k in _STATUS_KEYS}
        self.figures += 1
        self.status_at = time.monotonic()
        # Not over a notification heard while it was asked (the status may be the older); a daemon
        # from before the queue has none.
        if isinstance(status.get("queue"), dict) and heard == self.queue_heard:
            self.set_queue(status["queue"], status.get("run"))

    def set_queue(self, queue: dict[str, Any], run: dict[str, Any] | None) -> None:
        """The queue shown: a new object only when it changed (the ticker sends it when it is new)."""
        new = {"paused": queue.get("paused"), "current": queue.get("current"), "queued": queue.get("queued")}
        new["run"] = run
        if new != self.queue:
            self.queue = new
            self.figures += 1

    async def refresh_stats(self) -> None:
        """The current (or last) run's statistics, from the snapshot the server process keeps."""
        with contextlib.suppress(RpcError):
            self.stats = await self.backend.call("stats", [])
            self.figures += 1

    def strokes_after(self, seq: int) -> tuple[list[list[Any]], bool]:
        """The buffered strokes after `seq`, and whether some between were lost from the buffer."""
        if not self.strokes or self.strokes[-1][0] <= seq:
            return [], False
        first = self.strokes[0][0]
        if seq < first - 1:
            return [row for _, row in self.strokes], seq > 0
        # Numbered one by one: the new ones are the last `last - seq`, skipped to in C (a scan of
        # the 1,000 for each feed each tick was a tenth of the HTTP thread's time under a burst).
        new = self.strokes[-1][0] - seq
        return [row for _, row in itertools.islice(self.strokes, len(self.strokes) - new, None)], False

    def hello_text(self) -> tuple[str, int, Any, Any, Any]:
        """`hello()` as the JSON a feed is sent, with the stroke, statistics and state it is as of
        (the feed's cursor: the ticker sends what came after). Made at most every TICK_S and when
        the figures change, not for each feed: a burst of 200 feeds encoded the ~1,000 strokes
        once apiece, milliseconds each on the HTTP doors' loop, ahead of the panel's own estop.
        Returns (JSON, stroke, statistics, state, queue)."""
        now = time.monotonic()
        made = self._hello
        if made is None or made[0] != (self.figures, self.runs_version) or now - made[1] > TICK_S:
            text = json.dumps(self.hello(), separators=(",", ":"))
            made = self._hello = (
                (self.figures, self.runs_version),
                now,
                text,
                self.seq,
                self.stats,
                self.status,
                self.queue,
            )
        return made[2], made[3], made[4], made[5], made[6]

    def hello(self) -> dict[str, Any]:
        """What a panel gets when it opens: the state, the statistics, the strokes of the last seconds."""
        return {
            "type": "hello",
            "status": self.status,
            "stats": self.stats,
            "queue": self.queue,
            "strokes": [row for _, row in self.strokes],
            "runs_version": self.runs_version,
            "history_strokes": HISTORY_STROKES,
        }

    async def ticker(self) -> None:
        """Every TICK_S: each viewer gets what it has not seen, in one message, unless it is behind."""
        stats_at = 0.0
        while True:
            await asyncio.sleep(TICK_S)
            if not self.viewers:
                continue
            now = time.monotonic()
            if (self.status_stale or now - self.status_at > STATUS_EVERY_S) and (
                self._status_task is None or self._status_task.done()
            ):
                self.status_stale = False
                self._status_task = asyncio.create_task(self.refresh_status())
            if now - stats_at > 0.5:
                stats_at = now
                await self.refresh_stats()
            encoded: dict[tuple[int, bool, bool, bool, int], str] = {}
            for viewer in list(self.viewers):
                if viewer.busy():
                    continue
                fresh = bool(self.strokes) and self.strokes[-1][0] > viewer.seq
                send_stats = viewer.stats_sent is not self.stats
                send_status = viewer.status_sent is not self.status or send_stats
                send_queue = viewer.queue_sent is not self.queue
                if not fresh and not send_stats and not send_status and not send_queue:
                    continue
                key = (viewer.seq, send_stats, send_status, send_queue, self.runs_version)
                text = encoded.get(key)
                if text is None:  # the feeds opened together share one cursor: one encoding
                    rows, gap = self.strokes_after(viewer.seq)
                    msg: dict[str, Any] = {"type": "tick", "strokes": rows, "gap": gap}
                    msg["runs_version"] = self.runs_version
                    if send_stats:
                        msg["stats"] = self.stats
                    if send_status:
                        msg["status"] = self.status
                    if send_queue:
                        msg["queue"] = self.queue
                    text = encoded[key] = json.dumps(msg, separators=(",", ":"))
                viewer.seq = self.seq
                viewer.stats_sent = self.stats
                viewer.status_sent = self.status
                viewer.queue_sent = self.queue
                viewer.sending = asyncio.create_task(_send(viewer, text))

    # -- controls ------------------------------------------------------------------------------------
    def authorized(self, request: Asked) -> bool:
        """Whether the request carries the daemon's token, in its header or the cookie the URL's
        token was traded for (constant-time comparison)."""
        return any(
            self.token_ok(given)
            for given in (request.headers.get(TOKEN_HEADER, ""), request.cookies.get(TOKEN_COOKIE, ""))
        )

    def token_ok(self, given: str) -> bool:
        """Whether `given` is the daemon's token."""
        return (
            self.token is not None
            and bool(given)
            and hmac.compare_digest(given.encode(), self.token.encode())
        )

    def host_allowed(self, request: Asked) -> bool:
        """Whether the request's Host names this panel (loopback, or `[web] allowed_hosts`)."""
        return host_name(request.headers.get("Host", "")) in self.allowed_hosts

    async def feed_request(self, viewer: _Viewer, text: str) -> str:
        """The answer to a message a page sent on its live feed: `{"estop": ID}` only.

        The page's estop button sends it on the feed it holds open (a POST is its fallback): no
        connection to open, no request head to parse, and no place to wait at a full door. Only a
        feed opened with the token may; the answer is `{"estop": {"id": ID, "result": ...}}` or
        `{"estop": {"id": ID, "error": ..., "code": ...}}`.
        """
        try:
            msg = json.loads(text) if json_depth_ok(text.encode()) else None
        except ValueError:
            msg = None
        if not isinstance(msg, dict) or set(msg) != {"estop"} or not _small_id(msg["estop"]):
            return json.dumps({"error": FEED_TAKES})
        answer: dict[str, Any] = {"id": msg["estop"]}
        if not viewer.operator:
            answer.update(error=self.refusal(), code=None)
            return json.dumps({"estop": answer})
        try:
            answer["result"] = await self.backend.call("estop", [FEED_OWNER])
        except RpcError as exc:
            answer.update(error=exc.message, code=exc.code)
        self.status_stale = True
        return json.dumps({"estop": answer})

    def feed_refusal(self, operator: bool) -> str | None:
        """Why a live feed asked for now is refused (503), or None: it opens (an operator's in the
        place of the oldest read-only one when the feeds are full)."""
        for transport in [t for t in self.feeds_asked if t.is_closing()]:  # gone before their handler
            del self.feeds_asked[transport]
        asked_readonly = sum(1 for with_token in self.feeds_asked.values() if not with_token)
        if not operator and self.readonly_feeds + asked_readonly >= MAX_READONLY_PANELS:
            return f"too many read-only panels (max {MAX_READONLY_PANELS}); close one"
        full = self.feeds + len(self.feeds_asked) >= MAX_PANELS
        if full and (not operator or not any(not v.operator for v in self.viewers)):
            return f"too many open panels (max {MAX_PANELS}); close one"
        return None

    def control_answer(self, call: asyncio.Future[Any]) -> tuple[int, dict[str, Any]]:
        """A control's call, done -> (HTTP status, JSON body): its result, or the daemon's refusal."""
        try:
            result = call.result()
        except RpcError as exc:
            return _HTTP_OF_CODE.get(exc.code, 500), {"error": exc.message, "code": exc.code}
        self.status_stale = True
        return 200, {"ok": True, "result": result}

    # -- the express lane ----------------------------------------------------------------------------
    def express(self, transport: asyncio.BaseTransport, data: bytes) -> bytes | asyncio.Future[bytes] | None:
        """The door's express lane (web/express.py): a fresh connection's first read answered here
        when it is an estop POST with the token, or a live feed the feeds' cap refuses, by the
        checks and with the bodies of the routes below; None: aiohttp's, as any other request."""
        request = parse(data, MAX_BODY_BYTES)
        if request is None or not self.host_allowed(request) or not same_origin(request):
            return None
        if request.method == "POST" and request.path == ESTOP_PATH and self.authorized(request):
            try:
                method, params = control_call("estop", request.body)
            except (BadBody, RpcError):
                return None  # aiohttp's route says what is wrong with it
            call = asyncio.ensure_future(self.backend.call(method, params))
            if call.done():  # the estop socket answered at once: no step of the loop in between
                return self._estop_answer(call)
            answer: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
            call.add_done_callback(lambda done: answer.set_result(self._estop_answer(done)))
            return answer
        if request.method == "GET" and request.path == "/api/live":
            operator = self.authorized(request)
            if not operator and TOKEN_COOKIE in request.headers.get("Cookie", ""):
                return None  # a token cookie that is not the token, or one of two: aiohttp's to read
            refusal = self.feed_refusal(operator)
            if refusal is None:
                self.feeds_asked[transport] = operator
                return None
            return json_answer(503, {"error": refusal, "code": None})
        return None

    def _estop_answer(self, call: asyncio.Future[Any]) -> bytes:
        """The lane's whole HTTP answer to its estop call, done."""
        try:
            return json_answer(*self.control_answer(call))
        except (Exception, asyncio.CancelledError) as exc:  # not the daemon's refusal: a 500, as aiohttp's
            log.error("panel: estop failed: %r", exc)
            return json_answer(500, {"error": f"estop: {exc}", "code": None})

    def refusal(self) -> str:
        where = f" (it is in {self.token_file}, readable by the socket's group)" if self.token_file else ""
        return (
            "read-only: this panel was opened without the daemon's token; open the URL that"
            f" `usmswitchctl web-url` prints{where}"
        )


#: The estop's control: the express lane answers it, and the door lets its first read go first.
ESTOP_PATH = "/api/control/estop"
_ESTOP_HEAD = f"POST {ESTOP_PATH} ".encode()

_STATUS_KEYS = (
    "rig", "driver", "driver_ok", "state", "mode", "fault", "model", "order", "cycle",
    "target_on_ns", "target_off_ns", "open_delay_ns", "version", "uptime_ns", "scheduling",
)  # fmt: skip


def estop_post(first_read: bytes) -> bool:
    """Whether a connection's first read begins the estop's POST: the door handles it as it comes,
    before the first reads waiting their turn (web/door.py)."""
    return first_read.startswith(_ESTOP_HEAD)


def _small_id(value: object) -> bool:
    return (isinstance(value, int) and not isinstance(value, bool) and abs(value) < 2**53) or (
        isinstance(value, str) and len(value) <= 64
    )


async def _send(viewer: _Viewer, text: str) -> None:
    with contextlib.suppress(ConnectionError, RuntimeError, asyncio.CancelledError):
        await viewer.ws.send_str(text)


def _error(status: int, message: str, code: int | None = None) -> web.Response:
    return web.json_response({"error": message, "code": code}, status=status)


def control_call(name: str, raw: bytes) -> tuple[str, list[Any]]:
    """A control's body as read -> (socket method, params): BadBody when it is not a flat JSON
    object's text, RpcError(INVALID_PARAMS) when its fields are not the control's."""
    if not json_depth_ok(raw):
        raise BadBody(f"{name}: the body nests deeper than {MAX_JSON_DEPTH} (a control is a flat object)")
    try:
        body = json.loads(raw) if raw.strip() else {}
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise BadBody(f"{name}: the body is not JSON: {exc}") from None
    return control_params(name, body)


def same_origin(request: Asked) -> bool:
    """No Origin (a script, curl) or the page's own: a page of another site open in the same browser
    may not read the feed over WebSocket (which browsers let cross origins open) or post controls.
    The page's own is http (or https behind a TLS proxy) and the Host it was asked as."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    scheme, sep, host = origin.partition("://")
    return (
        bool(sep) and scheme in ("http", "https") and bool(host) and host == request.headers.get("Host", "")
    )


def host_name(host: str) -> str:
    """The name part of a Host header, lower case: `127.0.0.1:8790` -> `127.0.0.1`, `[::1]:80` -> `[::1]`."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[: host.find("]") + 1] if "]" in host else host
    return host.rpartition(":")[0] if host.count(":") == 1 else host


def json_depth_ok(raw: bytes, most: int = MAX_JSON_DEPTH) -> bool:
    """Whether a JSON text nests at most `most` deep (counted on its brackets outside strings,
    before json.loads recurses: 2,000 nested `[` were a RecursionError and a 500)."""
    depth = 0
    in_str = escaped = False
    for ch in raw:
        if in_str:
            if escaped:
                escaped = False
            elif ch == 0x5C:  # backslash
                escaped = True
            elif ch == 0x22:  # quote
                in_str = False
        elif ch == 0x22:
            in_str = True
        elif ch in (0x5B, 0x7B):  # [ {
            depth += 1
            if depth > most:
                return False
        elif ch in (0x5D, 0x7D):
            depth -= 1
    return True


async def _no_icon(request: web.Request) -> web.Response:
    return web.Response(status=204)


def make_app(panel: Panel, door: Door | None = None) -> web.Application:
    """The panel's routes: the page and its assets, the live feed, the runs, the controls."""
    app = web.Application(client_max_size=MAX_BODY_BYTES)
    static = resources.files("usmswitch.web") / "static"

    async def index(request: web.Request) -> web.StreamResponse:
        if "token" in request.query:
            # The URL's token traded for a cookie, then a clean URL: the token stays out of the
            # history, caches, Referer headers and proxies' logs (Jupyter's way). A wrong token is
            # dropped from the URL too; the page is then read-only and says how to get the token.
            rest = [(k, v) for k, v in request.query.items() if k != "token"]
            clean = request.rel_url.with_query(rest).path_qs if rest else request.path
            resp = web.HTTPSeeOther(location=clean, headers={"Cache-Control": "no-store"})
            if panel.token_ok(request.query["token"]):
                resp.set_cookie(
                    TOKEN_COOKIE, request.query["token"], httponly=True, samesite="Strict", path="/"
                )
            return resp
        return web.Response(
            body=(static / "index.html").read_bytes(),
            content_type="text/html",
            charset="utf-8",
            headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"},
        )

    async def asset(request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        kind = next((t for ext, t in _STATIC_TYPES.items() if name.endswith(ext)), None)
        item = static / name
        if kind is None or "/" in name or name.startswith(".") or not item.is_file():
            return _error(404, f"no asset {name!r}")
        return web.Response(
            body=item.read_bytes(),
            content_type=kind,
            charset="utf-8",
            headers={"Cache-Control": "max-age=3600"},
        )

    async def session(request: web.Request) -> web.StreamResponse:
        ok = panel.authorized(request)
        return web.json_response({"control": ok, "message": None if ok else panel.refusal()})

    async def live(request: web.Request) -> web.StreamResponse:
        if request.transport is not None:
            panel.feeds_asked.pop(request.transport, None)  # its handler counts it from here on
        if not same_origin(request):
            return _error(403, "the live feed is for the panel's own page (another site's Origin)")
        operator = panel.authorized(request)
        refusal = panel.feed_refusal(operator)
        if refusal is not None:
            return _error(503, refusal)
        if panel.feeds >= MAX_PANELS:  # full: this operator's feed takes the oldest read-only one's place
            oldest = min((v for v in panel.viewers if not v.operator), key=lambda v: v.opened)
            panel.viewers.discard(oldest)
            closing = asyncio.create_task(
                oldest.ws.close(code=1013, message=b"replaced: the feeds are full and an operator opened one")
            )
            panel.closing.add(closing)
            closing.add_done_callback(panel.closing.discard)
        # Counted before the first await: a burst cannot pass the cap between the check and the count.
        panel.feeds += 1
        panel.readonly_feeds += not operator
        try:
            ws = web.WebSocketResponse(heartbeat=30.0, max_msg_size=4096)
            await ws.prepare(request)
            if panel.status is None or time.monotonic() - panel.status_at > STATUS_EVERY_S:
                await panel.refresh_status()
            if panel.stats is None:
                await panel.refresh_stats()
            viewer = _Viewer(ws, request.transport, operator)  # type: ignore[arg-type]
            hello, viewer.seq, viewer.stats_sent, viewer.status_sent, viewer.queue_sent = panel.hello_text()
            await ws.send_str(hello)
            panel.viewers.add(viewer)
            try:
                async for msg in ws:  # reading keeps pings answered; the page sends only its estop
                    if msg.type == WSMsgType.ERROR:
                        break
                    if msg.type == WSMsgType.TEXT:
                        answer = await panel.feed_request(viewer, msg.data)
                        with contextlib.suppress(ConnectionError):  # the page went meanwhile
                            await ws.send_str(answer)
            finally:
                panel.viewers.discard(viewer)
            return ws
        finally:
            panel.feeds -= 1
            panel.readonly_feeds -= not operator

    async def runs(request: web.Request) -> web.StreamResponse:
        try:
            listed = await panel.backend.call("runs", [RUNS_SHOWN])
            stats = await panel.backend.call("stats", [])
        except RpcError as exc:
            return _error(_HTTP_OF_CODE.get(exc.code, 500), exc.message, exc.code)
        current = (stats or {}).get("run") or {}
        out = []
        for run in listed:
            rid = run["run_id"]
            if run.get("end_reason") is None and current.get("run_id") == rid:
                run["stats"] = stats
            elif run.get("end_reason") is not None:
                if rid not in panel.run_stats:
                    with contextlib.suppress(RpcError):
                        panel.run_stats[rid] = await panel.backend.call("stats", [rid, None, None])
                    while len(panel.run_stats) > 4 * RUNS_SHOWN:
                        panel.run_stats.pop(min(panel.run_stats))
                run["stats"] = panel.run_stats.get(rid)
            out.append(run)
        return web.json_response({"runs": out})

    async def run_csv(request: web.Request) -> web.StreamResponse:
        text = request.match_info["run"]
        if not text.isdigit() or not 0 < int(text) < 2**62:
            return _error(400, f"run must be a run id (1, 2, ...), got {text!r}")
        run_id = int(text)
        # Asked first, so an unknown run is a 404 before any byte of the file goes out.
        try:
            listed = await panel.backend.call("runs", [1])
        except RpcError as exc:
            return _error(_HTTP_OF_CODE.get(exc.code, 500), exc.message, exc.code)
        last = listed[-1]["run_id"] if listed else 0
        if run_id > last:
            have = f"runs are 1..{last}" if last else "no run has been recorded yet"
            return _error(404, f"no run {run_id} ({have})")
        resp = web.StreamResponse(
            headers={
                "Content-Type": "text/csv; charset=utf-8",
                "Content-Disposition": f'attachment; filename="run-{run_id}.csv"',
            }
        )
        await resp.prepare(request)
        try:
            await panel.backend.export_csv(run_id, resp.write)
        except RpcError as exc:  # the headers are out: say so in the body, as the last line
            await resp.write(f"# export failed: {exc.message}\n".encode())
        await resp.write_eof()
        return resp

    async def control(request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        if not same_origin(request):
            return _error(403, "a control comes from the panel's own page, not another site's")
        if not panel.authorized(request):
            return _error(403, panel.refusal())
        if name not in CONTROLS:
            return _error(400, f"unknown control {name[:40]!r}; known: {', '.join(CONTROLS)}")
        try:
            method, params = control_call(name, await request.read())
        except BadBody as exc:
            return _error(400, str(exc))
        except RpcError as exc:
            return _error(_HTTP_OF_CODE.get(exc.code, 500), exc.message, exc.code)
        call = asyncio.ensure_future(panel.backend.call(method, params))
        await asyncio.wait((call,))
        status, body = panel.control_answer(call)
        return web.json_response(body, status=status)

    async def too_large(request: web.Request, handler: Any) -> web.StreamResponse:
        try:
            return await handler(request)
        except web.HTTPRequestEntityTooLarge:
            return _error(413, f"a control's body is at most {MAX_BODY_BYTES} bytes")

    async def known_host(request: web.Request, handler: Any) -> web.StreamResponse:
        # Before anything else: a page asked for under another name is another site's (rebinding).
        if not panel.host_allowed(request):
            return _error(
                403,
                f"this panel answers to {', '.join(sorted(panel.allowed_hosts))};"
                " add the name to [web] allowed_hosts to open it under another",
            )
        return await handler(request)  # type: ignore[no-any-return]

    if door is not None:
        app.middlewares.append(door.middleware())
    app.middlewares.append(web.middleware(known_host))
    app.middlewares.append(web.middleware(too_large))
    app.router.add_get("/", index)
    app.router.add_get("/favicon.ico", _no_icon)
    app.router.add_get("/static/{name}", asset)
    app.router.add_get("/api/session", session)
    app.router.add_get("/api/live", live)
    app.router.add_get("/api/runs", runs)
    app.router.add_get("/api/runs/{run}.csv", run_csv)
    app.router.add_post("/api/control/{name}", control)
    return app


class PanelServer:
    """The running panel: its aiohttp runner and ticker; `close()` ends both."""

    def __init__(
        self,
        runner: web.AppRunner,
        ticker: asyncio.Task[None],
        panel: Panel,
        server: asyncio.Server,
        door: Door,
    ) -> None:
        self.runner = runner
        self.ticker = ticker
        self.panel = panel
        self.server = server
        self.door = door

    def close(self) -> None:
        """Stop serving (from the event loop's thread); open feeds are dropped with the process."""
        self.ticker.cancel()
        self.door.close()
        self.server.close()
        asyncio.get_running_loop().create_task(self.runner.cleanup())


async def serve_panel(
    sock: socket.socket,
    backend: Backend,
    token: str | None,
    token_file: str | None = None,
    allowed_hosts: frozenset[str] = frozenset(),
) -> PanelServer:
    """Serve the panel on a listening TCP socket the daemon bound (the server process's event loop),
    behind its door's budget (web/door.py)."""
    panel = Panel(backend, token, token_file, allowed_hosts)
    door = Door(
        "panel", MAX_CONNECTIONS, HEAD_TIMEOUT_S, IDLE_TIMEOUT_S, express=panel.express, urgent=estop_post
    )
    runner = web.AppRunner(
        make_app(panel, door),
        access_log=None,
        handle_signals=False,
        keepalive_timeout=IDLE_TIMEOUT_S,
        logger=QuietLog("panel"),
    )
    await runner.setup()
    assert runner.server is not None
    server = await asyncio.get_running_loop().create_server(
        door.protocol_factory(runner.server), sock=sock, backlog=HTTP_BACKLOG
    )
    panel.seeding = asyncio.create_task(panel.seed())
    return PanelServer(runner, asyncio.create_task(panel.ticker()), panel, server, door)
