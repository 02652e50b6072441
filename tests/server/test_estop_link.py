"""The panel's estop by the estop socket (server/estop_link.py), against real Unix sockets: the
daemon's answer, its refusal, and every way the socket can fail to answer (which sends the panel's
estop the other way: EstopUnreached, within the link's time)."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import msgpack
import pytest

from usmswitch.protocol.wire import REQUEST, RESPONSE, ErrorCode, RpcError
from usmswitch.server.estop_link import EstopLink, EstopUnreached


@contextlib.contextmanager
def _serve(path: Path, answer: Callable[[socket.socket, list[object]], None]) -> Iterator[threading.Event]:
    """A one-connection-at-a-time stand-in for the estop socket: `answer(conn, request)`; the
    event yielded is set when the test is done with it."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.listen(4)
    listener.settimeout(0.1)
    done = threading.Event()

    def run() -> None:
        while not done.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            with conn:
                conn.settimeout(5)
                unpacker = msgpack.Unpacker(raw=False)
                while (data := conn.recv(512)) and not done.is_set():
                    unpacker.feed(data)
                    for msg in unpacker:
                        answer(conn, msg)
                        break
                    else:
                        continue
                    break

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield done
    finally:
        done.set()
        thread.join(5)
        listener.close()


@pytest.fixture
def sock_path(tmp_path: Path) -> Path:
    return tmp_path / "d.estop.sock"


def test_the_daemons_answer_is_the_result(sock_path: Path) -> None:
    seen: list[object] = []

    def answer(conn: socket.socket, msg: list[object]) -> None:
        seen.append(msg)
        conn.sendall(msgpack.packb([RESPONSE, msg[1], None, {"state": "FAULT"}]))

    with _serve(sock_path, answer):
        assert EstopLink(sock_path).call(["panel"]) == {"state": "FAULT"}
    assert seen == [[REQUEST, 1, "estop", ["panel"]]]


def test_a_refusal_is_the_daemons_error_not_a_fallback(sock_path: Path) -> None:
    def answer(conn: socket.socket, msg: list[object]) -> None:
        conn.sendall(msgpack.packb([RESPONSE, msg[1], [int(ErrorCode.BUSY), "no"], None]))

    with _serve(sock_path, answer), pytest.raises(RpcError) as err:
        EstopLink(sock_path).call(["panel"])
    assert err.value.code == ErrorCode.BUSY and not isinstance(err.value, EstopUnreached)


def test_no_socket_is_unreached(sock_path: Path) -> None:
    with pytest.raises(EstopUnreached, match=r"d\.estop\.sock"):
        EstopLink(sock_path).call(["panel"])


@pytest.mark.parametrize(
    "answer",
    [
        lambda conn, msg: None,  # silent: held
        lambda conn, msg: conn.shutdown(socket.SHUT_WR),  # closed without a word
        lambda conn, msg: conn.sendall(b"\xc1" * 8),  # bytes no msgpack decoder takes
    ],
    ids=["silent", "closed", "garbage"],
)
def test_a_socket_that_does_not_answer_is_unreached_within_the_links_time(
    sock_path: Path, answer: Callable[[socket.socket, list[object]], None]
) -> None:
    ended = threading.Event()

    def held(conn: socket.socket, msg: list[object]) -> None:
        answer(conn, msg)
        ended.wait(10)  # the connection stays open until the test has its answer

    with _serve(sock_path, held):
        t0 = time.monotonic()
        try:
            with pytest.raises(EstopUnreached):
                EstopLink(sock_path, timeout_s=0.2).call(["panel"])
        finally:
            took = time.monotonic() - t0
            ended.set()
    # The link's own time, not the socket's 10 s (a closed or garbled answer comes at once).
    assert took < 5, took
