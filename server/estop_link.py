"""The panel's estop by the estop socket: from the HTTP doors' thread (server/http_doors.py) straight
to the daemon's estop thread, not handed to the event loop of the Unix and TCP doors first.

Under loads on that loop (64 subscribed connections beside 16 estop holders, `make bench
BENCH=abuse`) a panel estop handed to it waited behind its queue and two thread crossings: p99
15-29 ms, where a fresh connection to the estop socket read 4 ms. The link keeps one connection
to the estop socket open (pinged every KEEP_WARM_S, well inside the socket's idle timeout): an
estop on it is a request and its answer, where a fresh connection also waits for the estop
thread's accept (p50 ~0.5 ms against ~1 ms, `make bench BENCH=abuse`). A full estop socket may
shed it for a newcomer (it is idle between pings); the estop then goes on a fresh connection, as
usmswitchctl's. What fails here (no socket, a refusal, no answer in time) goes the old way, by that
loop and the urgent channel: a faster path never loses an estop.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import msgpack

from usmswitch.protocol.wire import MAX_MSGID, NOTIFICATION, REQUEST, RESPONSE, RpcError

#: Time for the whole exchange (connect, request, answer) before the panel goes the old way.
TIMEOUT_S = 0.25
#: How often the kept connection is pinged: the estop socket closes a connection idle for 600 s
#: (Limits.idle_timeout_ns), and a ping finds one shed, and opens another, before an estop needs it.
KEEP_WARM_S = 30.0
_MAX_FRAME_BYTES = 512  # the estop socket's own bound on a frame


class EstopUnreached(Exception):
    """The estop socket did not answer this estop (gone, full of a newer peer, too slow)."""


class _Stale(Exception):
    """The kept connection was closed or shed before it served this request: a fresh one may."""


class EstopLink:
    """`call(params)`: an estop by the estop socket at `path`, from the one thread that calls it
    (and `keep_warm`): the connection is kept between calls."""

    def __init__(self, path: str | Path, timeout_s: float = TIMEOUT_S) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s
        self._sock: socket.socket | None = None
        self._unpacker: msgpack.Unpacker | None = None
        self._msgid = 0

    def call(self, params: list[Any]) -> Any:
        """The estop's result; RpcError if the daemon refused it; EstopUnreached if the socket did
        not answer (the caller then sends it another way).

        Blocking, on the HTTP doors' loop: the exchange is a millisecond (the daemon answers once
        the drive is off), its waits release the GIL, and nothing that loop holds is more urgent.
        Awaited, each step of it (the connect, the reply, the task's end, the handler's wake-up)
        waited a turn of that loop behind the other pages and scrapers and a handover of the GIL
        from the event loop's thread: p99 5-16 ms under loads where the estop socket read 2.
        """
        try:
            return self._request("estop", params)
        except (OSError, ValueError) as exc:  # TimeoutError is an OSError; ValueError: undecodable
            self.close()
            raise EstopUnreached(f"{self.path}: {type(exc).__name__}: {exc}") from exc

    def keep_warm(self) -> None:
        """A ping on the kept connection, or on a new one when it was shed or closed; a failure
        leaves it closed (the next estop opens one)."""
        try:
            self._request("ping", [])
        except (OSError, ValueError, RpcError):
            self.close()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
        self._sock = self._unpacker = None

    def _request(self, method: str, params: list[Any]) -> Any:
        deadline = time.monotonic() + self.timeout_s
        if self._sock is not None:
            try:
                return self._exchange(method, params, deadline)
            except _Stale:
                self.close()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.settimeout(self.timeout_s)  # a full backlog (1024) refuses at once: the old way then
            sock.connect(str(self.path))
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self._unpacker = msgpack.Unpacker(raw=False, max_buffer_size=_MAX_FRAME_BYTES, max_ext_len=0)
        try:
            return self._exchange(method, params, deadline)
        except _Stale as exc:  # a new connection's request unserved: the socket is not answering
            raise ConnectionError(str(exc)) from None

    def _exchange(self, method: str, params: list[Any], deadline: float) -> Any:
        sock, unpacker = self._sock, self._unpacker
        assert sock is not None and unpacker is not None
        # Anything that came since the last answer is the socket's word before it closed this
        # connection (shed for a newcomer, timed out): then nothing sent on it is read.
        sock.setblocking(False)
        try:
            early = sock.recv(_MAX_FRAME_BYTES)
        except BlockingIOError:
            pass
        except OSError as exc:
            raise _Stale(f"the kept connection failed: {exc}") from exc
        else:
            raise _Stale("the kept connection was closed" if not early else "the kept connection was shed")
        self._msgid = self._msgid % MAX_MSGID + 1
        msgid = self._msgid
        try:
            sock.settimeout(max(deadline - time.monotonic(), 0.001))
            sock.sendall(msgpack.packb([REQUEST, msgid, method, params], use_bin_type=True))
        except (BrokenPipeError, ConnectionResetError) as exc:
            raise _Stale(f"the kept connection was closed: {exc}") from exc
        while True:
            sock.settimeout(max(deadline - time.monotonic(), 0.001))
            try:
                data = sock.recv(_MAX_FRAME_BYTES)
            except ConnectionResetError as exc:
                raise _Stale(f"the connection was reset: {exc}") from exc
            if not data:
                # The estop socket answers a request before anything else it does to a
                # connection, so closed without the answer is closed without reading it.
                raise _Stale("the estop socket closed without answering")
            unpacker.feed(data)
            for msg in unpacker:
                if type(msg) is list and len(msg) == 4 and msg[0] == RESPONSE and msg[1] == msgid:
                    error = msg[2]
                    if error is None:
                        return msg[3]
                    raise RpcError.of(int(error[0]), str(error[1]))
                if type(msg) is list and msg and msg[0] == NOTIFICATION:
                    raise _Stale(f"the estop socket closed this connection: {msg[-1]!r:.120}")
