"""The HTTP doors of the server process (the browser panel, /metrics), each on an event loop of its own.

The Unix and TCP doors' event loop (server/rpc_process.py) must never have HTTP work queued ahead of
an estop: a burst of 200 live-feed handshakes to the panel put some 200 requests' parsing, routing
and WebSocket set-up in that loop's one queue, and a main-socket estop waited behind them (45 ms at
p99, `make bench BENCH=abuse`). Here the panel runs on a thread of its own, one SCHED_FIFO step
below that loop's thread when it is real-time (the daemon raises that thread from outside, so this
one follows it, looked at every FOLLOW_S), SCHED_OTHER when it is not; /metrics on another, a step
below the panel's: the panel's estop (its live feed's, its POST) never waits behind a scrape's
rendering (4 scrapers hammering /metrics put the panel POST's p99 at 7.0-7.2 ms beside 3.3 idle,
`make bench BENCH=abuse` with the CPUs polling, stop 51). The threads share the GIL: a higher one
takes it from a lower one within the switch interval (0.2 ms in the server process).

The panel reaches the server's state through `CrossBackend`: each call is handed to the event
loop's thread and its reply handed back, each notification likewise, so every socket method the
panel uses still goes through the one dispatcher (`_PanelConn`) with its checks and bounds.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import socket
import threading
from collections.abc import Awaitable, Callable
from typing import Any

from usmswitch.protocol.wire import RpcError
from usmswitch.runtime.realtime import name_thread
from usmswitch.server.estop_link import KEEP_WARM_S, EstopLink, EstopUnreached

log = logging.getLogger("usmswitch.rpc")

#: How often this thread looks at the event loop's thread's scheduling, to follow it.
FOLLOW_S = 0.5
#: The panel's thread's name in `ps -L` and /proc (prctl PR_SET_NAME, 15 bytes at most).
THREAD_NAME = "rpc-http"
#: The metrics page's.
METRICS_THREAD_NAME = "rpc-metrics"


class CrossBackend:
    """The panel's Backend (web/panel.py) on the HTTP doors' loop over one on the event loop's
    (`_PanelConn`): calls, notifications and exports each cross between the two threads."""

    def __init__(
        self,
        inner: Any,
        home: asyncio.AbstractEventLoop,
        here: asyncio.AbstractEventLoop,
        estop: EstopLink | None = None,
    ) -> None:
        self.inner = inner
        self.home = home  # the Unix and TCP doors' loop, where `inner` lives
        self.here = here
        self.estop = estop  # the estop socket, when the daemon has one (server/estop_link.py)

    def call(self, method: str, params: list[Any]) -> asyncio.Future[Any]:
        """A socket method, dispatched on the event loop's thread; the reply resolves here. An
        estop goes by the estop socket first, at once, not through that thread."""
        if method == "estop" and self.estop is not None:
            done: asyncio.Future[Any] = self.here.create_future()
            try:
                done.set_result(self.estop.call(params))
            except RpcError as exc:
                done.set_exception(exc)
            except EstopUnreached as exc:
                log.warning("rpc: panel estop by the event loop: no answer on the estop socket (%s)", exc)
                return self._via_home(method, params)
            return done
        return self._via_home(method, params)

    def _via_home(self, method: str, params: list[Any]) -> asyncio.Future[Any]:
        fut: asyncio.Future[Any] = self.here.create_future()

        def settle(done: asyncio.Future[Any]) -> None:
            if fut.done():
                return
            if done.cancelled():
                fut.cancel()
            elif (exc := done.exception()) is not None:
                fut.set_exception(exc)
            else:
                fut.set_result(done.result())

        def start() -> None:
            try:
                inner = self.inner.call(method, params)
            except Exception as exc:  # a bug in dispatch: the panel's caller sees it, not the loop
                failed = self.home.create_future()
                failed.set_exception(exc)
                inner = failed
            inner.add_done_callback(lambda done: self._hand_back(settle, done))

        self.home.call_soon_threadsafe(start)
        return fut

    def _hand_back(self, settle: Callable[[asyncio.Future[Any]], None], done: asyncio.Future[Any]) -> None:
        with contextlib.suppress(RuntimeError):  # this loop closed first, at the end
            self.here.call_soon_threadsafe(settle, done)

    def listen(self, listener: Callable[[str, Any], None]) -> None:
        """`listener(topic, payload)` on this loop for each notification the event loop's gets."""

        def handed(topic: str, payload: Any) -> None:
            with contextlib.suppress(RuntimeError):  # this loop closed first, at the end
                self.here.call_soon_threadsafe(listener, topic, payload)

        self.home.call_soon_threadsafe(self.inner.listen, handed)

    def export_csv(self, run_id: int, write: Callable[[bytes], Awaitable[None]]) -> Awaitable[int]:
        """A run as CSV: read by a worker thread, written from this loop (`inner` uses the running loop)."""
        return self.inner.export_csv(run_id, write)  # type: ignore[no-any-return]


class HttpDoors:
    """HTTP listeners served by a thread of their own (`start`, then `close`), `below` SCHED_FIFO
    steps under the event loop's thread when that is real-time."""

    def __init__(
        self,
        loop_factory: Callable[[], asyncio.AbstractEventLoop] | None,
        name: str = THREAD_NAME,
        below: int = 1,
    ) -> None:
        self.loop_factory = loop_factory or asyncio.new_event_loop
        self.name = name
        self.below = below
        self.loop: asyncio.AbstractEventLoop | None = None
        self.thread: threading.Thread | None = None
        self.servers: list[Any] = []
        self.leader_tid = threading.get_native_id()  # the event loop's thread, followed
        self.refused = False  # a priority refused (said once)

    async def start(self, setup: Callable[[asyncio.AbstractEventLoop], Awaitable[list[Any]]]) -> None:
        """Start the thread and, on its loop, `setup(loop)` (it returns the servers to close at the
        end); returns once they listen, or raises what setting them up raised."""
        ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self.thread = threading.Thread(target=self._run, args=(setup, ready), name=self.name, daemon=True)
        self.thread.start()
        await asyncio.wrap_future(ready)

    def _run(
        self,
        setup: Callable[[asyncio.AbstractEventLoop], Awaitable[list[Any]]],
        ready: concurrent.futures.Future[None],
    ) -> None:
        name_thread(self.name)
        self.follow()
        loop = self.loop = self.loop_factory()
        asyncio.set_event_loop(loop)
        try:
            self.servers = loop.run_until_complete(setup(loop))
        except BaseException as exc:
            ready.set_exception(exc)
            loop.close()
            return
        ready.set_result(None)
        follower = loop.create_task(self._follow_forever())
        try:
            loop.run_forever()
        finally:
            follower.cancel()
            with contextlib.suppress(Exception):
                loop.run_until_complete(self._close_servers())
            loop.close()

    async def _close_servers(self) -> None:
        for server in self.servers:
            with contextlib.suppress(Exception):
                server.close()
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def follow(self) -> None:
        """`below` SCHED_FIFO steps under the event loop's thread when it is real-time (yet above
        the worker threads' FIFO 1), SCHED_OTHER when it is not."""
        try:
            policy = os.sched_getscheduler(self.leader_tid)
            leader = os.sched_getparam(self.leader_tid).sched_priority if policy == os.SCHED_FIFO else 0
            now = os.sched_getparam(0).sched_priority if os.sched_getscheduler(0) == os.SCHED_FIFO else 0
        except OSError:  # the leader gone: the process is ending
            return
        want = max(leader - self.below, min(leader, 2))
        if want == now:
            return
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO if want else os.SCHED_OTHER, os.sched_param(want))
        except OSError as exc:
            if not self.refused:
                log.warning("rpc: thread %s stays as it is (SCHED_FIFO %d refused: %s)", self.name, want, exc)
            self.refused = True

    async def _follow_forever(self) -> None:
        while True:
            await asyncio.sleep(FOLLOW_S)
            self.follow()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop serving and end the thread (from the event loop's thread)."""
        loop, thread = self.loop, self.thread
        if loop is not None and thread is not None and thread.is_alive():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(loop.stop)
            thread.join(timeout_s)


class _KeptWarm:
    """The panel's estop link, its connection opened soon after the start (the daemon's estop
    thread may start after this thread) and pinged every KEEP_WARM_S, so that an estop finds it
    open; `close` at the end."""

    def __init__(self, link: EstopLink, loop: asyncio.AbstractEventLoop) -> None:
        self.link = link
        self.task = loop.create_task(self._ping())

    async def _ping(self) -> None:
        delay = 1.0
        while True:
            await asyncio.sleep(delay)
            self.link.keep_warm()
            delay = KEEP_WARM_S

    def close(self) -> None:
        self.task.cancel()
        self.link.close()


async def serve_http(
    listeners: list[tuple[socket.socket, str]],
    panel_conn: Any,
    snapshot: Callable[[], tuple[dict[str, bytes], dict[str, int]]],
    cfg: dict[str, Any],
    loop_factory: Callable[[], asyncio.AbstractEventLoop] | None,
    executor: Callable[[], concurrent.futures.Executor],
) -> list[HttpDoors]:
    """Serve the HTTP listeners (kind "metrics" or "web"): the panel on a thread of its own, /metrics
    on another a step below it; `panel_conn` is the panel's dispatcher on the calling (event)
    loop, `snapshot()` what the metrics page is made of, `executor()` an HTTP loop's default
    executor (its threads below it)."""
    home = asyncio.get_running_loop()
    panel = [sock for sock, kind in listeners if kind != "metrics"]
    metrics = [sock for sock, kind in listeners if kind == "metrics"]

    async def serve_panels(here: asyncio.AbstractEventLoop) -> list[Any]:
        from usmswitch.web.panel import serve_panel  # aiohttp: only here

        here.set_default_executor(executor())
        servers: list[Any] = []
        for sock in panel:
            hosts = frozenset(cfg.get("web_allowed_hosts", ()))
            estop = cfg.get("estop_socket")
            link = None if estop is None else EstopLink(estop)
            backend = CrossBackend(panel_conn, home, here, link)
            servers.append(await serve_panel(sock, backend, cfg["web_token"], cfg["web_token_file"], hosts))
            if link is not None:
                servers.append(_KeptWarm(link, here))
        return servers

    async def serve_pages(here: asyncio.AbstractEventLoop) -> list[Any]:
        from usmswitch.web.metrics_page import serve_metrics  # aiohttp, prometheus_client: only here

        here.set_default_executor(executor())
        return [await serve_metrics(sock, snapshot) for sock in metrics]

    started = []
    for socks, name, below, setup in (
        (panel, THREAD_NAME, 1, serve_panels),
        (metrics, METRICS_THREAD_NAME, 2, serve_pages),
    ):
        if socks:
            doors = HttpDoors(loop_factory, name, below)
            await doors.start(setup)
            started.append(doors)
    return started
