"""Thousands of random and mutated frames at the server; then a normal client still gets right answers."""

from __future__ import annotations

import contextlib
import random
import socket
import struct
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import pytest

from usmswitch.client import Client
from usmswitch.protocol.wire import ErrorCode, Limits
from usmswitch.server.rpc import RpcServer

GOOD = [
    [0, 1, "ping", []],
    [0, 2, "stats", []],
    [0, 3, "bump", []],
    [0, 4, "set_target", [12_000_000, "on"]],
    [0, 5, "history", [3]],
    [0, 6, "subscribe", [["stroke"]]],
    [0, 7, "auth", ["whatever"]],
]

# Headers that announce far more than the limits allow, ext types, deep nesting, odd keys.
HOSTILE = [
    b"\xdd\xff\xff\xff\xff",  # array32 of 4 billion
    b"\xdf\xff\xff\xff\xff",  # map32 of 4 billion
    b"\xdb\x7f\xff\xff\xff" + b"a" * 100,  # str32 of 2 GB
    b"\xc6\xff\xff\xff\xff",  # bin32 of 4 GB
    b"\xc9\x00\x01\x00\x00\x05" + b"\x00" * 64,  # ext32
    b"\xd4\x01\x00",  # fixext1
    b"\xd7\xff" + b"\x00" * 8,  # timestamp ext
    b"\x91" * 5000,  # nesting deeper than any stack limit
    b"\xc1",  # the never-used byte
    b"\x94\x00\x01\xa4ping\xdc\xff\xff",  # params array16 that never arrives
    msgpack.packb([0, 1, "ping", {b"k": 1}]),  # params a map
    b"\x81\x91\x01\x01",  # a map whose key is an array
    msgpack.packb([0, 2**40, "ping", []]),  # msgid beyond uint32
    msgpack.packb([0, -1, "ping", []]),
    msgpack.packb([0, 1.5, "ping", []]),
    msgpack.packb([1, 1, None, "a response sent to the server"]),
    msgpack.packb([2, "stroke", [{}]]),  # a notification sent to the server
    msgpack.packb([0, 1, "x" * 5000, []]),  # method name over max_str_len
    msgpack.packb([0, 1, "set_target", [2**63]]),
    msgpack.packb([0, 1, "set_drive", [{"frequency_hz": float("nan")}]]),
    msgpack.packb([0, 1, "start_cycling", [None, None, None]]),
    b"\xa3\xff\xfe\xfd",  # invalid UTF-8 in a str
]


def mutate(rng: random.Random, data: bytes) -> bytes:
    """Flip, cut, splice or repeat bytes of a frame."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(5)
        if op == 0 and b:
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        elif op == 1 and b:
            del b[rng.randrange(len(b)) :]
        elif op == 2:
            b[rng.randrange(len(b) + 1) : rng.randrange(len(b) + 1)] = rng.randbytes(rng.randint(1, 8))
        elif op == 3 and b:
            b[rng.randrange(len(b))] = rng.choice(b"\xc1\xc7\xc8\xc9\xd4\xd8\xdc\xdd\xde\xdf\xdb\xc6")
        else:
            b += bytes(b)
    return bytes(b)


def random_object(rng: random.Random, depth: int = 0) -> Any:
    kinds = ["int", "neg", "str", "bin", "float", "none", "bool"] + (["list", "map"] if depth < 3 else [])
    kind = rng.choice(kinds)
    if kind == "int":
        return rng.choice([0, 1, 2, 2**32 - 1, 2**32, 2**64 - 1, rng.randrange(2**16)])
    if kind == "neg":
        return -rng.randrange(1, 2**63)
    if kind == "str":
        return rng.choice(["ping", "stats", "bump", "on", "", "é", "subscribe"])
    if kind == "bin":
        return rng.randbytes(rng.randrange(8))
    if kind == "float":
        return rng.choice([0.0, -1.5, float("inf"), float("nan"), 1e300])
    if kind == "none":
        return None
    if kind == "bool":
        return rng.random() < 0.5
    if kind == "list":
        return [random_object(rng, depth + 1) for _ in range(rng.randrange(5))]
    return {
        rng.choice(["a", "b", "frequency_hz", "enabled"]): random_object(rng, depth + 1) for _ in range(2)
    }


def garbage(rng: random.Random) -> bytes:
    roll = rng.random()
    if roll < 0.25:
        return rng.randbytes(rng.randint(1, 200))
    if roll < 0.55:
        return mutate(rng, msgpack.packb(rng.choice(GOOD)))
    if roll < 0.7:
        return rng.choice(HOSTILE)
    # Well-formed msgpack of the right shape with random types in every slot.
    frame = [rng.choice([0, 0, 0, 1, 2, 3, -1]), random_object(rng), random_object(rng), random_object(rng)]
    return msgpack.packb(frame[: rng.choice([4, 4, 4, 3, 5])] if rng.random() < 0.9 else frame[:2])


class Counter:
    def __init__(self) -> None:
        self.bumps = 0

    def bump(self, params: list[Any]) -> int:
        self.bumps += 1
        return self.bumps


@pytest.fixture
def served() -> Iterator[tuple[RpcServer, Counter]]:
    counter = Counter()
    d = Path(tempfile.mkdtemp(prefix="usmfuzz-", dir="/tmp"))
    handlers = {
        "bump": counter.bump,
        "set_target": lambda params: {"target_on_ns": params[0]},
        "history": lambda params: [{"cycle": i} for i in range(params[0])],
    }
    limits = Limits(max_connections=256, auth_timeout_ns=2_000_000_000)
    srv = RpcServer(handlers, unix_path=d / "rpc.sock", snapshot_methods=["stats"], limits=limits)
    srv.snapshot("stats", {"count": 42})
    srv.start()
    yield srv, counter
    srv.stop()
    d.rmdir()


def drain(sock: socket.socket) -> list[Any]:
    """What the server said before it closed or went quiet; only msgpack-RPC frames are allowed."""
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=False)
    sock.settimeout(0.05)
    out: list[Any] = []
    try:
        while True:
            data = sock.recv(1 << 16)
            if not data:
                break
            unpacker.feed(data)
            out.extend(unpacker)
    except (TimeoutError, ConnectionResetError):
        pass
    return out


def test_fuzzed_frames_never_stop_the_server(served: tuple[RpcServer, Counter]) -> None:
    srv, counter = served
    pid = srv.server_pid
    rng = random.Random(20170517)
    frames = 0
    closed = 0
    for _ in range(400):
        sock = socket.socket(socket.AF_UNIX)
        sock.connect(str(srv.unix_path))
        sock.settimeout(2)
        batch = [garbage(rng) for _ in range(rng.randint(1, 15))]
        frames += len(batch)
        try:
            if rng.random() < 0.5:
                sock.sendall(b"".join(batch))
            else:
                for chunk in batch:  # split across reads: truncated frames must wait, not break
                    sock.sendall(chunk)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server already closed it, as it may
        for msg in drain(sock):
            assert type(msg) is list and msg[0] in (1, 2), f"not a response or notification: {msg!r}"
            if msg[0] == 1:
                assert len(msg) == 4 and (msg[2] is None or (type(msg[2]) is list and len(msg[2]) == 2))
            else:
                assert msg[1] in ("error", "dropped", "stroke", "state"), msg
                if msg[1] == "error":
                    closed += 1
        sock.close()
    assert frames >= 2500
    assert closed > 0, "hostile headers must have closed some connections"

    # The server process never died, and a normal client gets correct answers.
    assert srv.server_pid == pid and srv.alive and srv.restarts == 0
    before = counter.bumps
    with Client(srv.unix_path) as c:
        assert c.stats() == {"count": 42}
        assert c.call("bump") == before + 1
        assert c.history(3) == [{"cycle": 0}, {"cycle": 1}, {"cycle": 2}]
    srv.snapshot("stats", {"count": 43})
    deadline = time.monotonic() + 5
    with Client(srv.unix_path) as c:
        while c.stats() != {"count": 43}:
            assert time.monotonic() < deadline


def test_each_hostile_header_gets_an_answer_or_a_close(served: tuple[RpcServer, Counter]) -> None:
    srv, _ = served
    for data in HOSTILE:
        sock = socket.socket(socket.AF_UNIX)
        sock.connect(str(srv.unix_path))
        sock.sendall(data + msgpack.packb([0, 99, "ping", []]))
        msgs = drain(sock)
        if not msgs:
            # A str/bin header's length is checked once its bytes are there: the server waits,
            # holding at most max_frame_bytes; more than that and the connection is cut.
            with contextlib.suppress(BrokenPipeError, ConnectionResetError):
                sock.sendall(b"\x00" * 70_000)
            msgs = drain(sock)
        sock.close()
        pong = [m for m in msgs if m[:2] == [1, 99]]
        errors = [m for m in msgs if m[:2] == [2, "error"] or (m[0] == 1 and m[2] is not None)]
        # Either the stream stayed in sync (the ping after it is answered) or the server said why.
        assert pong == [[1, 99, None, "pong"]] or errors, f"{data[:12]!r}: no answer, got {msgs}"
        if not pong:
            codes = {m[2][0][0] if m[0] == 2 else m[2][0] for m in errors}
            assert codes & {ErrorCode.PARSE_ERROR, ErrorCode.TOO_LARGE, ErrorCode.INVALID_REQUEST}, (
                data,
                msgs,
            )


def test_an_endless_frame_is_cut_at_the_buffer_limit(served: tuple[RpcServer, Counter]) -> None:
    srv, _ = served
    sock = socket.socket(socket.AF_UNIX)
    sock.connect(str(srv.unix_path))
    sock.settimeout(5)
    header = b"\x94\x00\x01\xa4ping\x91\xdb" + struct.pack(">I", 4000)  # a 4000-byte str, within limits
    sock.sendall(header)
    sock.sendall(b"z" * 4000)  # completes it: answered (params wrong for ping)
    unpacker = msgpack.Unpacker(raw=False)
    while True:
        unpacker.feed(sock.recv(1 << 16))
        msgs = list(unpacker)
        if msgs:
            break
    assert msgs[0][2][0] == ErrorCode.INVALID_PARAMS
    with contextlib.suppress(BrokenPipeError, ConnectionResetError):  # a frame that never ends
        sock.sendall(b"\xdc\x03\xff" + b"\x92" * 70_000)
    msgs = drain(sock)
    assert msgs and msgs[-1][:2] == [2, "error"]
    assert msgs[-1][2][0][0] in (ErrorCode.TOO_LARGE, ErrorCode.PARSE_ERROR)
    with Client(srv.unix_path) as c:
        assert c.ping() == "pong"
