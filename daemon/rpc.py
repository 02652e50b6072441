"""The daemon's msgpack-RPC server: framing, limits, connections, dispatch and notifications.

Architecture (docs/protocol.md, "Architecture"): the sockets are served by a separate server process
(`python -m usmswitch.daemon.rpc`), never by a thread of the control loop's process, because any
CPU-bound Python in the loop's process holds the GIL for up to the switch interval (5 ms) and lands
directly in the loop's start lateness. The daemon binds the listening sockets itself (so bind and
permission errors surface in `RpcServer.start`) and hands their descriptors to the child with a
socketpair "channel". Over the channel the daemon sends pre-packed snapshots (`stats`, ...) that the
child answers from without waking the daemon, pre-packed notifications it fans out to subscribers, and
the results of forwarded calls; the child sends only validated, bounded calls back. In the daemon,
`publish` and `snapshot` are O(1) appends; one writer thread packs and sends, one bridge thread reads
calls and runs the handlers, one at a time.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import contextlib
import grp
import hmac
import importlib
import logging
import os
import queue
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import asdict, dataclass, fields
from enum import IntEnum
from pathlib import Path
from typing import Any

import msgpack

log = logging.getLogger("usmswitch.rpc")

#: Bumped when a method, a field or the framing changes incompatibly.
PROTOCOL_VERSION = 1

REQUEST, RESPONSE, NOTIFICATION = 0, 1, 2
MAX_MSGID = 2**32 - 1

#: Methods the server process answers itself, on every connection.
BUILTIN_METHODS = ("ping", "auth", "subscribe", "unsubscribe")
#: Notifications the server itself sends (never published by the daemon).
SERVER_TOPICS = ("dropped", "error")


class ErrorCode(IntEnum):
    """The `code` of an error `[code, message]`; JSON-RPC's numbers for the generic ones."""

    PARSE_ERROR = -32700  # not msgpack, or a frame over the limits: the connection is closed
    INVALID_REQUEST = -32600  # msgpack, but not [0, msgid, method, params]
    UNKNOWN_METHOD = -32601
    INVALID_PARAMS = -32602
    INTERNAL = -32603  # a bug in the daemon; the message says where
    BUSY = 1  # too many outstanding requests, connections or calls in flight: retry later
    UNAUTHORIZED = 2  # TCP without a valid `auth` first
    FAULT = 3  # the rig is in FAULT: reset_fault first
    STATE = 4  # not possible in the current state (e.g. switch while cycling)
    UNAVAILABLE = 5  # not configured or not ready (no drive board, no stats yet, daemon restarting)
    TIMEOUT = 6  # no answer from the daemon within the call timeout, or an idle connection closed
    TOO_LARGE = 7  # a frame or a reply above the limits


class RpcError(Exception):
    """An error the protocol carries as `[code, message]`; handlers raise it to answer with one."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(f"[{int(code)}] {message}")
        self.code = int(code)
        self.message = message

    def to_wire(self) -> list[object]:
        """The `[code, message]` pair of a response's error slot."""
        return [self.code, self.message]


@dataclass(frozen=True, slots=True)
class Limits:
    """Every bound the server enforces; the defaults suit a lab network of a few scripts."""

    max_frame_bytes: int = 65_536  # one incoming frame, and the unparsed buffer per connection
    max_str_len: int = 4_096
    max_bin_len: int = 4_096
    max_array_len: int = 1_024
    max_map_len: int = 64
    max_connections: int = 64  # Unix socket
    max_tcp_connections: int = 8  # TCP, apart: unauthenticated peers cannot take Unix slots
    max_urgent_connections: int = 16  # the estop socket, apart from both
    max_outstanding: int = 32  # per connection: calls waiting for the daemon
    max_forwarded: int = 256  # all connections: calls waiting for the daemon
    max_reads: int = 2  # history reads served from the records file at once (the rest wait)
    max_bad_frames: int = 8  # invalid requests on one connection before it is closed
    idle_timeout_ns: int = 600_000_000_000  # no request, no subscription, nothing outstanding
    auth_timeout_ns: int = 5_000_000_000  # TCP: time to send `auth`
    first_frame_timeout_ns: int = 2_000_000_000  # a new connection that sends no whole frame
    frame_timeout_ns: int = 2_000_000_000  # a frame begun and not finished
    urgent_timeout_ns: int = 250_000_000  # the estop socket: time to send the request
    call_timeout_ns: int = 30_000_000_000  # a forwarded call the daemon does not answer
    subscriber_buffer_bytes: int = 262_144  # unsent bytes above which notifications are dropped
    max_write_buffer_bytes: int = 16_777_216  # unsent bytes above which a connection is aborted
    publish_backlog: int = 4_096  # daemon side: notifications queued for the server process

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"Limits.{f.name} must be a positive integer, got {value!r}")
        if self.max_write_buffer_bytes < self.subscriber_buffer_bytes:
            raise ValueError(
                f"Limits.max_write_buffer_bytes ({self.max_write_buffer_bytes}) must be >= "
                f"subscriber_buffer_bytes ({self.subscriber_buffer_bytes})"
            )


# -- parameters of the documented methods ----------------------------------------------------------

_REQUIRED = object()
_MAX_TARGET_NS = 10_000_000_000
_MAX_PERIOD_NS = 3_600_000_000_000
_MAX_COUNT = 1_000_000_000
MAX_HISTORY = 10_000


def _import(ref: str) -> Callable[[Any], Any]:
    """`package.module:function` -> the function (a snapshot finisher, in the server process)."""
    module, _, name = ref.partition(":")
    return getattr(importlib.import_module(module), name)  # type: ignore[no-any-return]


def estop_socket_path(path: str | os.PathLike[str]) -> Path:
    """The estop socket beside the main one: `usmswitchd.sock` -> `usmswitchd.estop.sock`."""
    p = Path(path)
    return p.with_name(f"{p.stem}.estop{p.suffix}")


def _s(ns: int) -> str:
    """A timeout for people: 2 s, 250 ms."""
    return f"{ns / 1e9:g} s" if ns >= 1_000_000_000 else f"{ns / 1e6:g} ms"


def _show(value: object) -> str:
    """A value for an error message, cut short so an attacker's megabyte is not echoed back."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _integer(name: str, lo: int, hi: int) -> Callable[[str, object], object]:
    def check(method: str, value: object) -> object:
        if type(value) is not int or not lo <= value <= hi:
            raise RpcError(
                ErrorCode.INVALID_PARAMS,
                f"{method}: {name} must be an integer in [{lo}, {hi}], got {_show(value)}",
            )
        return value

    return check


def _choice(name: str, options: tuple[str, ...]) -> Callable[[str, object], object]:
    def check(method: str, value: object) -> object:
        if value not in options or type(value) is not str:
            raise RpcError(
                ErrorCode.INVALID_PARAMS,
                f"{method}: {name} must be one of {list(options)}, got {_show(value)}",
            )
        return value

    return check


def _string(name: str) -> Callable[[str, object], object]:
    def check(method: str, value: object) -> object:
        if type(value) is not str:
            raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: {name} must be a string, got {_show(value)}")
        return value

    return check


def _topics(method: str, value: object) -> object:
    if type(value) is not list or not all(type(t) is str for t in value):
        raise RpcError(
            ErrorCode.INVALID_PARAMS, f"{method}: topics must be an array of strings, got {_show(value)}"
        )
    return value


_DRIVE_KEYS = {"frequency_hz": (1.0, 1e7), "voltage_vpp": (0.0, 1e4)}


def _drive(method: str, value: object) -> object:
    if type(value) is not dict:
        raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: settings must be a map, got {_show(value)}")
    for key, item in value.items():
        if key == "enabled":
            if type(item) is not bool:
                raise RpcError(
                    ErrorCode.INVALID_PARAMS, f"{method}: enabled must be true or false, got {_show(item)}"
                )
        elif key in _DRIVE_KEYS:
            lo, hi = _DRIVE_KEYS[key]
            if type(item) not in (int, float) or not lo <= item <= hi:
                raise RpcError(
                    ErrorCode.INVALID_PARAMS,
                    f"{method}: {key} must be a number in [{lo:g}, {hi:g}], got {_show(item)}",
                )
        else:
            raise RpcError(
                ErrorCode.INVALID_PARAMS,
                f"{method}: unknown setting {_show(key)}; known: enabled, {', '.join(sorted(_DRIVE_KEYS))}",
            )
    return value


_Spec = tuple[tuple[str, Callable[[str, object], object], object], ...]

#: Positional params of every documented method: (name, check, default or _REQUIRED).
PARAMS: dict[str, _Spec] = {
    "ping": (),
    "auth": (("token", _string("token"), _REQUIRED),),
    "status": (),
    "get_target": (),
    "set_target": (
        ("target_ns", _integer("target_ns", 1, _MAX_TARGET_NS), _REQUIRED),
        ("direction", _choice("direction", ("on", "off", "both")), "both"),
    ),
    "stats": (),
    "history": (("n", _integer("n", 1, MAX_HISTORY), 20),),
    "switch": (("direction", _choice("direction", ("on", "off", "next")), "next"),),
    "start_cycling": (
        ("period_ns", _integer("period_ns", 1, _MAX_PERIOD_NS), _REQUIRED),
        ("count", _integer("count", 0, _MAX_COUNT), 0),
    ),
    "stop_cycling": (),
    "set_mode": (
        ("mode", _choice("mode", ("open", "closed")), _REQUIRED),
        ("open_delay_ns", _integer("open_delay_ns", 0, _MAX_TARGET_NS), None),
    ),
    "reset_fault": (),
    "estop": (),
    "set_drive": (("settings", _drive, {}),),
    "subscribe": (("topics", _topics, None),),
    "unsubscribe": (("topics", _topics, None),),
}


def check_params(method: str, params: list[Any]) -> list[Any]:
    """Validate a documented method's params and fill the defaults, so handlers get full lists."""
    spec = PARAMS.get(method)
    if spec is None:
        return params
    if len(params) > len(spec):
        names = ", ".join(name for name, _, _ in spec) or "none"
        raise RpcError(
            ErrorCode.INVALID_PARAMS,
            f"{method} takes at most {len(spec)} params ({names}), got {len(params)}",
        )
    out = []
    for i, (name, check, default) in enumerate(spec):
        if i < len(params):
            out.append(check(method, params[i]))
        elif default is _REQUIRED:
            raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: missing param {i} ({name})")
        else:
            out.append(default)
    return out


def unpacker(limits: Limits) -> msgpack.Unpacker:
    """A streaming decoder that refuses anything above `limits` and every ext type."""
    return msgpack.Unpacker(
        raw=False,
        use_list=True,
        strict_map_key=True,
        max_buffer_size=limits.max_frame_bytes,
        max_str_len=limits.max_str_len,
        max_bin_len=limits.max_bin_len,
        max_array_len=limits.max_array_len,
        max_map_len=limits.max_map_len,
        max_ext_len=0,
    )


_local = threading.local()


def _packb(obj: object) -> bytes:
    """msgpack-encode with this thread's Packer (a Packer is not thread-safe; making one costs ~1 us)."""
    try:
        packer = _local.packer
    except AttributeError:
        packer = _local.packer = msgpack.Packer(use_bin_type=True, autoreset=True)
    return packer.pack(obj)


_NIL = b"\xc0"
_RESPONSE_HEAD = b"\x94\x01"  # fixarray(4), RESPONSE


def _ok(msgid: int, result_bytes: bytes) -> bytes:
    """A success response spliced around an already packed result: no re-encoding per request."""
    return _RESPONSE_HEAD + _packb(msgid) + _NIL + result_bytes


def _err(msgid: int, code: int, message: str) -> bytes:
    return _packb([RESPONSE, msgid, [int(code), message], None])


def _note(topic: str, payload: object) -> bytes:
    return _packb([NOTIFICATION, topic, [payload]])


_PONG = _packb("pong")
_TRUE = _packb(True)

#: Listener kinds of the server process: the Unix socket and TCP (the estop socket is the daemon's).
_KINDS = ("unix", "tcp")
# A refused or timed-out connection is half-closed and kept this long (at most this many at once)
# so that the client reads the reason instead of a reset.
_LINGER_S = 0.5
_MAX_LINGERING = 256
_HISTORY_CHUNK = 200
_readers = threading.local()


def _history_reply(records_path: str, n: int) -> bytes:
    """The last `n` records packed as a msgpack array (a worker thread of the server process).

    Packed a chunk of records per call, so the event loop's thread gets the GIL between chunks
    and an estop or a ping is answered while a large history is being packed.
    """
    from .records import RecordStore, RecordStoreError  # the server process only

    store = getattr(_readers, "store", None)
    if store is None or str(store.path) != records_path:
        try:
            store = _readers.store = RecordStore(records_path, readonly=True)
        except RecordStoreError as exc:
            raise RpcError(ErrorCode.UNAVAILABLE, f"history: {exc}") from None
    records = store.history(n)
    packer = msgpack.Packer(use_bin_type=True, autoreset=True)
    parts = [packer.pack_array_header(len(records))]
    for i in range(0, len(records), _HISTORY_CHUNK):
        parts.append(b"".join(packer.pack(r.to_dict()) for r in records[i : i + _HISTORY_CHUNK]))
    return b"".join(parts)


# -- the server process ----------------------------------------------------------------------------


class _Hub:
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
            self.known |= {"history"}
        self.snaps: dict[str, bytes] = dict(cfg["snaps"])
        # Snapshots the daemon sends unfinished (the loop's stats without their percentiles):
        # finished here, on the first request after each update, so the loop never pays for it.
        self.finishers = {m: _import(ref) for m, ref in cfg["finishers"].items()}
        self.raw_snaps = {m: self.snaps.pop(m) for m in self.finishers if m in self.snaps}
        self.subs: dict[str, set[_Conn]] = {t: set() for t in self.topics}
        self.conns: set[_Conn] = set()
        self.counts = dict.fromkeys(_KINDS, 0)  # open connections per listener kind
        self.lingering = 0  # closed connections still draining their client's last bytes
        self.pending: dict[int, tuple[_Conn, int, int]] = {}  # fid -> (conn, msgid, deadline_ns)
        self.urgent_pending: dict[int, tuple[_Conn, int, int]] = {}
        self.next_fid = 1
        self.lost_seen: int = cfg["lost"]
        self.channel: _Channel | None = None
        self.urgent_channel: _Channel | None = None
        self.done: asyncio.Future[None] = loop.create_future()
        # History is read from the records file here, not in the daemon: the loop's process never
        # reads or packs a large reply. The pool bounds how many reads run at once.
        self.records_path: str | None = cfg["records_path"]
        self.reads = (
            concurrent.futures.ThreadPoolExecutor(self.limits.max_reads, thread_name_prefix="rpc-read")
            if self.records_path
            else None
        )

    def snapshot(self, method: str) -> bytes | None:
        """The packed result of a snapshot method, finished from its raw form when it has to be."""
        snap = self.snaps.get(method)
        if snap is None and method in self.raw_snaps:
            finished = self.finishers[method](msgpack.unpackb(self.raw_snaps[method], raw=False))
            snap = self.snaps[method] = _packb(finished)
        return snap

    def forward(self, conn: _Conn, msgid: int, method: str, params: list[Any]) -> bytes | None:
        """Send a call to the daemon, or return an error response when a bound says no."""
        if conn.outstanding >= self.limits.max_outstanding:
            return _err(
                msgid,
                ErrorCode.BUSY,
                f"{method}: {conn.outstanding} requests outstanding on this connection "
                f"(max {self.limits.max_outstanding}); read the responses first",
            )
        if len(self.pending) >= self.limits.max_forwarded:
            return _err(msgid, ErrorCode.BUSY, f"{method}: daemon busy, {len(self.pending)} calls in flight")
        if self.channel is None:
            return _err(msgid, ErrorCode.UNAVAILABLE, f"{method}: the daemon is not connected")
        fid = self.next_fid
        self.next_fid += 1
        self.pending[fid] = (conn, msgid, time.monotonic_ns() + self.limits.call_timeout_ns)
        conn.outstanding += 1
        self.channel.send(["call", fid, method, params])
        return None

    def forward_urgent(self, conn: _Conn, msgid: int, method: str, params: list[Any]) -> bytes | None:
        """An estop: straight to the daemon's urgent thread, behind nothing, refused by no call limit."""
        if self.urgent_channel is None:
            return _err(msgid, ErrorCode.UNAVAILABLE, f"{method}: the daemon is not connected")
        fid = self.next_fid
        self.next_fid += 1
        self.urgent_pending[fid] = (conn, msgid, time.monotonic_ns() + self.limits.call_timeout_ns)
        self.urgent_channel.send(["call", fid, method, params])
        return None

    def read(self, conn: _Conn, msgid: int, method: str, params: list[Any]) -> bytes | None:
        """A history read, served from the records file by a worker thread of this process."""
        if conn.outstanding >= self.limits.max_outstanding:
            return _err(
                msgid,
                ErrorCode.BUSY,
                f"{method}: {conn.outstanding} requests outstanding on this connection "
                f"(max {self.limits.max_outstanding}); read the responses first",
            )
        assert self.reads is not None and self.records_path is not None
        conn.outstanding += 1
        fut = self.loop.run_in_executor(self.reads, _history_reply, self.records_path, params[0])

        def done(fut: asyncio.Future[bytes]) -> None:
            conn.outstanding -= 1
            exc = fut.exception()
            if exc is None:
                conn.write(_ok(msgid, fut.result()))
            elif isinstance(exc, RpcError):
                conn.write(_err(msgid, exc.code, exc.message))
            else:
                log.error("rpc: history read failed: %s", exc)
                conn.write(_err(msgid, ErrorCode.INTERNAL, f"{method}: {type(exc).__name__}: {exc}"))

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
                conn.write(_ok(msgid, result_bytes))
            else:
                conn.write(_err(msgid, error[0], error[1]))
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
                        _err(
                            msgid,
                            ErrorCode.TIMEOUT,
                            f"no answer from the daemon in {_s(lim.call_timeout_ns)}",
                        )
                    )
        for conn in list(self.conns):
            if conn.partial_since_ns is not None and now - conn.partial_since_ns > lim.frame_timeout_ns:
                conn.fatal(
                    ErrorCode.TIMEOUT, f"a frame begun and not finished within {_s(lim.frame_timeout_ns)}"
                )
            elif not conn.frames and now - conn.born_ns > conn.first_frame_timeout_ns:
                conn.fatal(
                    ErrorCode.TIMEOUT, f"no request within {_s(conn.first_frame_timeout_ns)} of connecting"
                )
            elif not conn.authed and now - conn.born_ns > lim.auth_timeout_ns:
                conn.fatal(ErrorCode.UNAUTHORIZED, f"no auth within {_s(lim.auth_timeout_ns)}")
            elif not conn.topics and not conn.outstanding and now - conn.last_req_ns > lim.idle_timeout_ns:
                conn.fatal(ErrorCode.TIMEOUT, f"idle for more than {_s(lim.idle_timeout_ns)}")


class _Channel(asyncio.Protocol):
    """The server process's end of the daemon channel (trusted: the daemon is our parent)."""

    def __init__(self, hub: _Hub, urgent: bool = False) -> None:
        self.hub = hub
        self.urgent = urgent
        self.unpacker = msgpack.Unpacker(raw=False, max_buffer_size=1 << 30)
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
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
        self.transport.write(_packb(obj))


class _Conn(asyncio.Protocol):
    """One client connection: decode, validate, dispatch, and throttle its notifications."""

    def __init__(self, hub: _Hub, kind: str) -> None:
        self.hub = hub
        self.kind = kind
        self.tcp = kind == "tcp"
        self.unpacker = unpacker(hub.limits)
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

    # asyncio callbacks
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        limits = self.hub.limits
        most = limits.max_tcp_connections if self.tcp else limits.max_connections
        if self.hub.counts[self.kind] >= most:
            where = "TCP" if self.tcp else "Unix socket"
            self.fatal(ErrorCode.BUSY, f"too many connections on the {where} (max {most}); try again later")
            return
        self.hub.conns.add(self)
        self.hub.counts[self.kind] += 1
        self.counted = True
        transport.set_write_buffer_limits(high=limits.subscriber_buffer_bytes)

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        self._uncount()
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
        try:
            self.unpacker.feed(data)
        except msgpack.BufferFull:
            self.fatal(ErrorCode.TOO_LARGE, f"frame larger than {self.hub.limits.max_frame_bytes} bytes")
            return
        self.fed += len(data)
        out: list[bytes] = []
        try:
            for msg in self.unpacker:
                self.frames += 1
                self.frames_end = self.unpacker.tell()  # exact here; past a partial frame after
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
        self.last_req_ns = time.monotonic_ns()
        if not self.authed and method != "auth":
            self.fatal(ErrorCode.UNAUTHORIZED, "this TCP connection must send auth [token] first", msgid)
            return None
        try:
            if method not in self.hub.known:
                raise RpcError(
                    ErrorCode.UNKNOWN_METHOD,
                    f"unknown method {_show(method)}; known: {', '.join(sorted(self.hub.known))}",
                )
            if method in PARAMS:
                params = check_params(method, params)
            if method == "ping":
                return _ok(msgid, _PONG)
            if method in self.hub.urgent:
                return self.hub.forward_urgent(self, msgid, method, params)
            if method == "history" and self.hub.reads is not None:
                return self.hub.read(self, msgid, method, params)
            snap = self.hub.snapshot(method)
            if snap is not None and not params:
                return _ok(msgid, snap)
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
            return _err(msgid, exc.code, exc.message)
        except Exception as exc:  # a bug here must cost one request, not the server
            log.exception("rpc: %s failed", _show(method))
            return _err(msgid, ErrorCode.INTERNAL, f"{method}: internal error: {type(exc).__name__}")

    def _bad(self, msg: object, msgid: int | None = None) -> bytes | None:
        self.bad_frames += 1
        if msgid is None and type(msg) is list and len(msg) >= 2 and msg[0] == REQUEST:
            candidate = msg[1]
            if type(candidate) is int and 0 <= candidate <= MAX_MSGID:
                msgid = candidate
        text = f"expected [0, msgid (uint32), method (str), params (array)], got {_show(msg)}"
        if self.bad_frames > self.hub.limits.max_bad_frames:
            self.fatal(ErrorCode.INVALID_REQUEST, f"too many invalid requests; last: {text}", msgid)
            return None
        if msgid is None:
            return _note("error", [int(ErrorCode.INVALID_REQUEST), text])
        return _err(msgid, ErrorCode.INVALID_REQUEST, text)

    def _auth(self, msgid: int, token: str) -> bytes | None:
        if not self.tcp or self.hub.token is None:
            return _ok(msgid, _TRUE)
        if hmac.compare_digest(token.encode(), self.hub.token.encode()):
            self.authed = True
            return _ok(msgid, _TRUE)
        self.fatal(ErrorCode.UNAUTHORIZED, "wrong token", msgid)
        return None

    def _subscribe(self, msgid: int, topics: list[str] | None, on: bool) -> bytes:
        wanted = self.hub.topics if topics is None else topics
        for topic in wanted:
            if topic not in self.hub.subs:
                raise RpcError(
                    ErrorCode.INVALID_PARAMS,
                    f"unknown topic {_show(topic)}; known: {', '.join(self.hub.topics)}",
                )
        for topic in wanted:
            if on:
                self.hub.subs[topic].add(self)
                self.topics.add(topic)
            else:
                self.hub.subs[topic].discard(self)
                self.topics.discard(topic)
        return _ok(msgid, _packb({"topics": sorted(self.topics), "dropped": self.drop_total}))

    # output
    def write(self, data: bytes) -> None:
        """Queue bytes; a client that lets replies pile up past the hard limit is cut off."""
        if self.closed or self.transport is None:
            return
        self.transport.write(data)
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
        self.write(_note("dropped", {"count": count, "total": self.drop_total}))

    def fatal(self, code: int, message: str, msgid: int | None = None) -> None:
        """Say why (a response when there is a msgid, else an "error" notification), then close."""
        if self.closed or self.transport is None:
            return
        frame = _note("error", [int(code), message]) if msgid is None else _err(msgid, code, message)
        transport = self.transport
        transport.write(frame)
        self.closed = True
        self._uncount()
        hub = self.hub
        if transport.can_write_eof() and hub.lingering < _MAX_LINGERING:
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
            self.hub.counts[self.kind] -= 1


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
    hub = _Hub(cfg, loop)
    await loop.connect_accepted_socket(lambda: _Channel(hub), sock=chan)
    await loop.connect_accepted_socket(lambda: _Channel(hub, urgent=True), sock=urgent_chan)
    servers = []
    for sock, kind in listeners:
        # create_server, not create_unix_server: the latter unlinks the path on close (3.13+),
        # and the socket file belongs to the daemon, which outlives this process.
        servers.append(await loop.create_server(lambda kind=kind: _Conn(hub, kind), sock=sock))
    assert hub.channel is not None
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
        for conn in list(hub.conns):
            if conn.transport is not None:
                conn.transport.abort()
        if hub.reads is not None:
            hub.reads.shutdown(wait=False, cancel_futures=True)


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
    if nice:
        os.nice(nice)
    socks = [(socket.socket(fileno=fd), kind) for fd, kind in listeners]
    for sock, _ in socks:
        sock.setblocking(False)
    chan.setblocking(False)
    urgent = socket.socket(fileno=urgent_fd)
    urgent.setblocking(False)
    asyncio.run(_serve(chan, urgent, socks, cfg))


# -- the daemon side -------------------------------------------------------------------------------


@dataclass(slots=True)
class _Link:
    """One running server process (or thread) and the daemon's end of its channel."""

    gen: int
    sock: socket.socket
    urgent: socket.socket  # estop and the like: served by a thread of their own, behind nothing
    feed: msgpack.Unpacker
    proc: subprocess.Popen[bytes] | None
    thread: threading.Thread | None
    started_ns: int


class RpcServer:
    """The daemon's socket front: serves clients from a separate process, calls `handlers` here.

    `handlers[method](params)` runs in one bridge thread, one call at a time, with params already
    validated against docs/protocol.md (defaults filled). It returns a msgpack-able result, raises
    `RpcError`, or returns a `concurrent.futures.Future` the loop resolves later (e.g. `switch`:
    the record of the stroke). Keep handlers short: they share the GIL with the control loop.

    `urgent[method](params)` (estop) runs in a thread of its own, reached over a channel of its own:
    no other call, however many or slow, is ahead of it, and no call limit refuses it. It must
    return its result directly. `urgent_path` binds a socket that takes only these and ping, with
    its own connection limit, so a flood on the main socket cannot lock an estop out.
    `records_path` lets the server process answer `history` from the records file itself.
    """

    def __init__(
        self,
        handlers: Mapping[str, Callable[[list[Any]], object]],
        *,
        unix_path: str | os.PathLike[str],
        urgent: Mapping[str, Callable[[list[Any]], object]] | None = None,
        urgent_path: str | os.PathLike[str] | None = None,
        records_path: str | os.PathLike[str] | None = None,
        mode: int = 0o660,
        group: str | int | None = None,
        tcp: tuple[str, int] | None = None,
        tcp_token: str | None = None,
        limits: Limits | None = None,
        topics: Iterable[str] = ("stroke", "state"),
        snapshot_methods: Iterable[str] = (),
        snapshot_finishers: Mapping[str, str] | None = None,
        isolation: str = "process",
        nice: int = 5,
        max_restarts: int = 5,
    ) -> None:
        urgent = dict(urgent or {})
        for name, handler in [*handlers.items(), *urgent.items()]:
            if type(name) is not str or not callable(handler):
                raise ValueError(f"handlers must map method names to callables, got {name!r}: {handler!r}")
            if name in BUILTIN_METHODS:
                raise ValueError(f"handler {name!r} clashes with a method the server answers itself")
        if set(urgent) & set(handlers):
            raise ValueError(f"methods {sorted(set(urgent) & set(handlers))} are both urgent and not")
        if urgent_path is not None and not urgent:
            raise ValueError("urgent_path needs urgent handlers to serve")
        if isinstance(mode, bool) or not isinstance(mode, int) or not 0 <= mode <= 0o777:
            raise ValueError(f"mode must be permission bits in [0, 0o777], got {mode!r}")
        if tcp is not None:
            if not (
                isinstance(tcp, tuple) and len(tcp) == 2 and isinstance(tcp[0], str) and type(tcp[1]) is int
            ):
                raise ValueError(f"tcp must be (host, port), got {tcp!r}")
            if not 0 <= tcp[1] <= 65_535:
                raise ValueError(f"tcp port must be in [0, 65535], got {tcp[1]!r}")
            if not isinstance(tcp_token, str) or len(tcp_token) < 16:
                raise ValueError("tcp_token must be a string of at least 16 characters when tcp is set")
        if isolation not in ("process", "thread"):
            raise ValueError(f"isolation must be 'process' or 'thread', got {isolation!r}")
        if isinstance(nice, bool) or not isinstance(nice, int) or not 0 <= nice <= 19:
            raise ValueError(f"nice must be an integer in [0, 19], got {nice!r}")
        self.topics = tuple(topics)
        for topic in self.topics:
            if type(topic) is not str or topic in SERVER_TOPICS:
                raise ValueError(f"topic {topic!r} is not a name the daemon may publish")
        self.handlers = dict(handlers)
        self.urgent = urgent
        self.snapshot_methods = frozenset(snapshot_methods)
        #: method -> "module:function" the server process applies to that snapshot before serving it.
        self.snapshot_finishers = dict(snapshot_finishers or {})
        if set(self.snapshot_finishers) - self.snapshot_methods:
            raise ValueError("snapshot_finishers must name snapshot methods")
        self.unix_path = Path(unix_path)
        self.urgent_path = None if urgent_path is None else Path(urgent_path)
        self.records_path = None if records_path is None else Path(records_path)
        self.mode = mode
        self.gid = _resolve_group(group)
        self.tcp = tcp
        self.tcp_token = tcp_token
        self.limits = limits or Limits()
        self.isolation = isolation
        self.nice = nice
        self.max_restarts = max_restarts
        #: Where TCP listens once started (the port resolved when 0 was asked).
        self.tcp_address: tuple[str, int] | None = None
        #: Called by the bridge and writer threads before each piece of work: the daemon makes it
        #: wait while the loop is about to start a stroke (they share the GIL). Urgent calls never wait.
        self.gate: Callable[[], object] = lambda: None
        #: Counters for status and logs.
        self.published = 0
        self.lost = 0  # notifications dropped because the backlog to the server process was full
        self.restarts = 0
        self._listeners: list[tuple[socket.socket, str]] = []
        #: The bound estop socket (None without urgent_path): the daemon serves it itself.
        self.urgent_listener: socket.socket | None = None
        #: Stopped, in order, before the sockets close (the estop socket's server).
        self.companions: list[Any] = []
        self._unix_inos: dict[Path, int] = {}
        self._out: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self._snaps: dict[str, object] = {}
        self._snap_pending: set[str] = set()
        self._link: _Link | None = None
        self._gen = 0
        self._stopping = False
        self._started = False
        # One longer than the limit, so that "more than max_restarts in a minute" can be seen.
        self._restart_times: deque[int] = deque(maxlen=max_restarts + 1)
        self._threads: list[threading.Thread] = []

    # -- public API, called by the daemon --------------------------------------------------------
    def start(self) -> None:
        """Bind the sockets (errors name the path or address), start the server process, serve."""
        if self._started:
            raise RuntimeError("RpcServer already started")
        self._started = True
        try:
            self._listeners.append((self._bind_unix(self.unix_path), "unix"))
            if self.urgent_path is not None:
                # Bound here (mode, group, stale-socket checks as the main one); served in this
                # process by daemon/estop_socket.py, which the daemon starts on it.
                self.urgent_listener = self._bind_unix(self.urgent_path)
            if self.tcp is not None:
                tsock = socket.create_server(self.tcp, backlog=128)
                self.tcp_address = tsock.getsockname()[:2]
                self._listeners.append((tsock, "tcp"))
            self._link = self._spawn()
        except BaseException:
            self._close_listeners()
            raise
        for target, name in ((self._writer, "rpc-writer"), (self._bridge, "rpc-bridge")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def publish(self, topic: str, payload: object) -> bool:
        """Notify subscribers of `topic`; O(1), never blocks; False when dropped (backlog full).

        The server takes `payload` as is: do not mutate it afterwards.
        """
        if topic not in self.topics:
            raise ValueError(f"unknown topic {topic!r}; declared: {', '.join(self.topics)}")
        if self._out.qsize() >= self.limits.publish_backlog or self._stopping:
            self.lost += 1
            return False
        self._out.put(("note", topic, payload))
        self.published += 1
        return True

    def snapshot(self, method: str, result: object) -> None:
        """Set what `method []` returns, answered by the server process without calling the daemon.

        O(1), never blocks; snapshots set faster than they are sent coalesce to the latest. Those
        set before `start()` are served from the first request; later ones a moment after the call.
        """
        if method not in self.snapshot_methods:
            raise ValueError(
                f"{method!r} is not in snapshot_methods ({', '.join(sorted(self.snapshot_methods))})"
            )
        self._snaps[method] = result
        if method not in self._snap_pending:
            self._snap_pending.add(method)
            self._out.put(("snap", method))

    @property
    def alive(self) -> bool:
        """True while a server process (or thread) is serving."""
        link = self._link
        if link is None:
            return False
        if link.proc is not None:
            return link.proc.poll() is None
        return link.thread is not None and link.thread.is_alive()

    @property
    def server_pid(self) -> int | None:
        """The server process's pid (None in thread isolation or before start)."""
        link = self._link
        return link.proc.pid if link is not None and link.proc is not None else None

    def stop(self) -> None:
        """Stop serving: close every connection, end the server process, remove the socket file."""
        if not self._started or self._stopping:
            return
        self._stopping = True
        for companion in self.companions:
            companion.stop()
        self._out.put(("stop",))
        link = self._link
        if link is not None:
            self._end_link(link)
        for thread in self._threads:
            thread.join(timeout=5)
        if link is not None:
            link.sock.close()
            link.urgent.close()
        self._close_listeners()

    def __enter__(self) -> RpcServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- sockets ---------------------------------------------------------------------------------
    def _bind_unix(self, path: Path) -> socket.socket:
        if path.is_symlink() or path.exists():
            if not stat.S_ISSOCK(os.lstat(path).st_mode):
                raise RuntimeError(f"{path} exists and is not a socket; refusing to replace it")
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            probe.settimeout(1.0)
            try:
                probe.connect(str(path))
            except (ConnectionRefusedError, FileNotFoundError):
                path.unlink(missing_ok=True)  # stale: left by a daemon that died
            else:
                raise RuntimeError(f"another server is listening on {path}")
            finally:
                probe.close()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(str(path))
        except OSError as exc:
            sock.close()
            raise OSError(exc.errno, f"cannot bind the RPC socket {path}: {exc.strerror}") from exc
        try:
            # Bound with the process umask; restricted before listen(), so no client connects earlier.
            os.chmod(path, self.mode)
            if self.gid is not None:
                os.chown(path, -1, self.gid)
            sock.listen(128)
        except OSError as exc:
            sock.close()
            path.unlink(missing_ok=True)
            raise OSError(exc.errno, f"cannot set up the RPC socket {path}: {exc.strerror}") from exc
        self._unix_inos[path] = os.stat(path).st_ino
        return sock

    def _close_listeners(self) -> None:
        for sock, _ in self._listeners:
            sock.close()
        self._listeners.clear()
        if self.urgent_listener is not None:
            self.urgent_listener.close()
            self.urgent_listener = None
        for path, ino in self._unix_inos.items():
            with contextlib.suppress(OSError):
                if os.stat(path).st_ino == ino:  # still ours: not replaced by a newer daemon
                    path.unlink()
        self._unix_inos.clear()

    # -- the server process ------------------------------------------------------------------------
    def _config(self) -> dict[str, Any]:
        return {
            "limits": asdict(self.limits),
            "token": self.tcp_token if self.tcp is not None else None,
            "handlers": sorted(self.handlers),
            "urgent": sorted(self.urgent),
            "records_path": None if self.records_path is None else str(self.records_path),
            "snapshot_methods": sorted(self.snapshot_methods),
            "finishers": self.snapshot_finishers,
            "topics": list(self.topics),
            "lost": self.lost,
            # Snapshots set so far are served from the first request (and after a restart).
            "snaps": {method: _packb(value) for method, value in list(self._snaps.items())},
        }

    def _spawn(self) -> _Link:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        u_ours, u_theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        self._gen += 1
        proc = thread = None
        try:
            if self.isolation == "process":
                cmd = [sys.executable, "-m", "usmswitch.daemon.rpc", "--channel", str(theirs.fileno())]
                cmd += ["--urgent-channel", str(u_theirs.fileno())]
                for sock, kind in self._listeners:
                    cmd += ["--listen", f"{sock.fileno()}:{kind}"]
                cmd += ["--nice", str(self.nice)]
                fds = [theirs.fileno(), u_theirs.fileno()] + [sock.fileno() for sock, _ in self._listeners]
                proc = subprocess.Popen(cmd, pass_fds=fds, stdin=subprocess.DEVNULL)
                theirs.close()
                u_theirs.close()
            else:
                listeners = [(os.dup(sock.fileno()), kind) for sock, kind in self._listeners]
                thread = threading.Thread(
                    target=serve,
                    args=(theirs.detach(), u_theirs.detach(), listeners),
                    name="rpc-server",
                    daemon=True,
                )
                thread.start()
            cfg = _packb(self._config())
            ours.sendall(len(cfg).to_bytes(4, "big") + cfg)
            link = _Link(
                self._gen,
                ours,
                u_ours,
                msgpack.Unpacker(raw=False, max_buffer_size=1 << 24),
                proc,
                thread,
                time.monotonic_ns(),
            )
            self._await_ready(link)
        except BaseException:
            ours.close()
            u_ours.close()
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
            raise
        # Snapshots set while the process started may have missed the config: send them again.
        for method in list(self._snaps):
            if method not in self._snap_pending:
                self._snap_pending.add(method)
                self._out.put(("snap", method))
        urgent = threading.Thread(target=self._serve_urgent, args=(link,), name="rpc-urgent", daemon=True)
        urgent.start()
        return link

    def _await_ready(self, link: _Link) -> None:
        link.sock.settimeout(30.0)
        try:
            while True:
                data = link.sock.recv(65_536)
                if not data:
                    code = link.proc.wait() if link.proc is not None else None
                    raise RuntimeError(f"the RPC server process exited during start-up (exit status {code})")
                link.feed.feed(data)
                for msg in link.feed:
                    if msg[0] == "ready":
                        return
        except TimeoutError as exc:
            raise RuntimeError("the RPC server process did not start within 30 s") from exc
        finally:
            link.sock.settimeout(None)

    def _end_link(self, link: _Link) -> None:
        if link.proc is not None:
            try:
                link.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                link.proc.kill()
                link.proc.wait()
        elif link.thread is not None:
            link.thread.join(timeout=5)
        with contextlib.suppress(OSError):
            link.sock.shutdown(socket.SHUT_RDWR)

    def _respawn(self, old: _Link) -> _Link | None:
        """Replace a server process that died; give up after too many deaths in a minute."""
        if old.proc is not None:
            old.proc.wait()
        old.sock.close()
        old.urgent.close()
        now = time.monotonic_ns()
        self._restart_times.append(now)
        recent = [t for t in self._restart_times if now - t < 60_000_000_000]
        if len(recent) > self.max_restarts:
            log.error("rpc: server process died %d times in a minute; no longer serving", len(recent))
            return None
        log.warning(
            "rpc: server process died (exit %s); restarting", old.proc.returncode if old.proc else "-"
        )
        self.restarts += 1
        try:
            return self._spawn()
        except (OSError, RuntimeError):
            log.exception("rpc: cannot restart the server process")
            return None

    # -- daemon-side threads -----------------------------------------------------------------------
    def _writer(self) -> None:
        """The only writer of the channel: packs here, so publish() costs the loop one append."""
        out = self._out
        while True:
            item = out.get()
            self.gate()
            kind = item[0]
            link = self._link
            try:
                if kind == "note":
                    data = _packb(["note", item[1], _note(item[1], item[2]), self.lost])
                elif kind == "snap":
                    self._snap_pending.discard(item[1])
                    data = _packb(["snap", item[1], _packb(self._snaps[item[1]])])
                elif kind == "resp":
                    _, gen, fid, error, result = item
                    if link is None or gen != link.gen:
                        continue  # the process that asked is gone
                    try:
                        data = _packb(["resp", fid, error, _packb(result)])
                    except (TypeError, ValueError, OverflowError) as exc:
                        data = _packb(
                            ["resp", fid, [int(ErrorCode.INTERNAL), f"result not msgpack-able: {exc}"], None]
                        )
                elif kind == "stop":
                    if link is not None:
                        with contextlib.suppress(OSError):
                            link.sock.sendall(_packb(["stop"]))
                    return
                else:
                    continue
            except (TypeError, ValueError, OverflowError) as exc:
                log.error("rpc: cannot pack %s %r: %s", kind, item[1], exc)
                continue
            if link is None:
                continue
            try:
                link.sock.sendall(data)
            except OSError:
                if kind == "note":
                    self.lost += 1

    def _bridge(self) -> None:
        """Read calls from the server process and run the handlers; respawn it if it dies."""
        while not self._stopping:
            link = self._link
            if link is None:
                return
            try:
                data = link.sock.recv(262_144)
            except OSError:
                data = b""
            if not data:
                if self._stopping:
                    return
                self._link = self._respawn(link)
                continue
            link.feed.feed(data)
            for msg in link.feed:
                if msg[0] == "call":
                    self.gate()
                    self._call(link.gen, msg[1], msg[2], msg[3])

    def _serve_urgent(self, link: _Link) -> None:
        """One link's urgent calls, each answered from this thread as soon as it is done."""
        feed = msgpack.Unpacker(raw=False, max_buffer_size=1 << 20)
        packer = msgpack.Packer(use_bin_type=True, autoreset=True)
        while True:
            try:
                data = link.urgent.recv(65_536)
            except OSError:
                return
            if not data:
                return
            feed.feed(data)
            for msg in feed:
                if msg[0] != "call":
                    continue
                _, fid, method, params = msg
                error = result = None
                try:
                    result = self.urgent[method](params)
                except RpcError as exc:
                    error = exc.to_wire()
                except Exception as exc:
                    log.exception("rpc: urgent handler %s failed", method)
                    error = [int(ErrorCode.INTERNAL), f"{method}: internal error: {type(exc).__name__}"]
                try:
                    link.urgent.sendall(packer.pack(["resp", fid, error, packer.pack(result)]))
                except OSError:
                    return

    def _call(self, gen: int, fid: int, method: str, params: list[Any]) -> None:
        error = result = None
        try:
            result = self.handlers[method](params)
        except RpcError as exc:
            error = exc.to_wire()
        except Exception as exc:
            log.exception("rpc: handler %s failed", method)
            error = [int(ErrorCode.INTERNAL), f"{method}: internal error: {type(exc).__name__}: {exc}"]
        if isinstance(result, Future):
            result.add_done_callback(lambda fut: self._finish(gen, fid, method, fut))
            return
        self._out.put(("resp", gen, fid, error, result))

    def _finish(self, gen: int, fid: int, method: str, fut: Future[Any]) -> None:
        error = result = None
        if fut.cancelled():
            error = [int(ErrorCode.UNAVAILABLE), f"{method}: cancelled"]
        elif (exc := fut.exception()) is not None:
            if isinstance(exc, RpcError):
                error = exc.to_wire()
            else:
                error = [int(ErrorCode.INTERNAL), f"{method}: internal error: {type(exc).__name__}: {exc}"]
        else:
            result = fut.result()
        self._out.put(("resp", gen, fid, error, result))


def _resolve_group(group: str | int | None) -> int | None:
    if group is None:
        return None
    if isinstance(group, bool):
        raise ValueError(f"group must be a name or a gid, got {group!r}")
    if isinstance(group, int):
        if group < 0:
            raise ValueError(f"group gid must be >= 0, got {group!r}")
        return group
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise ValueError(f"group {group!r} does not exist") from None


def main(argv: list[str] | None = None) -> int:
    """Entry of the server process the daemon spawns (not a command for people)."""
    parser = argparse.ArgumentParser(prog="usmswitch.daemon.rpc", description=__doc__.splitlines()[0])
    parser.add_argument("--channel", type=int, required=True, help="fd of the socketpair to the daemon")
    parser.add_argument("--urgent-channel", type=int, required=True, help="fd of the estop socketpair")
    parser.add_argument(
        "--listen", action="append", default=[], help="FD:unix, FD:tcp or FD:urgent, a listening socket"
    )
    parser.add_argument("--nice", type=int, default=0)
    args = parser.parse_args(argv)
    # The daemon owns shutdown: a Ctrl-C to the terminal's process group or systemd's SIGTERM to the
    # cgroup must not kill the server under it mid-stop. It ends when the daemon's channel closes.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # a closed terminal: the daemon decides
    # A reader thread packing a long history gives the GIL back to the event loop this often
    # (set here, in the process of its own, not in serve(), which a test may run in a thread).
    sys.setswitchinterval(0.0005)
    listeners = []
    for spec in args.listen:
        fd, _, kind = spec.partition(":")
        if kind not in _KINDS or not fd.isdigit():
            parser.error(f"--listen must be FD:unix, FD:tcp or FD:urgent, got {spec!r}")
        listeners.append((int(fd), kind))
    serve(args.channel, args.urgent_channel, listeners, args.nice)
    return 0


if __name__ == "__main__":
    sys.exit(main())
