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

import socket
import time
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
    """`call(params)`: an estop by the estop socket at `path`, from the thread that calls it."""

    def __init__(self, path: str | Path, timeout_s: float = TIMEOUT_S) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s

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
            return self._exchange(params)
        except (OSError, ValueError) as exc:  # TimeoutError is an OSError; ValueError: undecodable
            raise EstopUnreached(f"{self.path}: {type(exc).__name__}: {exc}") from exc

    def _exchange(self, params: list[Any]) -> Any:
        frame = msgpack.packb([REQUEST, _MSGID, "estop", params], use_bin_type=True)
        deadline = time.monotonic() + self.timeout_s
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(self.timeout_s)  # the connect too: a full backlog waits to be taken
            sock.connect(str(self.path))
            sock.sendall(frame)
            unpacker = msgpack.Unpacker(raw=False, max_buffer_size=_MAX_FRAME_BYTES, max_ext_len=0)
            while True:
                sock.settimeout(max(deadline - time.monotonic(), 0.001))
                data = sock.recv(_MAX_FRAME_BYTES)
                if not data:
                    raise ConnectionError("the estop socket closed without answering")
                unpacker.feed(data)
                for msg in unpacker:
                    if type(msg) is list and len(msg) == 4 and msg[0] == RESPONSE and msg[1] == _MSGID:
                        error = msg[2]
                        if error is None:
                            return msg[3]
                        raise RpcError.of(int(error[0]), str(error[1]))
                    # else a notification ("gave way", a timeout): the socket closes after it
