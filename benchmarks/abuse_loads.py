"""The abusive loads of `make bench BENCH=abuse` (benchmarks/bench_abuse.py measures under them).

Each load is the body of a process, `body(path, stop, **kw)`, that hammers the daemon at the Unix
socket `path` (or the doors beside it) until the multiprocessing Event `stop` is set. `LOADS` names
them in the bench's order with their process counts; `NEEDS` says which addresses the daemon serves
(`url`, `web_url`, `tcp`) and which shared counter (`edits`) a body takes, filled in by the bench
once the daemon is up.
"""

from __future__ import annotations

import contextlib
import os
import random
import socket
import time
from collections.abc import Callable
from typing import Any

import msgpack

from usmswitch.client import Client, ConnectionClosed, RpcError
from usmswitch.protocol.wire import estop_socket_path

MS = 1_000_000


# -- loads, each the body of a process that runs until `stop` is set ----------------------------------
def connect_unix(path: str) -> socket.socket:
    """A connected Unix stream socket to `path` (the loads' and the estopper's raw connections)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(path)
    return s


def _frames(method: str, params: list[Any], n: int) -> bytes:
    return b"".join(msgpack.packb([0, i, method, params]) for i in range(n))


def load_stats(path: str, stop: Any) -> None:
    with Client(path) as c:
        while not stop.is_set():
            c.stats()


def load_unread_history(path: str, stop: Any, conns: int = 1) -> None:
    try:
        socks = [connect_unix(path) for _ in range(conns)]
    except OSError:
        return  # the daemon is gone (the SIGTERM row: a loader started after its exit)
    for s in socks:
        s.sendall(_frames("history", [10_000], 32))
    stop.wait()


def load_exports(path: str, stop: Any) -> None:
    try:
        c = Client(path, timeout=60)
    except OSError:
        return  # the daemon is gone (the SIGTERM row: a loader started after its exit)
    with c:
        while not stop.is_set():
            try:
                c.history(10_000)
            except (ConnectionClosed, FileNotFoundError, ConnectionRefusedError):
                return  # the daemon went (the SIGTERM row ends it under this load; its socket too)
            except (OSError, RpcError):
                if stop.is_set():
                    return  # the load ended mid-call
                raise


def load_set_target(path: str, stop: Any) -> None:
    s = connect_unix(path)
    unpacker = msgpack.Unpacker()
    k = 0
    while not stop.is_set():
        k += 1
        s.sendall(_frames("set_target", [12 * MS + 1000 * (k % 2)], 32))
        got = 0
        while got < 32:
            unpacker.feed(s.recv(65_536))
            got += sum(1 for _ in unpacker)


def load_connection_flood(path: str, stop: Any) -> None:
    held: list[socket.socket] = []
    while not stop.is_set():
        while len(held) < 600:
            try:
                held.append(connect_unix(path))
            except OSError:
                break
        time.sleep(0.05)
        held = _renew(held)  # refused ones were closed by the server: open them again


def load_one_byte(path: str, stop: Any) -> None:
    """32 connections on each socket that send one byte of a request and then nothing, renewed."""
    targets = (path, str(estop_socket_path(path)))
    held: list[socket.socket] = []
    while not stop.is_set():
        for target in targets:
            while sum(1 for s in held if s.getpeername() == target) < 32:
                try:
                    s = connect_unix(target)
                    s.sendall(b"\x94")
                    held.append(s)
                except OSError:
                    break
        time.sleep(0.05)
        held = _renew(held)


def _http_response(s: socket.socket, buf: bytes) -> bytes:
    """Read one HTTP response (head and Content-Length body) from `s`; returns what follows it."""
    while b"\r\n\r\n" not in buf:
        buf += s.recv(65_536)
    head, _, rest = buf.partition(b"\r\n\r\n")
    length = int(head.lower().split(b"content-length:")[1].split(b"\r\n")[0])
    while len(rest) < length:
        rest += s.recv(65_536)
    return rest[length:]


def load_scrapes(path: str, stop: Any, url: str = "", keep_alive: bool = True) -> None:
    """GET /metrics as fast as the page answers, reading every byte: over one kept-alive
    connection, as Prometheus scrapes, or a new connection per scrape."""
    host, _, port = url.split("/")[2].rpartition(":")
    request = f"GET /metrics HTTP/1.1\r\nHost: {host}\r\nAccept: text/plain\r\n\r\n".encode()
    s = None
    buf = b""
    while not stop.is_set():
        if s is None:
            s = socket.create_connection((host, int(port)), timeout=10)
        s.sendall(request)
        buf = _http_response(s, buf)
        if not keep_alive:
            s.close()
            s, buf = None, b""


def load_panel(path: str, stop: Any, web_url: str = "") -> None:
    """One open browser panel: the page and its assets, the runs list, then the live feed read as
    it comes (every message decoded, as the page does), the runs list again every 5 s."""
    import asyncio
    import json

    import aiohttp

    async def panel() -> None:
        async with aiohttp.ClientSession() as http:
            for part in ("", "static/panel.js", "static/uPlot.iife.min.js", "api/session", "api/runs"):
                async with http.get(web_url + part) as resp:
                    await resp.read()
            async with http.ws_connect(web_url + "api/live") as ws:
                next_runs = time.monotonic() + 5
                while not stop.is_set():
                    try:
                        msg = await ws.receive(timeout=0.5)
                    except TimeoutError:
                        continue
                    if msg.type != aiohttp.WSMsgType.TEXT:
                        return
                    json.loads(msg.data)
                    if time.monotonic() > next_runs:
                        next_runs += 5
                        async with http.get(web_url + "api/runs") as resp:
                            await resp.read()

    asyncio.run(panel())


# -- issue 35's loads: the doors held ------------------------------------------------------------------
def _renew(held: list[socket.socket]) -> list[socket.socket]:
    """The connections the server has not closed; the closed ones are closed here too."""
    alive = []
    for s in held:
        s.setblocking(False)
        try:
            closed = s.recv(1 << 16) == b""
        except BlockingIOError:
            closed = False
        except OSError:
            closed = True
        if closed:
            s.close()
        else:
            alive.append(s)
    return alive


def load_hold_every_slot(path: str, stop: Any) -> None:
    """64 subscribed Unix connections and 16 estop-socket holders (each answered a ping), renewed
    when shed: issue 35's item 2."""
    held: list[socket.socket] = []
    urgent = str(estop_socket_path(path))
    while not stop.is_set():
        counts = {path: 0, urgent: 0}
        for s in held:
            counts[s.getpeername()] += 1
        for target, want, method, params in (
            (path, 64, "subscribe", [["stroke", "state"]]),
            (urgent, 16, "ping", []),
        ):
            for _ in range(want - counts[target]):
                try:
                    s = connect_unix(target)
                    s.sendall(msgpack.packb([0, 1, method, params]))
                    s.recv(65_536)
                    held.append(s)
                except OSError:
                    break
        time.sleep(0.2)
        held = _renew(held)
    for s in held:
        s.close()


def load_half_open(path: str, stop: Any, web_url: str = "", n: int = 1100) -> None:
    """1,100 connections to the panel's port that send nothing, renewed as they are shed: item 4."""
    host, _, port = web_url.split("/")[2].rpartition(":")
    held: list[socket.socket] = []
    while not stop.is_set():
        while len(held) < n and not stop.is_set():
            try:
                held.append(socket.create_connection((host, int(port)), timeout=5))
            except OSError:
                break
        time.sleep(0.2)
        held = _renew(held)
    for s in held:
        s.close()


def load_slowloris(path: str, stop: Any, web_url: str = "", url: str = "") -> None:
    """10 connections to the panel and 17 to /metrics dripping a byte of a request head every
    second, renewed when closed: items 4 and 6."""
    targets = []
    for u, n in ((web_url, 10), (url, 17)):
        host, _, port = u.split("/")[2].rpartition(":")
        targets += [(host, int(port))] * n
    conns: list[socket.socket | None] = [None] * len(targets)
    while not stop.is_set():
        for i, target in enumerate(targets):
            s = conns[i]
            try:
                if s is None:
                    s = conns[i] = socket.create_connection(target, timeout=5)
                s.sendall(b"G")
            except OSError:
                if s is not None:
                    s.close()
                conns[i] = None
        time.sleep(1.0)


def load_bad_http(path: str, stop: Any, web_url: str = "", url: str = "") -> None:
    """Malformed HTTP requests to both doors as fast as they are answered: item 9."""
    bad = b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nno colon here\r\n\r\n"
    addrs = []
    for u in (web_url, url):
        host, _, port = u.split("/")[2].rpartition(":")
        addrs.append((host, int(port)))
    k = 0
    while not stop.is_set():
        k += 1
        with contextlib.suppress(OSError), socket.create_connection(addrs[k % 2], timeout=5) as s:
            s.sendall(bad)
            while s.recv(65_536):
                pass


def load_feed_bursts(path: str, stop: Any, web_url: str = "") -> None:
    """Bursts of 200 live feeds opened at once, held 2 s, closed: item 5."""
    import asyncio

    import aiohttp

    async def bursts() -> None:
        async with aiohttp.ClientSession() as http:
            while not stop.is_set():

                async def one() -> Any:
                    try:
                        return await http.ws_connect(web_url.replace("http://", "ws://") + "api/live")
                    except aiohttp.ClientError:
                        return None

                feeds = await asyncio.gather(*(one() for _ in range(200)))
                await asyncio.sleep(2.0)
                for ws in feeds:
                    if ws is not None:
                        await ws.close()

    asyncio.run(bursts())


def load_tcp_guessing(path: str, stop: Any, tcp: str = "") -> None:
    """Wrong TCP tokens as fast as they are answered, and 8 silent connections renewed: items 8, 12.
    From 127.0.0.2, another peer than the operator's 127.0.0.1: the back-off is per address, and a
    client on the guesser's own address shares its wait (docs/protocol.md)."""
    host, _, port = tcp.rpartition(":")
    src = ("127.0.0.2", 0)
    silent: list[socket.socket] = []
    k = 0
    while not stop.is_set():
        while len(silent) < 8:
            try:
                silent.append(socket.create_connection((host, int(port)), timeout=5, source_address=src))
            except OSError:
                break
        k += 1
        with (
            contextlib.suppress(OSError),
            socket.create_connection((host, int(port)), timeout=5, source_address=src) as s,
        ):
            s.sendall(msgpack.packb([0, 1, "auth", [f"guess-{k:016d}"]]))
            while s.recv(65_536):
                pass
        silent = _renew(silent)


# -- issue 38's load: the queue of runs edited ---------------------------------------------------------
def load_queue_edits(path: str, stop: Any, edits: Any = None, share: int = 25) -> None:
    """One of the clients that keep a queue of runs edited: `share` runs of its own queued (4 x 25:
    100), then, as fast as the daemon answers, one of them re-prioritised, or cancelled and another
    submitted in its place, or a run's label and notes edited (the run going, or an earlier one).
    Each edit answered (submit, priority, cancel, notes) adds one to the shared counter `edits`; at
    `stop` it cancels what it queued.

    The bench keeps its own run going with `start_cycling [take_over]` after each of its estops'
    `reset_fault` (Estopper.resume). A queued run never ends that run, but the reset lets the queue
    start its head (a person's reset, docs/protocol.md), which the bench's take-over would then
    end, one entry a reset. So the queue is **paused** first (`queue_pause [true]`, by each process
    before its first submit): nothing queued starts, the window's run is the bench's all along, and
    the queue is left paused and empty. The entries are submitted with `submit` (Client.submit_entry:
    Client.submit is the same call with subscriptions to follow the run, which nothing here reads).
    """
    rng = random.Random(os.getpid())
    k = 0  # calls answered

    def done() -> None:
        nonlocal k
        k += 1
        if edits is not None:
            with edits.get_lock():
                edits.value += 1

    with Client(path, timeout=30) as c:
        c.queue_pause(operator=True)
        mine: list[int] = []

        def submit() -> None:
            entry = c.submit_entry(
                period=f"{rng.choice((15, 20, 30))}ms",
                count=rng.randint(10, 5000),
                label=f"sweep-{rng.randrange(20)}",
                notes=f"queued by pid {os.getpid()}, edit {k}: " + "x" * rng.randrange(400),
                priority=rng.randint(-1000, 1000),
            )
            mine.append(entry["entry"])
            done()

        runs: list[int] = []
        annotated = 0
        while len(mine) < share and not stop.is_set():
            submit()
        while not stop.is_set():
            op = rng.randrange(3)
            if op == 0:
                c.queue_priority(rng.choice(mine), rng.randint(-1000, 1000))
                done()
            elif op == 1:  # a re-submit: one cancelled, another in its place
                c.queue_cancel(mine.pop(rng.randrange(len(mine))))
                done()
                submit()
            else:
                if annotated % 20 == 0:  # the bench's runs (one an estop); the daemon's own is not ours
                    runs = [r["run_id"] for r in c.runs(50) if r["settings"].get("owner") != "autostart"]
                annotated += 1
                if runs:  # the latest (the run going, mostly) or an earlier one
                    run = runs[-1] if rng.random() < 0.5 else rng.choice(runs)
                    c.annotate_run(run, f"edit {k} by pid {os.getpid()}", label=f"abuse-{k % 7}")
                    done()
        for entry in mine:
            with contextlib.suppress(RpcError):
                c.queue_cancel(entry)


LOADS: list[tuple[str, Callable[..., None] | None, int, dict[str, Any]]] = [
    ("idle", load_stats, 0, {}),
    ("8 clients hammering stats", load_stats, 8, {}),
    ("history 10000 x32 pipelined, unread", load_unread_history, 1, {}),
    ("4 x 32 history 10000, unread", load_unread_history, 1, {"conns": 4}),
    ("8 x 32 history 10000, unread", load_unread_history, 1, {"conns": 8}),
    ("10 export clients (history 10000)", load_exports, 10, {}),
    ("32 set_target pipelined, repeated", load_set_target, 1, {}),
    ("600 connections, renewed", load_connection_flood, 1, {}),
    ("32 one-byte connections per socket", load_one_byte, 1, {}),
    # The url is filled in at start.
    ("4 Prometheus scrapers hammering /metrics", load_scrapes, 4, {}),
    ("4 scrapers hammering /metrics, a connection each", load_scrapes, 4, {"keep_alive": False}),
    # The web_url is filled in at start.
    ("10 open panels (live feed, runs)", load_panel, 10, {}),
    # Issue 35 (web_url, url and tcp filled in at start).
    ("64 subscribed + 16 estop holders", load_hold_every_slot, 1, {}),
    ("1,100 half-open panel connections", load_half_open, 1, {}),
    ("slowloris: 10 on the panel, 17 on /metrics", load_slowloris, 1, {}),
    ("bad HTTP requests to both doors", load_bad_http, 2, {}),
    ("live feeds in bursts of 200", load_feed_bursts, 1, {}),
    ("TCP: token guessing and 8 silent", load_tcp_guessing, 1, {}),
    # Issue 38 (edits filled in at start).
    ("a queue of 100 runs, edited by 4 clients", load_queue_edits, 4, {"share": 25}),
]
#: The loads whose bodies take each address the daemon serves, or the shared counter (filled in at start).
NEEDS = {
    load_scrapes: ("url",),
    load_panel: ("web_url",),
    load_half_open: ("web_url",),
    load_slowloris: ("web_url", "url"),
    load_bad_http: ("web_url", "url"),
    load_feed_bursts: ("web_url",),
    load_tcp_guessing: ("tcp",),
    load_queue_edits: ("edits",),
}
