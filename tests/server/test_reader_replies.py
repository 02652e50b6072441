"""A records reader's replies as the server process takes them (server/records_reads.py,
REPLY_HEAD): the body handed on in the pieces it arrived in, never unpacked or joined on the event
loop, whatever the reads split; an error's code and message; replies back to back."""

from __future__ import annotations

import asyncio
from typing import Any

import msgpack
import pytest

from usmswitch.protocol.wire import ErrorCode, RpcError, packb
from usmswitch.server.records_reads import REPLY_HEAD, _Job, _send_reply, _Worker


class _Lane:
    """Stands in for a lane: hands the worker the next job when it is free."""

    def __init__(self, jobs: list[_Job]) -> None:
        self.jobs = jobs
        self.freed = 0

    def next(self, worker: _Worker) -> None:
        self.freed += 1
        if self.jobs:
            worker.job = self.jobs.pop(0)


class _Sent:
    """A socket's sendall, kept."""

    def __init__(self) -> None:
        self.data = b""

    def sendall(self, data: bytes) -> None:
        self.data += data


def _job(loop: asyncio.AbstractEventLoop) -> _Job:
    return _Job("history", [10_000], loop.create_future(), lambda: False)


def _worker(loop: asyncio.AbstractEventLoop, jobs: int) -> tuple[_Worker, list[_Job]]:
    made = [_job(loop) for _ in range(jobs)]
    worker = _Worker(_Lane(made[1:]), None)  # type: ignore[arg-type]
    worker.job = made[0]
    return worker, made


def _framed(error: list[Any] | None, body: bytes) -> bytes:
    sent = _Sent()
    _send_reply(sent, 7, error, body)  # type: ignore[arg-type]
    return sent.data


@pytest.mark.parametrize("cut", [1, 5, REPLY_HEAD.size, REPLY_HEAD.size + 1, 1000, 65_536])
def test_a_reply_is_handed_on_in_the_pieces_it_arrived_in(cut: int) -> None:
    loop = asyncio.new_event_loop()
    try:
        body = packb(list(range(40_000)))
        data = _framed(None, body)
        worker, (job,) = _worker(loop, 1)
        reads = [data[i : i + cut] for i in range(0, len(data), cut)]
        for read in reads:
            worker.data_received(read)
        pieces = job.future.result()
        assert b"".join(pieces) == body
        # Each read begun past the head is a piece as it came: not copied, not joined.
        kept = {id(p) for p in pieces}
        assert all(
            id(r) in kept
            for o, r in zip(range(0, len(data), cut), reads, strict=True)
            if o >= REPLY_HEAD.size
        )
        assert worker.lane.freed == 1 and worker.job is None and worker.body is None
    finally:
        loop.close()


def test_an_error_reply_raises_its_code_and_message() -> None:
    loop = asyncio.new_event_loop()
    try:
        worker, (job,) = _worker(loop, 1)
        worker.data_received(_framed([ErrorCode.INVALID_PARAMS, "history: no run 9 (runs are 1..3)"], b""))
        with pytest.raises(RpcError) as caught:
            job.future.result()
        assert caught.value.code == ErrorCode.INVALID_PARAMS
        assert caught.value.message == "history: no run 9 (runs are 1..3)"
    finally:
        loop.close()


def test_replies_back_to_back_in_one_read_go_to_their_jobs_in_turn() -> None:
    loop = asyncio.new_event_loop()
    try:
        first, second = packb({"n": 1}), packb(["x" * 300])
        worker, jobs = _worker(loop, 3)
        data = _framed(None, first) + _framed(None, second) + _framed([ErrorCode.UNAVAILABLE, "gone"], b"")
        worker.data_received(data[:3])
        worker.data_received(data[3:])
        assert msgpack.unpackb(b"".join(jobs[0].future.result())) == {"n": 1}
        assert b"".join(jobs[1].future.result()) == second
        assert isinstance(jobs[2].future.exception(), RpcError)
        assert worker.lane.freed == 3
    finally:
        loop.close()
