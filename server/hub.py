"""The socket server process's state (`Hub`: connections, subscriptions, snapshots, calls in flight,
the records readers) and its ends of the wire: `Channel` to the daemon, `Conn` a client's
connection (decode, validate, dispatch, throttle its notifications). Served by
`usmswitch.server.rpc_process`; the doors' budgets: docs/protocol.md, "Doors and budgets".
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import pkgutil
import time
from typing import Any, cast

import msgpack

from usmswitch.protocol.rpc_params import PARAMS, check_params, show
from usmswitch.protocol.wire import (
    BUILTIN_METHODS,
    MAX_MSGID,
    REQUEST,
    ErrorCode,
    Limits,
    RpcError,
    error_frame,
    note_frame,
    ok_frame,
    ok_head,
    packb,
    unpacker,
)
from usmswitch.server.busy_poll import BusyPoll, usable_cpus
from usmswitch.server.records_reads import READS, RecordsReaders

log = logging.getLogger("usmswitch.rpc")


def _s(ns: int) -> str:
    """A timeout for people: 2 s, 250 ms."""
    return f"{ns / 1e9:g} s" if ns >= 1_000_000_000 else f"{ns / 1e6:g} ms"


_PONG = packb("pong")
_TRUE = packb(True)

#: Listener kinds of the server process: the Unix socket and TCP (the estop socket is the daemon's).
KINDS = ("unix", "tcp")
#: The HTTP listener of the metrics page (web/metrics_page.py), also bound by the daemon.
METRICS = "metrics"
#: The HTTP listener of the browser panel (web/panel.py), also bound by the daemon.
WEB = "web"
# The TCP listener's backlog (the Unix socket's is Limits.unix_backlog): past it the kernel drops a
# SYN and the client tries again a second later, so deep. The estop socket's thread takes every
# pending connection at once and reads it (server/estop_socket.py): deep too.
TCP_BACKLOG = 128
URGENT_BACKLOG = 1024
# A refused or timed-out connection is half-closed and kept this long (at most this many at once)
# so that the client reads the reason instead of a reset.
_LINGER_S = 0.5
MAX_LINGERING = 256
# TCP auth back-off per peer address: free tries, then a wait doubling from 100 ms up to 30 s.
_AUTH_FREE = 3
_AUTH_BACKOFF_NS = 100_000_000
_AUTH_MAX_NS = 30_000_000_000
_AUTH_PEERS = 4096  # addresses remembered (the oldest forgotten first)


class Hub:
    """The server process's state: connections, subscriptions, snapshots, calls in flight."""

    def __init__(self, cfg: dict[str, Any], loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.limits = Limits(**cfg["limits"])
        self.token: str | None = cfg["token"]
        self.handlers = frozenset(cfg["handlers"])
        self.urgent = frozenset(cfg["urgent"])
        self.snapshot_methods = frozenset(cfg["snapshot_methods"])
        self.topics = tuple(cfg["topics"])
        self.known = frozenset(BUILTIN_METHODS) | self.handlers | self.urgent | self.snapshot_methods
        if cfg["records_path"]:
            self.known |= {"history", "runs", "export"}
        self.snaps: dict[str, bytes] = dict(cfg["snaps"])
        # Snapshots the daemon sends unfinished (the loop's stats without their percentiles):
        # finished here, on the first request after each update, so the loop never pays for it.
        self.finishers = {m: pkgutil.resolve_name(ref) for m, ref in cfg["finishers"].items()}
        self.raw_snaps = {m: self.snaps.pop(m) for m in self.finishers if m in self.snaps}
        # The run each finished snapshot covers: `stats [run]` of that run is the snapshot.
        self.snap_runs: dict[str, int | None] = {}
        self.subs: dict[str, set[Conn]] = {t: set() for t in self.topics}
        self.conns: set[Conn] = set()
        self.counts = dict.fromkeys(KINDS, 0)  # open connections per listener kind
        self.reserved = dict.fromkeys(KINDS, 0)  # past the budget, for an estop (Limits.urgent_reserve)
        self.shed = dict.fromkeys(KINDS, 0)  # holders shed for newcomers, since start
        # Per door, its holders not yet proven (silent since connecting, or not authenticated), in
        # the order they came: the first shed, found without a scan of every connection (under a
        # renewed flood of 600 that scan was some 60 % of this loop's busy time).
        self.unproven: dict[str, dict[Conn, None]] = {k: {} for k in KINDS}
        # A newcomer is not shed before the loop has read what it sent: a burst of accepts makes
        # every connection of it before reading any, and the later ones of a burst of 600 shed
        # the earlier, an estop among them, unread. Connections made in this loop's turn carry
        # its `epoch`; only those of an earlier turn may give way.
        self.epoch = 0
        self._epoch_moving = False
        self._shed_logged_ns = 0
        self._shed_frames: dict[tuple[str, int, str], bytes] = {}
        self.auth_failures: dict[str, tuple[int, int]] = {}  # TCP peer address -> (failures, wait until)
        self.auth_failed_total = 0
        self._auth_logged_ns = 0
        self.lingering = 0  # closed connections still draining their client's last bytes
        self.pending: dict[int, tuple[Conn, int, int]] = {}  # fid -> (conn, msgid, deadline_ns)
        self.urgent_pending: dict[int, tuple[Conn, int, int]] = {}
        self.next_fid = 1
        self.lost_seen: int = cfg["lost"]
        self.channel: Channel | None = None
        self.urgent_channel: Channel | None = None
        self.done: asyncio.Future[None] = loop.create_future()
        window = cfg["busy_poll_ns"]
        self.busy = BusyPoll(loop, window, usable_cpus()) if window else None
        # The records file is read here, not in the daemon: the loop's process never reads or packs
        # a large reply; and by processes of their own, never holding the GIL against this loop.
        self.readers = (
            RecordsReaders(loop, cfg["records_path"], cfg["records_reader"], self.limits.max_reads)
            if cfg["records_path"]
            else None
        )

    def snapshot(self, method: str) -> bytes | None:
        """The packed result of a snapshot method, finished from its raw form when it has to be."""
        snap = self.snaps.get(method)
        if snap is None and method in self.raw_snaps:
            finished = self.finishers[method](msgpack.unpackb(self.raw_snaps[method], raw=False))
            snap = self.snaps[method] = packb(finished)
            run = finished.get("run") if isinstance(finished, dict) else None
            self.snap_runs[method] = run.get("run_id") if isinstance(run, dict) else None
        return snap

    def stats_from_snapshot(self, params: list[Any]) -> bytes | None:
        """The published stats when `params` ask for what they cover (the current or last run)."""
        run, first, last, label = params
        if first is not None or last is not None or label is not None:
            return None
        snap = self.snapshot("stats")
        if snap is None or (run is not None and self.snap_runs.get("stats") != run):
            return None
        return snap

    def auth_backoff(self, peer: str) -> int:
        """Nanoseconds this address must still wait before its next auth is even compared."""
        entry = self.auth_failures.get(peer)
        return 0 if entry is None else max(0, entry[1] - time.monotonic_ns())

    def auth_failed(self, peer: str) -> None:
        """Count a wrong token from `peer`: past _AUTH_FREE in a row, each costs a doubling wait."""
        now = time.monotonic_ns()
        count = self.auth_failures.pop(peer, (0, 0))[0] + 1
        over = count - _AUTH_FREE
        wait = 0 if over <= 0 else min(_AUTH_BACKOFF_NS << min(over - 1, 20), _AUTH_MAX_NS)
        self.auth_failures[peer] = (count, now + wait)  # re-inserted: the dict stays oldest-first
        while len(self.auth_failures) > _AUTH_PEERS:
            del self.auth_failures[next(iter(self.auth_failures))]
        self.auth_failed_total += 1
        if now - self._auth_logged_ns >= 1_000_000_000 or count == 1:
            self._auth_logged_ns = now
            log.warning(
                "rpc: TCP auth failed from %s (%d in a row, %d in all); next try after %s",
                peer,
                count,
                self.auth_failed_total,
                _s(wait) if wait else "no wait",
            )

    def arrival_epoch(self) -> int:
        """The epoch of a connection made now: it ends two turns of the loop later, when the
        turn after this one has read the sockets (uvloop and asyncio alike)."""
        if not self._epoch_moving:
            self._epoch_moving = True
            self.loop.call_soon(self.loop.call_soon, self._next_epoch)
        return self.epoch

    def _next_epoch(self) -> None:
        self.epoch += 1
        self._epoch_moving = False

    def full_text(self, kind: str, most: int) -> str:
        """What a connection past a door's budget is told."""
        where = "TCP" if kind == "tcp" else "Unix socket"
        return f"too many connections on the {where} (max {most}); try again later (past it: estop only)"

    def shed_one(self, kind: str, most: int) -> bool:
        """Make room on a full door: close its unauthenticated holder, else its longest-idle one
        (nothing outstanding, no request for `shed_idle_ns`; a subscription is no exemption)."""
        now = time.monotonic_ns()
        epoch = self.epoch
        victim = next(
            (c for c in self.unproven[kind] if c.epoch < epoch and not (c.outstanding or c.closed)), None
        )
        if victim is not None:
            how = "silent" if victim.authed else "not authenticated"
        else:
            how = "idle longest"
            since = now - self.limits.shed_idle_ns + 1  # idle long enough: no request since
            for conn in self.conns:  # the proven: the longest idle
                if conn.kind != kind or conn.reserved or conn.closed or conn.outstanding:
                    continue
                if conn.epoch < epoch and conn.last_req_ns < since:
                    victim, since = conn, conn.last_req_ns
            if victim is None:
                return False
        frame = self._shed_frames.get((kind, most, how))
        if frame is None:  # the same words at every shed: packed once (a flood sheds thousands a second)
            text = f"{self.full_text(kind, most)}: this connection, {how}, gave way"
            frame = self._shed_frames[kind, most, how] = note_frame("error", [int(ErrorCode.BUSY), text])
        victim.close_with(frame)
        self.shed[kind] += 1
        if now - self._shed_logged_ns >= 10_000_000_000:  # one line per 10 s, however many
            self._shed_logged_ns = now
            log.warning(
                "rpc: %s full (max %d): holders shed for newcomers, %d so far", kind, most, self.shed[kind]
            )
        return True

    def _too_many(self, conn: Conn, msgid: int, method: str) -> bytes:
        return error_frame(
            msgid,
            ErrorCode.BUSY,
            f"{method}: {conn.outstanding} requests outstanding on this connection "
            f"(max {self.limits.max_outstanding}); read the responses first",
        )

    def forward(self, conn: Conn, msgid: int, method: str, params: list[Any]) -> bytes | None:
        """Send a call to the daemon, or return an error response when a bound says no."""
        if conn.outstanding >= self.limits.max_outstanding:
            return self._too_many(conn, msgid, method)
        if len(self.pending) >= self.limits.max_forwarded:
            return error_frame(
                msgid, ErrorCode.BUSY, f"{method}: daemon busy, {len(self.pending)} calls in flight"
            )
        if self.channel is None:
            return error_frame(msgid, ErrorCode.UNAVAILABLE, f"{method}: the daemon is not connected")
        fid = self.next_fid
        self.next_fid += 1
        self.pending[fid] = (conn, msgid, time.monotonic_ns() + self.limits.call_timeout_ns)
        conn.outstanding += 1
        self.channel.send(["call", fid, method, params])
        return None

    def forward_urgent(self, conn: Conn, msgid: int, method: str, params: list[Any]) -> bytes | None:
        """An estop: straight to the daemon's urgent thread, behind nothing, refused by no call limit."""
        if self.urgent_channel is None:
            return error_frame(msgid, ErrorCode.UNAVAILABLE, f"{method}: the daemon is not connected")
        fid = self.next_fid
        self.next_fid += 1
        self.urgent_pending[fid] = (conn, msgid, time.monotonic_ns() + self.limits.call_timeout_ns)
        self.urgent_channel.send(["call", fid, method, params])
        return None

    def read(self, conn: Conn, msgid: int, method: str, params: list[Any]) -> bytes | None:
        """A read (history, runs, a past run's stats, an export's chunk) answered from the records
        file by a reader process (server/records_reads.py)."""
        if conn.outstanding >= self.limits.max_outstanding:
            return self._too_many(conn, msgid, method)
        assert self.readers is not None
        conn.outstanding += 1
        fut = self.readers.read(method, params, lambda: conn.closed)
        conn.reads.add(fut)

        def done(fut: asyncio.Future[list[bytes]]) -> None:
            conn.outstanding -= 1
            conn.reads.discard(fut)
            if fut.cancelled() or conn.closed:
                return
            exc = fut.exception()
            if exc is None:
                conn.write_parts([ok_head(msgid), *fut.result()])
            elif isinstance(exc, RpcError):
                if exc.code == ErrorCode.INTERNAL:
                    log.error("rpc: %s read failed: %s", method, exc.message)
                conn.write(error_frame(msgid, exc.code, exc.message))
            else:
                log.error("rpc: %s read failed: %s", method, exc)
                conn.write(error_frame(msgid, ErrorCode.INTERNAL, f"{method}: {type(exc).__name__}: {exc}"))

        fut.add_done_callback(done)
        return None

    def on_daemon(self, msg: list[Any], urgent: bool = False) -> None:
        """A message from the daemon over the channel (or the urgent channel)."""
        kind = msg[0]
        if kind == "resp":
            _, fid, error, result_bytes = msg
            entry = (self.urgent_pending if urgent else self.pending).pop(fid, None)
            if entry is None:  # timed out already
                return
            conn, msgid, _ = entry
            if not urgent:
                conn.outstanding -= 1
            if error is None:
                conn.write(ok_frame(msgid, result_bytes))
            else:
                conn.write(error_frame(msgid, error[0], error[1]))
        elif kind == "note":
            _, topic, frame, lost_total = msg
            if lost_total > self.lost_seen:
                delta, self.lost_seen = lost_total - self.lost_seen, lost_total
                for conn in {c for subs in self.subs.values() for c in subs}:
                    conn.dropped(delta)
            for conn in tuple(self.subs.get(topic, ())):
                conn.notify(frame)
        elif kind == "snap":
            if msg[1] in self.finishers:
                self.raw_snaps[msg[1]] = msg[2]
                self.snaps.pop(msg[1], None)  # finished again at the next request
            else:
                self.snaps[msg[1]] = msg[2]
        elif kind == "stop" and not self.done.done():
            self.done.set_result(None)

    def sweep(self) -> None:
        """Time out calls the daemon does not answer, TCP clients that never authenticate, idlers."""
        now = time.monotonic_ns()
        lim = self.limits
        for table in (self.pending, self.urgent_pending):
            for fid, (conn, msgid, deadline) in list(table.items()):
                if deadline < now:
                    del table[fid]
                    if table is self.pending:
                        conn.outstanding -= 1
                    conn.write(
                        error_frame(
                            msgid,
                            ErrorCode.TIMEOUT,
                            f"no answer from the daemon in {_s(lim.call_timeout_ns)}",
                        )
                    )
        for conn in list(self.conns):
            if conn.reserved:  # one deadline only: its hold
                if now - conn.born_ns > lim.urgent_hold_ns:
                    most = lim.max_tcp_connections if conn.tcp else lim.max_connections
                    conn.fatal(ErrorCode.BUSY, self.full_text(conn.kind, most))
            elif conn.partial_since_ns is not None and now - conn.partial_since_ns > lim.frame_timeout_ns:
                conn.fatal(
                    ErrorCode.TIMEOUT, f"a frame begun and not finished within {_s(lim.frame_timeout_ns)}"
                )
            elif not conn.frames and now - conn.born_ns > conn.first_frame_timeout_ns:
                conn.fatal(
                    ErrorCode.TIMEOUT, f"no request within {_s(conn.first_frame_timeout_ns)} of connecting"
                )
            elif not conn.authed and now - conn.born_ns > lim.auth_timeout_ns:
                conn.fatal(ErrorCode.UNAUTHORIZED, f"no auth within {_s(lim.auth_timeout_ns)}")
            elif (
                conn.authed
                and not conn.topics
                and not conn.outstanding
                and now - conn.last_req_ns > lim.idle_timeout_ns
            ):
                conn.fatal(ErrorCode.TIMEOUT, f"idle for more than {_s(lim.idle_timeout_ns)}")


class Channel(asyncio.Protocol):
    """The server process's end of the daemon channel (trusted: the daemon is our parent)."""

    def __init__(self, hub: Hub, urgent: bool = False) -> None:
        self.hub = hub
        self.urgent = urgent
        self.unpacker = msgpack.Unpacker(raw=False, max_buffer_size=1 << 30)
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # Idempotent (_serve calls it too: uvloop calls it late). A cast: uvloop's transports are not
        # asyncio.Transport subclasses.
        self.transport = cast(asyncio.Transport, transport)
        if self.urgent:
            self.hub.urgent_channel = self
        else:
            self.hub.channel = self

    def data_received(self, data: bytes) -> None:
        self.unpacker.feed(data)
        for msg in self.unpacker:
            self.hub.on_daemon(msg, self.urgent)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.urgent:
            self.hub.urgent_channel = None
            return
        self.hub.channel = None
        if not self.hub.done.done():
            self.hub.done.set_result(None)

    def send(self, obj: object) -> None:
        assert self.transport is not None
        self.transport.write(packb(obj))


class Conn(asyncio.Protocol):
    """One client connection: decode, validate, dispatch, and throttle its notifications."""

    def __init__(self, hub: Hub, kind: str) -> None:
        self.hub = hub
        self.kind = kind
        self.tcp = kind == "tcp"
        self.unpacker: msgpack.Unpacker | None = None  # made at the first byte: silent ones cost none
        self.transport: asyncio.Transport | None = None
        self.closed = False
        self.counted = False
        self.authed = not self.tcp
        self.born_ns = self.last_req_ns = time.monotonic_ns()
        self.fed = 0  # bytes fed to the unpacker; those past the last frame's end are a partial frame
        self.frames = 0
        self.frames_end = 0
        self.partial_since_ns: int | None = None
        lim = hub.limits
        self.first_frame_timeout_ns = lim.first_frame_timeout_ns
        self.outstanding = 0
        self.bad_frames = 0
        self.topics: set[str] = set()
        self.paused = False
        self.drop_pending = 0
        self.drop_total = 0
        self.reserved = False  # taken past the door's budget: auth and estop only, briefly
        self.epoch = 0  # the loop's turn it came in (Hub.arrival_epoch)
        self.reads: set[asyncio.Future[bytes]] = set()  # in a reader's queue or being read

    # asyncio callbacks
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport = cast(asyncio.Transport, transport)  # uvloop's: not subclasses
        hub = self.hub
        limits = hub.limits
        transport.set_write_buffer_limits(high=limits.subscriber_buffer_bytes)
        most = limits.max_tcp_connections if self.tcp else limits.max_connections
        self.epoch = hub.arrival_epoch()
        if hub.counts[self.kind] >= most and not hub.shed_one(self.kind, most):
            # Past the budget with nobody to shed: a reserved slot that takes only auth and estop,
            # so that no holder of every slot can keep an estop out of this door.
            self.reserved = True
            if hub.reserved[self.kind] >= limits.urgent_reserve:
                # The oldest that has been read gives way; none has (a burst past every slot):
                # the reserve grows for this turn, bounded by the listen backlog.
                oldest = min(
                    (
                        c
                        for c in hub.conns
                        if c.reserved and c.kind == self.kind and not c.closed and c.epoch < hub.epoch
                    ),
                    key=lambda c: c.born_ns,
                    default=None,
                )
                if oldest is not None:
                    oldest.fatal(ErrorCode.BUSY, hub.full_text(self.kind, most))
            hub.conns.add(self)
            hub.reserved[self.kind] += 1
            self.counted = True
            return
        hub.conns.add(self)
        hub.counts[self.kind] += 1
        hub.unproven[self.kind][self] = None
        self.counted = True

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        for fut in list(self.reads):  # queued reads are dropped unread; a running one is not sent
            fut.cancel()
        self._uncount()
        if self.hub.busy is not None:
            self.hub.busy.forget(self)
        for topic in self.topics:
            self.hub.subs[topic].discard(self)

    def pause_writing(self) -> None:
        # The client is not reading: stop reading its requests too (back-pressure on pipelining).
        self.paused = True
        if self.transport is not None and not self.closed:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        self.paused = False
        if self.transport is not None and not self.closed:
            self.transport.resume_reading()
            if self.drop_pending:
                self._tell_dropped()

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        up = self.unpacker
        if up is None:
            up = self.unpacker = unpacker(self.hub.limits)
        try:
            up.feed(data)
        except msgpack.BufferFull:
            self.fatal(ErrorCode.TOO_LARGE, f"frame larger than {self.hub.limits.max_frame_bytes} bytes")
            return
        self.fed += len(data)
        out: list[bytes] = []
        try:
            for msg in up:
                self.frames += 1
                self.frames_end = up.tell()  # exact here; past a partial frame after
                reply = self.handle(msg)
                if reply is not None:
                    out.append(reply)
                if self.closed:
                    break
        except Exception as exc:  # any decoder complaint: the stream cannot be resynchronised
            if out:
                self.write(b"".join(out))
            self.fatal(ErrorCode.PARSE_ERROR, f"undecodable msgpack: {type(exc).__name__}: {exc}")
            return
        if out:
            self.write(b"".join(out))
        if self.frames and self.authed:
            self.hub.unproven[self.kind].pop(self, None)
        if self.frames_end < self.fed:
            if self.partial_since_ns is None:
                self.partial_since_ns = time.monotonic_ns()
        else:
            self.partial_since_ns = None

    # dispatch
    def handle(self, msg: object) -> bytes | None:
        """Answer one decoded frame; None when the answer comes later (a forwarded call)."""
        if type(msg) is not list or len(msg) != 4 or msg[0] != REQUEST:
            return self._bad(msg)
        _, msgid, method, params = msg
        if type(msgid) is not int or not 0 <= msgid <= MAX_MSGID:
            return self._bad(msg)
        if type(method) is not str or type(params) is not list:
            return self._bad(msg, msgid)
        self.last_req_ns = now = time.monotonic_ns()
        if self.hub.busy is not None:
            self.hub.busy.request(self, now)
        if not self.authed and method != "auth":
            self.fatal(ErrorCode.UNAUTHORIZED, "this TCP connection must send auth [token] first", msgid)
            return None
        if self.reserved and method not in self.hub.urgent and method != "auth":
            most = self.hub.limits.max_tcp_connections if self.tcp else self.hub.limits.max_connections
            self.fatal(ErrorCode.BUSY, self.hub.full_text(self.kind, most), msgid)
            return None
        try:
            if method not in self.hub.known:
                raise RpcError(
                    ErrorCode.UNKNOWN_METHOD,
                    f"unknown method {show(method)}; known: {', '.join(sorted(self.hub.known))}",
                )
            if method in PARAMS:
                params = check_params(method, params)
            if method == "ping":
                return ok_frame(msgid, _PONG)
            if method in self.hub.urgent:
                return self.hub.forward_urgent(self, msgid, method, params)
            if method == "stats":
                snap = self.hub.stats_from_snapshot(params)
                if snap is not None:
                    return ok_frame(msgid, snap)
                if any(p is not None for p in params):
                    if self.hub.readers is not None:
                        return self.hub.read(self, msgid, method, params)
                    raise RpcError(
                        ErrorCode.UNAVAILABLE,
                        f"{method}: past runs and cycle ranges are read from the records file; "
                        "this server has none",
                    )
                raise RpcError(ErrorCode.UNAVAILABLE, f"{method}: nothing published yet")
            if method in READS and self.hub.readers is not None:
                return self.hub.read(self, msgid, method, params)
            snap = self.hub.snapshot(method)
            if snap is not None and not params:
                return ok_frame(msgid, snap)
            if method == "auth":
                return self._auth(msgid, params[0])
            if method == "subscribe":
                return self._subscribe(msgid, params[0], True)
            if method == "unsubscribe":
                return self._subscribe(msgid, params[0], False)
            if method in self.hub.handlers:
                return self.hub.forward(self, msgid, method, params)
            if params:
                raise RpcError(ErrorCode.INVALID_PARAMS, f"{method} takes no params, got {len(params)}")
            raise RpcError(ErrorCode.UNAVAILABLE, f"{method}: nothing published yet")
        except RpcError as exc:
            if method == "auth" and not self.authed:  # a token that is not a string: no second try
                self.hub.auth_failed(self.peer_host())
                self.fatal(ErrorCode.UNAUTHORIZED, exc.message, msgid)
                return None
            return error_frame(msgid, exc.code, exc.message)
        except Exception as exc:  # a bug here must cost one request, not the server
            log.exception("rpc: %s failed", show(method))
            return error_frame(msgid, ErrorCode.INTERNAL, f"{method}: internal error: {type(exc).__name__}")

    def _bad(self, msg: object, msgid: int | None = None) -> bytes | None:
        self.bad_frames += 1
        if msgid is None and type(msg) is list and len(msg) >= 2 and msg[0] == REQUEST:
            candidate = msg[1]
            if type(candidate) is int and 0 <= candidate <= MAX_MSGID:
                msgid = candidate
        text = f"expected [0, msgid (uint32), method (str), params (array)], got {show(msg)}"
        if self.bad_frames > self.hub.limits.max_bad_frames:
            self.fatal(ErrorCode.INVALID_REQUEST, f"too many invalid requests; last: {text}", msgid)
            return None
        if msgid is None:
            return note_frame("error", [int(ErrorCode.INVALID_REQUEST), text])
        return error_frame(msgid, ErrorCode.INVALID_REQUEST, text)

    def _auth(self, msgid: int, token: str) -> bytes | None:
        if not self.tcp or self.hub.token is None:
            return ok_frame(msgid, _TRUE)
        peer = self.peer_host()
        wait_ns = self.hub.auth_backoff(peer)
        if wait_ns:  # not even compared: guessing from this address is slowed to the back-off's pace
            self.fatal(
                ErrorCode.UNAUTHORIZED,
                f"too many failed auth attempts from {peer}: try again in {_s(wait_ns)}",
                msgid,
            )
            return None
        if hmac.compare_digest(token.encode(), self.hub.token.encode()):
            self.authed = True
            self.hub.auth_failures.pop(peer, None)
            return ok_frame(msgid, _TRUE)
        self.hub.auth_failed(peer)
        self.fatal(ErrorCode.UNAUTHORIZED, "wrong token", msgid)
        return None

    def peer_host(self) -> str:
        """The peer's address without its port (the back-off is per address)."""
        name = None if self.transport is None else self.transport.get_extra_info("peername")
        return str(name[0]) if isinstance(name, tuple) and name else "?"

    def _subscribe(self, msgid: int, topics: list[str] | None, on: bool) -> bytes:
        wanted = self.hub.topics if topics is None else topics
        for topic in wanted:
            if topic not in self.hub.subs:
                raise RpcError(
                    ErrorCode.INVALID_PARAMS,
                    f"unknown topic {show(topic)}; known: {', '.join(self.hub.topics)}",
                )
        for topic in wanted:
            if on:
                self.hub.subs[topic].add(self)
                self.topics.add(topic)
            else:
                self.hub.subs[topic].discard(self)
                self.topics.discard(topic)
        return ok_frame(msgid, packb({"topics": sorted(self.topics), "dropped": self.drop_total}))

    # output
    def write(self, data: bytes) -> None:
        """Queue bytes; a client that lets replies pile up past the hard limit is cut off."""
        if self.closed or self.transport is None:
            return
        self.transport.write(data)
        self._cut_off_past_the_limit()

    def write_parts(self, parts: list[bytes]) -> None:
        """Queue one frame given in pieces (a records read's reply as its reader sent it), as
        `write`: the transport takes them as they are, no copy joins them."""
        if self.closed or self.transport is None:
            return
        self.transport.writelines(parts)
        self._cut_off_past_the_limit()

    def _cut_off_past_the_limit(self) -> None:
        assert self.transport is not None
        if self.transport.get_write_buffer_size() > self.hub.limits.max_write_buffer_bytes:
            self.closed = True
            self.transport.abort()

    def notify(self, frame: bytes) -> None:
        """Send a notification unless the client is behind; then drop it and count."""
        if self.closed or self.transport is None:
            return
        # Same test as asyncio's pause_writing, so every drop is followed by a resume_writing
        # that tells the client (even when no further notification comes).
        if self.paused or self.transport.get_write_buffer_size() > self.hub.limits.subscriber_buffer_bytes:
            self.drop_pending += 1
            self.drop_total += 1
            return
        if self.drop_pending:
            self._tell_dropped()
        self.write(frame)

    def dropped(self, count: int) -> None:
        """Notifications lost before reaching this process (the daemon's backlog was full)."""
        self.drop_pending += count
        self.drop_total += count
        if not self.paused:
            self._tell_dropped()

    def _tell_dropped(self) -> None:
        count, self.drop_pending = self.drop_pending, 0
        self.write(note_frame("dropped", {"count": count, "total": self.drop_total}))

    def fatal(self, code: int, message: str, msgid: int | None = None) -> None:
        """Say why (a response when there is a msgid, else an "error" notification), then close."""
        if self.closed or self.transport is None:
            return
        self.close_with(
            note_frame("error", [int(code), message]) if msgid is None else error_frame(msgid, code, message)
        )

    def close_with(self, frame: bytes) -> None:
        """Send `frame` (why), then close: half-closed and read on a moment, when it can be."""
        if self.closed or self.transport is None:
            return
        transport = self.transport
        transport.write(frame)
        self.closed = True
        self._uncount()
        hub = self.hub
        if transport.can_write_eof() and hub.lingering < MAX_LINGERING:
            # Half-close and read on for a moment: closing outright with the client's request
            # unread makes the kernel send a reset, and the client would never see why.
            transport.write_eof()
            hub.lingering += 1

            def finish() -> None:
                hub.lingering -= 1
                transport.close()

            hub.loop.call_later(_LINGER_S, finish)
        else:
            transport.close()  # flushes what is buffered, then closes

    def _uncount(self) -> None:
        if self.counted:
            self.counted = False
            self.hub.conns.discard(self)
            self.hub.unproven[self.kind].pop(self, None)
            if self.reserved:
                self.hub.reserved[self.kind] -= 1
            else:
                self.hub.counts[self.kind] -= 1
