"""A Unix socket whose backlog is full (a connection flood the server sheds at its accepts): a
Client with a timeout waits for a place, as a TCP connect does, instead of failing at once with
EAGAIN (the abuse bench's estop by the main socket under 600 connections renewed: 5 of 20 failed)."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

from usmswitch.client import Client


def test_a_full_backlog_is_waited_out_not_an_error(tmp_path: Path) -> None:
    path = str(tmp_path / "full.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(1)
    flood: list[socket.socket] = []
    while True:  # fill the backlog: the next connect fails at once
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.setblocking(False)
        try:
            s.connect(path)
        except BlockingIOError:
            s.close()
            break
        flood.append(s)
    got: list[object] = []
    accepted: list[socket.socket] = []
    asker = threading.Thread(target=lambda: got.append(_connect(path)))
    try:
        asker.start()
        time.sleep(0.2)  # it meets the full backlog (no figure is judged)
        listener.setblocking(False)
        while asker.is_alive():  # the server takes the flood: a place frees
            try:
                accepted.append(listener.accept()[0])
            except BlockingIOError:
                time.sleep(0.01)
        assert len(got) == 1 and isinstance(got[0], Client), got
        assert got[0].connected
        got[0].close()
    finally:
        asker.join(30)
        for s in flood + accepted:
            s.close()
        listener.close()


def _connect(path: str) -> object:
    try:
        return Client(path, timeout=30)
    except OSError as exc:
        return exc
