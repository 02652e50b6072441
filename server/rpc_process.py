"""The socket server process (`python -m usmswitch.server.rpc_process`), spawned by `RpcServer`.

It serves the Unix and TCP sockets the daemon bound: decodes, validates and bounds every request,
answers ping/auth/subscribe, `stats` from the daemon's snapshots (finished here) and `history` from
the records file, fans out notifications, and forwards the other calls over its channel to the
daemon, estops over the urgent channel. Why a process of its own: docs/protocol.md, "Architecture".
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import concurrent.futures
import contextlib
import faulthandler
import gc
import importlib
import logging
import os
import signal
import socket
import sys
from collections.abc import Callable
from typing import Any

import msgpack

from usmswitch.protocol.export_plan import ExportPlan
from usmswitch.protocol.wire import (
    MAX_MSGID,
    REQUEST,
    ErrorCode,
    Limits,
    RpcError,
    note_frame,
)
from usmswitch.runtime.logsetup import configure_logging
from usmswitch.runtime.process_exit import exit_now
from usmswitch.runtime.realtime import drop_realtime, renice, server_fifo
from usmswitch.server.hub import KINDS, MAX_LINGERING, METRICS, TCP_BACKLOG, WEB, Channel, Conn, Hub

log = logging.getLogger("usmswitch.rpc")


#: The worker threads' SCHED_FIFO priority when the event loop has one: the lowest there is. At
#: SCHED_OTHER a worker holding the GIL was preempted by the machine's ordinary processes and the
#: event loop waited for it (an estop by the panel took up to 575 ms under the abuse bench's loads).
#: Below the event loop, a worker gives the GIL back within the switch interval whenever the event
#: loop wants it. (The records reads run in processes of their own: server/records_reads.py.)
WORKER_PRIORITY = 1
#: How long a thread that wants the GIL waits before the holder must give it up: a panel estop
#: takes it back from the event loop's thread at each step (its frame read, the estop socket's
#: reply, its answer). Under 8 clients hammering `stats` the panel feed's estop read p99 3.61 ms
#: (max 6.73) at 0.5 ms, 2.86 (max 5.27) at 0.2 ms, the daemon's own (300 each, one run each, stop 58).
SWITCH_INTERVAL_S = 0.0002


def _worker_priority() -> None:
    """A worker thread (started by the event loop's, whose policy it inherits) at SCHED_FIFO
    WORKER_PRIORITY when the event loop is real-time, else as it is."""
    with contextlib.suppress(OSError):
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(WORKER_PRIORITY))


def _workers(n: int, name: str) -> concurrent.futures.ThreadPoolExecutor:
    """A pool of `n` worker threads below the event loop (`_worker_priority`)."""
    return concurrent.futures.ThreadPoolExecutor(n, thread_name_prefix=name, initializer=_worker_priority)


# -- the server process ----------------------------------------------------------------------------

#: The panel is handed the queue at most this often (seconds), the latest then. Each edit of the
#: queue publishes it whole (~50 KB with 100 runs and their notes), and a script that edits it makes
#: ~200 a second; decoding each took 0.3-0.5 ms of the event loop every socket's estop goes through.
#: The panel shows the queue once a tick anyway (web/panel.py's TICK_S, 0.1 s).
QUEUE_EVERY_S = 0.1
#: How a queue notification begins ([NOTIFICATION, "queue", [payload]]): known without decoding it.
_QUEUE_HEAD = note_frame("queue", None)[:-1]


class PanelConn(Conn):
    """The browser panel's way in (web/panel.py's Backend): its calls go through `handle` as a socket
    client's requests do (the same checks, forwarded to the daemon over the channel, estop over the
    urgent channel, reads from the records file), so there is no second way into the loop. It has
    no transport: replies resolve the callers' futures, notifications go to the panel's listeners.
    All open panels share it, and with it one connection's bound on calls in flight."""

    def __init__(self, hub: Hub) -> None:
        super().__init__(hub, WEB)
        self.waiting: dict[int, asyncio.Future[Any]] = {}
        self.msgid = 0
        self.listeners: list[Callable[[str, Any], None]] = []
        self._queue_frame: bytes | None = None  # the latest queue notification not handed on yet
        self._queue_timer: asyncio.TimerHandle | None = None

    def call(self, method: str, params: list[Any]) -> asyncio.Future[Any]:
        """A socket method; the future's result is the decoded reply, or it raises RpcError."""
        self.msgid = self.msgid % MAX_MSGID + 1
        fut: asyncio.Future[Any] = self.hub.loop.create_future()
        self.waiting[self.msgid] = fut
        reply = self.handle([REQUEST, self.msgid, method, params])
        if reply is not None:
            self.write(reply)
        return fut

    def listen(self, listener: Callable[[str, Any], None]) -> None:
        self.listeners.append(listener)

    async def export_csv(self, run_id: int, write: Callable[[bytes], Any]) -> int:
        """A run as CSV, its chunks read by reader processes as the socket's `export` (a few in
        flight, `protocol.export_plan`, so the next is built while this one is written), each
        written as the browser takes it: the memory is a few chunks, a browser gone reads no more."""
        from usmswitch.protocol.record_csv import csv_header_line  # the panel's export only

        hub = self.hub
        if hub.readers is None:
            raise RpcError(ErrorCode.UNAVAILABLE, "export: this server has no records file")
        readers = hub.readers

        def read(method: str, params: list[Any]) -> asyncio.Future[list[bytes]]:
            async def on_hub() -> list[bytes]:  # on the hub's loop, where the readers live
                return await readers.read(method, params)

            return asyncio.wrap_future(asyncio.run_coroutine_threadsafe(on_hub(), hub.loop))

        plan = ExportPlan()
        asked: collections.deque[asyncio.Future[list[bytes]]] = collections.deque()
        about: asyncio.Future[list[bytes]] | None = read("stats", [run_id, None, None, None])  # label, notes
        n = 0

        def ask() -> None:
            for first, last, most in plan.requests():
                asked.append(read("export", [run_id, first, last, most]))

        try:  # on the HTTP doors' loop (server/http_doors.py)
            ask()
            # Replies come in the pieces they arrived in (server/records_reads.py): joined here.
            while asked:
                part = msgpack.unpackb(b"".join(await asked.popleft()), raw=False)
                if about is not None:  # the run is known (its first read said so): the header
                    run = msgpack.unpackb(b"".join(await about), raw=False)["run"]
                    about = None
                    await write(csv_header_line([run]).encode())
                handed = plan.answered(part["strokes"], part["last_cycle"])
                ask()  # the next in flight before this one is written
                if handed and part["strokes"]:
                    n += part["strokes"]
                    await write(part["csv"].encode())
            return n
        finally:
            for fut in (*asked, *([about] if about is not None else [])):
                if not fut.cancel() and not fut.cancelled():
                    fut.exception()  # retrieved, not warned of: the export failed or ended already

    def write(self, data: bytes) -> None:
        _, msgid, error, result = msgpack.unpackb(data, raw=False)
        fut = self.waiting.pop(msgid, None)
        if fut is None or fut.done():
            return
        if error is not None:
            fut.set_exception(RpcError(error[0], error[1]))
        else:
            fut.set_result(result)

    def write_parts(self, parts: list[bytes]) -> None:
        self.write(b"".join(parts))

    def notify(self, frame: bytes) -> None:
        if frame.startswith(_QUEUE_HEAD):
            self._queue_frame = frame
            if self._queue_timer is None:
                self._hand_queue()
            return
        self._hand(frame)

    def _hand_queue(self) -> None:
        """The latest queue notification to the listeners, then none for QUEUE_EVERY_S: one that
        comes meanwhile waits for the end of it (a newer one in its place)."""
        frame, self._queue_frame = self._queue_frame, None
        if frame is None:
            self._queue_timer = None
            return
        self._queue_timer = self.hub.loop.call_later(QUEUE_EVERY_S, self._hand_queue)
        self._hand(frame)

    def _hand(self, frame: bytes) -> None:
        _, topic, (payload,) = msgpack.unpackb(frame, raw=False)
        for listener in self.listeners:
            listener(topic, payload)

    def dropped(self, count: int) -> None:
        for listener in self.listeners:
            listener("dropped", {"count": count})

    def fatal(self, code: int, message: str, msgid: int | None = None) -> None:
        fut = None if msgid is None else self.waiting.pop(msgid, None)
        if fut is not None and not fut.done():
            fut.set_exception(RpcError(code, message))


def _recv_exact(sock: socket.socket, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        data = sock.recv(n - len(buf))
        if not data:
            return None
        buf += data
    return bytes(buf)


async def _serve(
    chan: socket.socket,
    urgent_chan: socket.socket,
    listeners: list[tuple[socket.socket, str]],
    cfg: dict[str, Any],
) -> None:
    loop = asyncio.get_running_loop()
    loop.set_default_executor(_workers(4, "rpc-default"))  # aiohttp's file reads: below the loop too
    hub = Hub(cfg, loop)
    # uvloop calls connection_made a step after connect_accepted_socket returns: take the
    # transports from its return, so the "ready" below has its channel either way.
    for urgent, sock in ((False, chan), (True, urgent_chan)):
        transport, proto = await loop.connect_accepted_socket(lambda u=urgent: Channel(hub, u), sock=sock)
        proto.connection_made(transport)
    # create_server, not create_unix_server: that unlinks the path on close (3.13+). Its backlog
    # is the listener's again (it listens anew: its default of 100 undid the daemon's own).
    backlogs = {"unix": hub.limits.unix_backlog, "tcp": TCP_BACKLOG}
    servers = [
        await loop.create_server(lambda k=k: Conn(hub, k), sock=s, backlog=backlogs[k])
        for s, k in listeners
        if k in KINDS
    ]
    http, doors = [(sock, kind) for sock, kind in listeners if kind not in KINDS], []
    if http:  # the panel and /metrics: never ahead of an estop on this loop (server/http_doors.py)
        from usmswitch.server.http_doors import serve_http

        panel = PanelConn(hub) if any(kind == WEB for _, kind in http) else None
        snapshot = lambda: (dict(hub.snaps), dict(hub.counts))  # noqa: E731  (copies: another thread)
        doors = await serve_http(http, panel, snapshot, cfg, _loop_factory(), lambda: _workers(2, "rpc-http"))
        if panel is not None:
            await panel.call("subscribe", [["stroke", "state", "run", "queue"]])
    assert hub.channel is not None
    # What start-up made is never garbage: a full collection scanned it all (43.7 ms on the loop).
    gc.freeze()
    hub.channel.send(["ready", os.getpid()])

    async def sweeper() -> None:
        while True:
            await asyncio.sleep(0.05)
            hub.sweep()

    task = loop.create_task(sweeper())
    try:
        await hub.done
    finally:
        task.cancel()
        for server in servers:
            server.close()
        for door in doors:
            door.close()
        for conn in list(hub.conns):
            if conn.transport is not None:
                conn.transport.abort()
        if hub.readers is not None:
            hub.readers.close()


def _loop_factory() -> Callable[[], asyncio.AbstractEventLoop] | None:
    """uvloop's event loop where it is installed (docs/protocol.md, "Where a request's time goes"):
    its transports and selector are C, the per-request cost of asyncio's own Python is most of what
    the server spends beside the send itself. asyncio's default loop otherwise."""
    if os.environ.get("USMSWITCH_RPC_LOOP") == "asyncio":
        return None
    try:
        import uvloop
    except ImportError:
        return None
    return uvloop.new_event_loop


def descriptors_needed(limits: Limits) -> int:
    """Descriptors the server process may hold at once with every door at its budget: each door's
    connections (and reserved slots), the connections draining their last bytes, the listeners,
    channels, records readers and logs. The units' LimitNOFILE is set above it (docs/service.md)."""
    from usmswitch.web.budgets import METRICS_CONNECTIONS, PANEL_CONNECTIONS  # no aiohttp

    doors = limits.max_connections + limits.max_tcp_connections + 2 * limits.urgent_reserve
    # A door sheds or refuses a newcomer only after accepting it: one more per door, briefly.
    http = PANEL_CONNECTIONS + METRICS_CONNECTIONS + 2
    readers = limits.max_reads + 1  # a socket to each reader process (their files are theirs)
    return doors + http + MAX_LINGERING + readers + 64  # 64: listeners, channels, std streams, libs


def fit_descriptors(limits: Limits) -> int:
    """Raise this process's soft RLIMIT_NOFILE toward what the budgets need (up to the hard limit);
    the soft limit after. A hard limit below the need is a warning naming both, never an exit."""
    import resource

    need = descriptors_needed(limits)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < need:
        want = need if hard == resource.RLIM_INFINITY else min(need, hard)
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
            soft = want
        if soft < need:
            log.warning(
                "rpc: %d descriptors allowed (hard limit %d), the doors' budgets need %d: raise"
                " LimitNOFILE (docs/service.md); past it new connections wait in the kernel",
                soft,
                hard,
                need,
            )
    return int(soft)


def serve(chan_fd: int, urgent_fd: int, listeners: list[tuple[int, str]], nice: int = 0) -> None:
    """The server process's body: read the config from the channel, then serve until told to stop."""
    chan = socket.socket(fileno=chan_fd)
    chan.setblocking(True)
    # The config comes first, length-prefixed, so not a byte of what follows is read here.
    head = _recv_exact(chan, 4)
    if head is None:
        return
    body = _recv_exact(chan, int.from_bytes(head, "big"))
    if body is None:
        return
    cfg = msgpack.unpackb(body, raw=False)
    fit_descriptors(Limits(**cfg["limits"]))
    if cfg["finishers"]:  # stats' percentiles import numpy at first use: 0.3-0.6 s on the loop, loaded
        with contextlib.suppress(ImportError):
            importlib.import_module("numpy")
    renice(nice, "server", "the socket's clients compete with the loop for CPU at the loop's nice")
    socks = [(socket.socket(fileno=fd), kind) for fd, kind in listeners]
    for sock, _ in socks:
        sock.setblocking(False)
    chan.setblocking(False)
    urgent = socket.socket(fileno=urgent_fd)
    urgent.setblocking(False)
    with asyncio.Runner(loop_factory=_loop_factory()) as runner:
        runner.run(_serve(chan, urgent, socks, cfg))


def raise_event_loop(priority: int) -> bool:
    """SCHED_FIFO `priority` for the calling thread (the event loop's, before it starts anything):
    an estop through the main socket, TCP or the panel is read, forwarded and answered the moment
    it arrives, not when the machine's ordinary processes leave the CPU (at SCHED_OTHER on 2 busy
    cores: p99 15-600 ms, `make bench BENCH=abuse`). Its worker threads run below it
    (`WORKER_PRIORITY`). A refusal is a warning: it serves at SCHED_OTHER."""
    return server_fifo(0, priority)


def main(argv: list[str] | None = None) -> int:
    """Entry of the server process the daemon spawns (not a command for people)."""
    parser = argparse.ArgumentParser(prog="usmswitch.server.rpc_process", description=__doc__.splitlines()[0])
    parser.add_argument("--channel", type=int, required=True, help="fd of the socketpair to the daemon")
    parser.add_argument("--urgent-channel", type=int, required=True, help="fd of the estop socketpair")
    parser.add_argument(
        "--listen",
        action="append",
        default=[],
        help="FD:unix, FD:tcp, FD:metrics or FD:web, a listening socket",
    )
    parser.add_argument("--nice", type=int, default=0)
    parser.add_argument("--priority", type=int, default=0, help="SCHED_FIFO of the event loop (0: off)")
    parser.add_argument("--log-format", default="auto", help="as [daemon] log_format")
    parser.add_argument("--log-level", default="info", help="as [daemon] log_level")
    args = parser.parse_args(argv)
    # Started again by the daemon's bridge thread, which runs SCHED_FIFO one below the loop when the
    # loop has it: dropped, then raised to what the daemon says (--priority, below its helpers).
    drop_realtime()
    configure_logging(args.log_format, args.log_level, sys.stderr)
    if args.priority:
        raise_event_loop(args.priority)
    # The daemon owns shutdown: a Ctrl-C to the terminal's process group or systemd's SIGTERM to the
    # cgroup must not kill the server under it mid-stop. It ends when the daemon's channel closes.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # a closed terminal: the daemon decides
    # Set here, in the process of its own, not in serve(), which a test may run in a thread.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    listeners = []
    for spec in args.listen:
        fd, _, kind = spec.partition(":")
        if kind not in (*KINDS, METRICS, WEB) or not fd.isdigit():
            parser.error(f"--listen must be FD:unix, FD:tcp, FD:metrics or FD:web, got {spec!r}")
        listeners.append((int(fd), kind))
    serve(args.channel, args.urgent_channel, listeners, args.nice)
    return 0


if __name__ == "__main__":
    faulthandler.enable(all_threads=True)  # a hang's stacks on SIGABRT, as the daemon's (daemon/cli.py)
    exit_now(main())  # every read is read-only and every client closed: nothing is left to save
