"""An urgent handler's work after its reply (server/after_reply.py): the reply is out first, by the
estop socket and by the main socket's urgent channel alike, and the work still runs, also when the
reply could not be sent or the work before it failed."""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from rawsock import Raw
from urgent_server import urgent_server

from usmswitch.server.after_reply import AfterReply
from usmswitch.server.rpc import RpcServer

#: How long the work after the reply waits to see the reply arrive; far past any run's need.
WAIT_S = 5.0


class Urgent:
    """An estop handler whose work after the reply waits until the test has read the reply."""

    def __init__(self) -> None:
        self.replied = threading.Event()  # set by the test once it holds the reply
        self.ran = threading.Event()
        self.saw_reply: list[bool] = []
        self.fail_next = False

    def estop(self, params: list[Any]) -> AfterReply:
        return AfterReply({"state": "fault"}, self.after)

    def after(self) -> None:
        # Waits while the reply is unsent, when the reply came after this work (the old order).
        self.saw_reply.append(self.replied.wait(WAIT_S))
        self.ran.set()
        if self.fail_next:
            self.fail_next = False
            raise RuntimeError("planted failure after the reply")


@pytest.fixture
def urgent() -> Urgent:
    return Urgent()


@pytest.fixture
def server(sockdir: Path, urgent: Urgent) -> Iterator[RpcServer]:
    with urgent_server(sockdir, urgent.estop) as srv:
        try:
            yield srv
        finally:
            urgent.replied.set()  # never leave a handler thread waiting


def _path(srv: RpcServer, door: str) -> str:
    return str(srv.urgent_path if door == "estop socket" else srv.unix_path)


def _estop(raw: Raw, urgent: Urgent, msgid: int = 1) -> list[Any]:
    urgent.ran.clear()
    urgent.replied.clear()
    reply = raw.call("estop", msgid=msgid)
    urgent.replied.set()
    assert urgent.ran.wait(WAIT_S + 5), "the work after the reply never ran"
    return reply


@pytest.mark.parametrize("door", ["estop socket", "main socket"])
def test_the_reply_goes_out_before_the_work_after_it(server: RpcServer, urgent: Urgent, door: str) -> None:
    raw = Raw(_path(server, door))
    reply = _estop(raw, urgent)
    assert reply[2] is None and reply[3] == {"state": "fault"}, reply
    assert urgent.saw_reply == [True]


@pytest.mark.parametrize("door", ["estop socket", "main socket"])
def test_a_failure_after_the_reply_is_logged_and_the_next_estop_is_answered(
    server: RpcServer, urgent: Urgent, door: str, caplog: pytest.LogCaptureFixture
) -> None:
    raw = Raw(_path(server, door))
    urgent.fail_next = True
    with caplog.at_level(logging.ERROR, logger="usmswitch.rpc"):
        assert _estop(raw, urgent)[3] == {"state": "fault"}
        assert _estop(raw, urgent, msgid=2)[3] == {"state": "fault"}
    assert urgent.saw_reply == [True, True]
    assert "the work after an urgent reply failed" in caplog.text


def test_the_work_runs_when_the_caller_left_before_its_reply(server: RpcServer, urgent: Urgent) -> None:
    """A caller that sent its estop and closed at once: the estop's record and latch still happen."""
    urgent.replied.set()  # nobody will read this reply
    with socket.socket(socket.AF_UNIX) as s:
        s.connect(_path(server, "estop socket"))
        s.sendall(b"\x94\x00\x01\xa5estop\x90")  # [0, 1, "estop", []]
        s.shutdown(socket.SHUT_RDWR)
    assert urgent.ran.wait(WAIT_S + 5)
