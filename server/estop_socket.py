"""The estop socket: `estop` and `ping` only, served in the daemon by one thread of its own.

Beside the main socket (`usmswitchd.sock` -> `usmswitchd.estop.sock`, same mode and group). Not in
the socket's server process: an estop here takes no process hop and waits behind nothing, however
busy that process is (a connection flood, large history replies), and the thread runs at the
daemon's helper priority. What an attacker can do to it is bounded: a few connections
(`Limits.max_urgent_connections`), frames of a few hundred bytes, a request within
`Limits.urgent_timeout_ns` of connecting and a frame finished within `Limits.frame_timeout_ns`.
Every connection is accepted and read the moment it comes (an estop cannot be told from the rest
before it is read); closing connections that timed out waits its turn behind the loop's start (`gate`).
"""

from __future__ import annotations

import contextlib
import logging
import selectors
import socket
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import msgpack

from usmswitch.protocol.rpc_params import check_params
from usmswitch.protocol.wire import MAX_MSGID, NOTIFICATION, REQUEST, RESPONSE, ErrorCode, Limits, RpcError
from usmswitch.runtime.realtime import name_thread
from usmswitch.server.after_reply import run_afters, split

log = logging.getLogger("usmswitch.rpc")

MAX_FRAME_BYTES = 512
#: The thread's name, in Python and as the kernel shows it (ps -L).
THREAD_NAME = "rpc-estop"
_TICK_S = 0.05  # deadlines are checked at least this often


class _Peer:
    __slots__ = ("deadline_ns", "fed", "frames", "frames_end", "last_ns", "sock", "unpacker")

    def __init__(self, sock: socket.socket, now_ns: int, deadline_ns: int) -> None:
        self.sock = sock
        self.unpacker = msgpack.Unpacker(raw=False, max_buffer_size=MAX_FRAME_BYTES, max_ext_len=0)
        self.deadline_ns = deadline_ns
        self.last_ns = now_ns  # connected, or its last request answered: the shedding order
        self.fed = self.frames = self.frames_end = 0


class EstopSocket:
    """Serve `handlers` (the urgent methods) and ping on a bound, listening Unix socket."""

    def __init__(
        self,
        sock: socket.socket,
        handlers: Mapping[str, Callable[[list[Any]], object]],
        limits: Limits,
        gate: Callable[[], object] = lambda: None,
    ) -> None:
        self.sock = sock
        self.handlers = dict(handlers)
        self.limits = limits
        self.gate = gate
        self._peers: dict[socket.socket, _Peer] = {}
        self._wake_r, self._wake_w = socket.socketpair()
        self._stopping = False
        self._shed = 0  # connections shed for newcomers, since start
        self._shed_logged_ns = 0
        self._thread = threading.Thread(target=self._run, name=THREAD_NAME, daemon=True)

    def start(self) -> None:
        self.sock.setblocking(False)
        self._thread.start()

    def stop(self) -> None:
        self._stopping = True
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._thread.join(5)
        for peer in list(self._peers.values()):
            peer.sock.close()
        self._peers.clear()
        self._wake_r.close()
        self._wake_w.close()

    # -- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        name_thread(THREAD_NAME)
        sel = selectors.DefaultSelector()
        sel.register(self.sock, selectors.EVENT_READ, None)
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        try:
            while not self._stopping:
                for key, _ in sel.select(_TICK_S):
                    if key.data == "wake":
                        continue
                    if key.data is None:
                        self._accept(sel)
                    else:
                        self._read(sel, key.data)
                self._sweep(sel)
        except Exception:  # a bug here must not take the daemon down; the main socket still serves
            log.exception("rpc: the estop socket's thread failed; estop remains on the main socket")
        finally:
            sel.close()

    def _accept(self, sel: selectors.BaseSelector) -> None:
        # Every pending connection is taken at once and its request read, an estop answered: the
        # only way to find an estop is to read it, so none waits behind the connections ahead of
        # it in the backlog, silent or not (32 one-byte holders, renewed, each made the next accept
        # wait the loop's start: an estop behind them, p99 7.8 ms). An accept and a read are a few
        # tens of microseconds, each a system call that lets the loop have the GIL; the backlog
        # (1024) and the attacker's own connects bound the round. What is more than reading (the
        # timeouts' closes) still waits its turn behind the loop's start, in `_sweep`.
        while True:
            try:
                conn, _ = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # out of descriptors: the backlog waits for the next round
                log.warning("rpc: estop socket accept failed: %s", exc)
                return
            most = self.limits.max_urgent_connections
            if len(self._peers) >= most:
                # Every peer here is idle between requests (each is answered at once), so the
                # one idle longest gives way: holders cannot lock a new estop out. A newcomer is
                # never the one shed.
                oldest = min(self._peers.values(), key=lambda p: p.last_ns)
                self._close(
                    sel,
                    oldest,
                    ErrorCode.BUSY,
                    f"too many connections on the estop socket (max {most}):"
                    " this one, idle longest, gave way",
                )
                self._shed += 1
                self._log_shed(most)
            conn.setblocking(False)
            now = time.monotonic_ns()
            peer = _Peer(conn, now, now + self.limits.urgent_timeout_ns)
            self._peers[conn] = peer
            sel.register(conn, selectors.EVENT_READ, peer)
            self._read(sel, peer)  # its request is often there already: answered before more accepts

    def _log_shed(self, most: int) -> None:
        now = time.monotonic_ns()
        if now - self._shed_logged_ns >= 10_000_000_000:  # one line per 10 s, however many
            self._shed_logged_ns = now
            log.warning("rpc: estop socket full (max %d): idle connections shed, %d so far", most, self._shed)

    def _read(self, sel: selectors.BaseSelector, peer: _Peer) -> None:
        try:
            data = peer.sock.recv(MAX_FRAME_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop(sel, peer)
            return
        try:
            peer.unpacker.feed(data)
        except msgpack.BufferFull:
            self._close(sel, peer, ErrorCode.TOO_LARGE, f"frame larger than {MAX_FRAME_BYTES} bytes")
            return
        peer.fed += len(data)
        afters: list[Callable[[], None]] = []
        try:
            self._answer_all(sel, peer, afters)
        finally:
            run_afters(afters)  # the estops' work after their replies, also when none got out

    def _answer_all(self, sel: selectors.BaseSelector, peer: _Peer, afters: list[Callable[[], None]]) -> None:
        out = []
        try:
            for msg in peer.unpacker:
                peer.frames += 1
                peer.frames_end = peer.unpacker.tell()
                out.append(self._answer(msg, afters))
        except Exception as exc:  # undecodable: the stream cannot be resynchronised
            self._close(sel, peer, ErrorCode.PARSE_ERROR, f"undecodable msgpack: {type(exc).__name__}")
            return
        now = time.monotonic_ns()
        lim = self.limits
        if out:
            peer.last_ns = now
        partial = peer.frames_end < peer.fed
        peer.deadline_ns = now + (lim.frame_timeout_ns if partial else lim.idle_timeout_ns)
        if out:
            try:
                peer.sock.sendall(b"".join(out))  # a few dozen bytes: fits any socket buffer
            except OSError:
                self._drop(sel, peer)

    def _answer(self, msg: object, afters: list[Callable[[], None]]) -> bytes:
        if type(msg) is not list or len(msg) != 4 or msg[0] != REQUEST:
            return _note(ErrorCode.INVALID_REQUEST, "expected [0, msgid, method, params]")
        _, msgid, method, params = msg
        if type(msgid) is not int or not 0 <= msgid <= MAX_MSGID or type(params) is not list:
            return _note(
                ErrorCode.INVALID_REQUEST, "expected [0, msgid (uint32), method (str), params (array)]"
            )
        try:
            if method == "ping":
                return _reply(msgid, None, "pong")
            if method not in self.handlers:
                raise RpcError(
                    ErrorCode.UNKNOWN_METHOD,
                    f"the estop socket takes only {', '.join(sorted(self.handlers))} and ping,"
                    f" got {method!r:.40}",
                )
            result, then = split(self.handlers[method](check_params(method, params)))
            afters.extend(then)
            return _reply(msgid, None, result)
        except RpcError as exc:
            return _reply(msgid, exc.to_wire(), None)
        except Exception as exc:
            log.exception("rpc: estop socket handler %s failed", method)
            return _reply(
                msgid, [int(ErrorCode.INTERNAL), f"{method}: internal error: {type(exc).__name__}"], None
            )

    def _sweep(self, sel: selectors.BaseSelector) -> None:
        now = time.monotonic_ns()
        late = [p for p in self._peers.values() if now > p.deadline_ns]
        if not late:
            return
        self.gate()
        for peer in late:
            if peer.frames_end < peer.fed:
                why = f"a frame begun and not finished within {self.limits.frame_timeout_ns / 1e6:g} ms"
            elif not peer.frames:
                why = f"no request within {self.limits.urgent_timeout_ns / 1e6:g} ms of connecting"
            else:
                why = "idle"
            self._close(sel, peer, ErrorCode.TIMEOUT, why)

    def _close(self, sel: selectors.BaseSelector, peer: _Peer, code: int, message: str) -> None:
        self._forget(sel, peer)
        _send_close(peer.sock, _note(code, message))

    def _drop(self, sel: selectors.BaseSelector, peer: _Peer) -> None:
        self._forget(sel, peer)
        peer.sock.close()

    def _forget(self, sel: selectors.BaseSelector, peer: _Peer) -> None:
        self._peers.pop(peer.sock, None)
        with contextlib.suppress(KeyError, ValueError):
            sel.unregister(peer.sock)


def _reply(msgid: int, error: object, result: object) -> bytes:
    return msgpack.packb([RESPONSE, msgid, error, result], use_bin_type=True)


def _note(code: int, message: str) -> bytes:
    return msgpack.packb([NOTIFICATION, "error", [[int(code), message]]], use_bin_type=True)


def _send_close(sock: socket.socket, frame: bytes) -> None:
    """Say why, then close; what the client sent is read first so the close is not a reset."""
    with contextlib.suppress(OSError):
        sock.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            while sock.recv(MAX_FRAME_BYTES):
                pass
        sock.send(frame)
        sock.shutdown(socket.SHUT_WR)
    sock.close()
