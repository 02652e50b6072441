"""A Unix socket whose backlog is full (a connection flood the server sheds at its accepts): a
Client with a timeout waits for a place, as a TCP connect does, instead of failing at once with
EAGAIN (the abuse bench's estop by the main socket under 600 connections renewed: 5 of 20 failed);
and it waits its turn among the flood's own waiting connects, first come first served, not
polling for a place each of them takes first (then 9-11 ms at p99 in that bench); so does the
AsyncClient."""

from __future__ import annotations

import asyncio
import socket
import struct
import threading
import time
from pathlib import Path

import msgpack

from usmswitch.client import AsyncClient, Client


def test_a_full_backlog_is_waited_out_not_an_error(tmp_path: Path) -> None:
    path = str(tmp_path / "full.sock")
    listener = _listener(path)
    flood = _fill(path)
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


def test_a_client_waits_its_turn_among_a_floods_waiting_connects(tmp_path: Path) -> None:
    """A flood that connects again the moment a place frees (blocking connects, as the bench's
    loader makes them) took every place a polling Client looked for: it got in only when the
    flood paused. Queued in the kernel with the flood's connects, it is in within a few accepts."""
    path = str(tmp_path / "flooded.sock")
    listener = _listener(path)
    stop = threading.Event()
    flood: list[socket.socket] = []

    def flooding() -> None:
        while not stop.is_set():
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:  # blocking connects that give up after 0.5 s, so that the test can end
                s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("@ll", 0, 500_000))
                s.connect(path)
                flood.append(s)
            except OSError:
                s.close()

    flooder = threading.Thread(target=flooding)
    got: list[object] = []
    asker = threading.Thread(target=lambda: got.append(_connect(path)))
    accepted: list[socket.socket] = []
    try:
        flooder.start()
        time.sleep(0.2)  # the backlog full, the flood waiting in connect for a place
        asker.start()
        time.sleep(0.1)  # the Client meets the full backlog, behind the flood's waiting connect
        for _ in range(200):  # the server takes one connection each 5 ms
            accepted.append(listener.accept()[0])
            time.sleep(0.005)
            if got:
                break
        assert got and isinstance(got[0], Client), got
        assert len(accepted) <= 8, f"in only after {len(accepted)} accepts"
        got[0].close()
    finally:
        stop.set()
        flooder.join(10)
        asker.join(30)
        for s in flood + accepted:
            s.close()
        listener.close()


def test_the_async_client_waits_out_a_full_backlog(tmp_path: Path) -> None:
    """asyncio's own connect met a full backlog's EAGAIN as a connect in progress, and its first
    write failed; the AsyncClient waits for a place as the Client does."""
    path = str(tmp_path / "full.sock")
    listener = _listener(path)
    flood = _fill(path)

    async def main() -> str:
        client = AsyncClient(path, timeout=30)
        connecting = asyncio.ensure_future(client.connect())
        await asyncio.sleep(0.2)
        assert not connecting.done(), connecting
        for _ in flood:  # the server takes the flood: places free
            await asyncio.get_running_loop().run_in_executor(None, lambda: listener.accept()[0].close())
        await asyncio.wait_for(connecting, 10)
        # A connection, not a socket left unconnected: a call goes through to this end and back.
        answering = asyncio.get_running_loop().run_in_executor(None, _answer_one_ping, listener)
        pong = await client.call("ping")
        await answering
        await client.close()
        return pong

    try:
        assert asyncio.run(main()) == "pong"
    finally:
        for s in flood:
            s.close()
        listener.close()


def _listener(path: str) -> socket.socket:
    """A Unix listener with a backlog of 1 that nobody accepts from until the test does."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(1)
    return listener


def _fill(path: str) -> list[socket.socket]:
    """Connections that fill `path`'s backlog: the next non-blocking connect fails at once."""
    flood = []
    while True:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.setblocking(False)
        try:
            s.connect(path)
        except BlockingIOError:
            s.close()
            return flood
        flood.append(s)


def _answer_one_ping(listener: socket.socket) -> None:
    end = listener.accept()[0]
    with end:
        end.settimeout(10)
        unpacker = msgpack.Unpacker(raw=False)
        while True:
            unpacker.feed(end.recv(4096))
            for _, msgid, method, _ in unpacker:
                assert method == "ping"
                end.sendall(msgpack.packb([1, msgid, None, "pong"]))
                return


def _connect(path: str) -> object:
    try:
        return Client(path, timeout=30)
    except OSError as exc:
        return exc
