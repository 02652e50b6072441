"""The panel's estop by the estop socket (server/estop_link.py), against real Unix sockets: the
daemon's answer, its refusal, and every way the socket can fail to answer (which sends the panel's
estop the other way: EstopUnreached, within the link's time)."""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import msgpack
import pytest

from usmswitch.protocol.wire import REQUEST, RESPONSE, ErrorCode, Limits, RpcError
from usmswitch.server.estop_link import EstopLink, EstopUnreached
from usmswitch.server.estop_socket import EstopSocket


@contextlib.contextmanager
def _serve(
    path: Path, answer: Callable[[socket.socket, list[object]], None], keep: bool = False
) -> Iterator[threading.Event]:
    """A one-connection-at-a-time stand-in for the estop socket: `answer(conn, request)` for each
    connection's first request, or with `keep` for every request until its peer closes it; the
    event yielded is set when the test is done with it."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.listen(4)
    listener.settimeout(0.1)
    done = threading.Event()

    def serve(conn: socket.socket) -> None:
        conn.settimeout(0.1)
        unpacker = msgpack.Unpacker(raw=False)
        while not done.is_set():
            try:
                data = conn.recv(512)
            except TimeoutError:
                continue
            if not data:
                return
            unpacker.feed(data)
            for msg in unpacker:
                answer(conn, msg)
                if not keep:
                    return

    def run() -> None:
        while not done.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            with conn:
                serve(conn)

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
    assert seen == [[REQUEST, 1, "estop", ["panel"]]]  # (msgid 1: the connection's first)


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


class _Counted:
    """The real estop socket (server/estop_socket.py) with `slots` slots, its estops counted."""

    def __init__(self, path: Path, slots: int) -> None:
        self.path = path
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.listener.bind(str(path))
        self.listener.listen(16)
        self.estops = 0
        self.estop_socket = EstopSocket(
            self.listener, {"estop": self.estop}, Limits(max_urgent_connections=slots)
        )
        self.estop_socket.start()

    def estop(self, params: list[object]) -> dict[str, object]:
        self.estops += 1
        return {"state": "fault", "n": self.estops}

    def close(self) -> None:
        self.estop_socket.stop()
        self.listener.close()


@pytest.fixture
def counted(sock_path: Path) -> Iterator[_Counted]:
    served = _Counted(sock_path, slots=2)
    yield served
    served.close()


def _wait_for(what: Callable[[], bool]) -> None:
    for _ in range(500):
        if what():
            return
        time.sleep(0.01)
    raise AssertionError("not within 5 s")


def test_the_link_keeps_its_connection_between_estops(counted: _Counted) -> None:
    """An estop on a kept connection is its request and answer alone (no connect, no wait for the
    estop thread's accept: p50 ~0.5 ms against ~1 ms fresh, `make bench BENCH=abuse`)."""
    link = EstopLink(counted.path)
    try:
        link.keep_warm()
        _wait_for(lambda: len(counted.estop_socket._peers) == 1)
        (peer,) = counted.estop_socket._peers
        assert [link.call(["panel"])["n"] for _ in range(3)] == [1, 2, 3]
        assert list(counted.estop_socket._peers) == [peer]  # the same connection all along
    finally:
        link.close()


def test_a_kept_connection_shed_for_newcomers_leaves_no_estop_unanswered(counted: _Counted) -> None:
    """A full estop socket sheds the peer idle longest, the link's kept connection among them: the
    next estop finds it closed (the socket's BUSY word on it) and goes on a fresh connection, not
    the slow way; so does a keep-warm ping."""
    link = EstopLink(counted.path)
    holders: list[socket.socket] = []
    try:
        assert link.call(["panel"])["n"] == 1
        for k in range(2):
            for _ in range(2):  # as many newcomers as slots: the link's connection is shed
                holder = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                holder.connect(str(counted.path))
                holder.sendall(msgpack.packb([REQUEST, 0, "ping", []]))
                holders.append(holder)
            kept = link._sock
            assert kept is not None
            _wait_for(lambda kept=kept: bool(select.select([kept], [], [], 0)[0]))  # its BUSY word
            if k == 0:
                assert link.call(["panel"])["n"] == 2
            else:
                link.keep_warm()
                assert link.call(["panel"])["n"] == 3  # on the connection the ping opened
        assert counted.estops == 3
    finally:
        for holder in holders:
            holder.close()
        link.close()


def test_a_kept_connection_closed_by_the_daemon_is_opened_again(sock_path: Path) -> None:
    """The daemon restarted (its estop socket made again): the kept connection reads end of file,
    and the estop goes on a new one to the new socket."""
    first = _Counted(sock_path, slots=4)
    link = EstopLink(sock_path)
    try:
        assert link.call(["panel"])["n"] == 1
        first.close()
        sock_path.unlink()
        second = _Counted(sock_path, slots=4)
        try:
            assert link.call(["panel"])["n"] == 1  # the second socket's first
        finally:
            second.close()
    finally:
        link.close()


def test_a_kept_connection_that_does_not_answer_is_unreached_within_the_links_time(
    sock_path: Path,
) -> None:
    """A kept connection that takes the request and says nothing (the daemon stuck) is not tried
    again on a fresh one: the estop goes the slow way after the link's time, not twice that."""
    answered = 0
    ended = threading.Event()

    def answer(conn: socket.socket, msg: list[object]) -> None:
        nonlocal answered
        if answered:
            ended.wait(10)  # the second request: held, unanswered, on the same connection
            return
        answered += 1
        conn.sendall(msgpack.packb([RESPONSE, msg[1], None, "pong"]))

    with _serve(sock_path, answer, keep=True):
        link = EstopLink(sock_path, timeout_s=0.3)
        link.keep_warm()
        t0 = time.monotonic()
        try:
            with pytest.raises(EstopUnreached, match="TimeoutError"):
                link.call(["panel"])
        finally:
            took = time.monotonic() - t0
            ended.set()
            link.close()
    assert took < 0.55, took  # once the link's time (0.3 s), not a fresh try's too
