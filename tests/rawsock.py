"""A bare msgpack socket for tests that must send exactly the bytes they want (importable from any test)."""

from __future__ import annotations

import socket
from typing import Any

import msgpack


class Raw:
    """A bare msgpack socket, to send exactly the bytes a test wants."""

    def __init__(self, address: Any, family: int = socket.AF_UNIX, timeout: float = 5.0) -> None:
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        self.sock.settimeout(timeout)
        self.sock.connect(address)
        self.unpacker = msgpack.Unpacker(raw=False)
        self.msgs: list[Any] = []

    def send(self, *frames: Any) -> None:
        self.sock.sendall(b"".join(msgpack.packb(f) for f in frames))

    def read(self, n: int) -> list[Any]:
        """The next n messages (responses and notifications) in arrival order."""
        while len(self.msgs) < n:
            data = self.sock.recv(1 << 16)
            if not data:
                raise ConnectionError(f"closed after {len(self.msgs)} of {n} messages: {self.msgs}")
            self.unpacker.feed(data)
            self.msgs.extend(self.unpacker)
        out, self.msgs = self.msgs[:n], self.msgs[n:]
        return out

    def call(self, method: str, *params: Any, msgid: int = 1) -> list[Any]:
        self.send([0, msgid, method, list(params)])
        return self.read(1)[0]

    def read_until_closed(self) -> list[Any]:
        while True:
            try:
                data = self.sock.recv(1 << 16)
            except ConnectionResetError:
                data = b""
            if not data:
                out, self.msgs = self.msgs, []
                return out
            self.unpacker.feed(data)
            self.msgs.extend(self.unpacker)

    def close(self) -> None:
        self.sock.close()
