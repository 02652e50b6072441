"""The panel's estop by the estop socket: from the HTTP doors' thread (server/http_doors.py) straight
to the daemon's estop thread, not handed to the event loop of the Unix and TCP doors first.

Under loads on that loop (64 subscribed connections beside 16 estop holders, `make bench
BENCH=abuse`) a panel estop handed to it waited behind its queue and two thread crossings: p99
15-29 ms, where a fresh connection to the estop socket read 4 ms. Here each estop is such a fresh
connection, as usmswitchctl's: the estop socket takes a new connection's request at once and, when
full, sheds its longest idle holder for it. What fails here (no socket, a refusal, no answer in
time) goes the old way, by that loop and the urgent channel: a faster path never loses an estop.
"""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path
from typing import Any

import msgpack

from usmswitch.protocol.wire import REQUEST, RESPONSE, RpcError

#: Time for the whole exchange (connect, request, answer) before the panel goes the old way.
TIMEOUT_S = 0.25
_MAX_FRAME_BYTES = 512  # the estop socket's own bound on a frame
_MSGID = 1  # one request per connection: its id needs to be unique on it alone


class EstopUnreached(Exception):
    """The estop socket did not answer this estop (gone, full of a newer peer, too slow)."""


class EstopLink:
    """`call(params)`: an estop by the estop socket at `path`, on the running loop."""

    def __init__(self, path: str | Path, timeout_s: float = TIMEOUT_S) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s

    async def call(self, params: list[Any]) -> Any:
        """The estop's result; RpcError if the daemon refused it; EstopUnreached if the socket did
        not answer (the caller then sends it another way)."""
        try:
            async with asyncio.timeout(self.timeout_s):
                return await self._exchange(params)
        except (OSError, TimeoutError, ValueError) as exc:  # ValueError: undecodable bytes
            raise EstopUnreached(f"{self.path}: {type(exc).__name__}: {exc}") from exc

    async def _exchange(self, params: list[Any]) -> Any:
        # Connected and sent at once, not a loop callback later: the estop socket's thread reads a
        # new connection's request as it accepts it, and one not there yet waited its next round
        # (p99 7-9 ms by the panel where the estop socket read 2, `make bench BENCH=abuse`).
        loop = asyncio.get_running_loop()
        frame = msgpack.packb([REQUEST, _MSGID, "estop", params], use_bin_type=True)
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.setblocking(False)
            try:
                sock.connect(str(self.path))
            except BlockingIOError:  # its backlog full: the connection completes when it is taken
                await loop.sock_connect(sock, str(self.path))
            sent = sock.send(frame)  # a few dozen bytes into an empty buffer: all of it
            if sent < len(frame):
                await loop.sock_sendall(sock, frame[sent:])
            unpacker = msgpack.Unpacker(raw=False, max_buffer_size=_MAX_FRAME_BYTES, max_ext_len=0)
            while data := await loop.sock_recv(sock, _MAX_FRAME_BYTES):
                unpacker.feed(data)
                for msg in unpacker:
                    if type(msg) is list and len(msg) == 4 and msg[0] == RESPONSE and msg[1] == _MSGID:
                        error = msg[2]
                        if error is None:
                            return msg[3]
                        raise RpcError.of(int(error[0]), str(error[1]))
                    # else a notification ("gave way", a timeout): the socket closes after it
            raise ConnectionError("the estop socket closed without answering")
