"""The synchronous client against a real server: typed calls, errors, subscriptions, reconnects, TCP."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import tempfile
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import msgpack
import pytest

from usmswitch.client import Client, ConnectionClosed
from usmswitch.client.api import run_owner
from usmswitch.client.connection import parse_address
from usmswitch.protocol.wire import ErrorCode, Limits, RpcError
from usmswitch.server.rpc import RpcServer

TOKEN = "client-test-token-0123"
METHODS = (
    "runs",
    "status",
    "get_target",
    "set_target",
    "history",
    "switch",
    "start_cycling",
    "stop_cycling",
    "set_mode",
    "reset_fault",
    "estop",
    "set_drive",
    "annotate_run",
    "submit",
    "queue_cancel",
    "queue_priority",
    "queue_pause",
    "queue_resume",
)


class Recorder:
    """Handlers that record what they were called with and answer something recognisable."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, list[Any]]] = []
        self.slow = threading.Event()

    def handlers(self) -> dict[str, Any]:
        return {name: self._make(name) for name in METHODS}

    def _make(self, name: str) -> Any:
        def handler(params: list[Any]) -> Any:
            self.calls.append((name, params))
            if name == "reset_fault":
                raise RpcError(ErrorCode.STATE, "no fault latched")
            if name == "switch":
                fut: Future[Any] = Future()
                threading.Timer(0.02, fut.set_result, args=({"cycle": 41, "direction": 0},)).start()
                return fut
            if name == "status" and self.slow.is_set():
                time.sleep(0.5)
            return {"method": name, "params": params}

        return handler


@pytest.fixture
def rec() -> Recorder:
    return Recorder()


@pytest.fixture
def server(rec: Recorder) -> Iterator[RpcServer]:
    d = Path(tempfile.mkdtemp(prefix="usmcli-", dir="/tmp"))
    srv = RpcServer(
        rec.handlers(),
        unix_path=d / "rpc.sock",
        tcp=("127.0.0.1", 0),
        tcp_token=TOKEN,
        snapshot_methods=["stats"],
        limits=Limits(subscriber_buffer_bytes=8192),
    )
    srv.snapshot("stats", {"all": {"count": 3}})
    srv.start()
    yield srv
    srv.stop()
    d.rmdir()


def test_every_typed_method_sends_the_documented_params(server: RpcServer, rec: Recorder) -> None:
    with Client(server.unix_path) as c:
        assert c.ping() == "pong"
        assert c.stats() == {"all": {"count": 3}}
        c.status()
        c.get_target()
        c.set_target(24_000_000)
        c.set_target("12ms", "off")
        c.set_target("10.5 ms", allow_late=True)
        c.history()
        c.history(5, run=3)
        c.runs()
        assert c.switch("on") == {"cycle": 41, "direction": 0}
        c.start_cycling(50_000_000, 1000)
        c.start_cycling(period="20ms", target="12ms")
        c.start_cycling("20ms", 5, label="sweep-1", notes="why")
        c.annotate_run(3, "seen")
        c.annotate_run(3, label="x", operator=True)
        c.submit_entry("20ms", 3, label="q", priority=2)
        c.queue_cancel(4)
        c.queue_priority(4, -3)
        c.queue_priority(5, 7, operator=True)
        c.queue_pause(operator=True)
        c.queue_resume()
        c.stop_cycling()
        c.set_mode("open")
        c.set_mode("open", "2ms")
        c.estop()
        c.set_drive(frequency_hz=40_500.0, enabled=True)
        c.set_drive()
        with pytest.raises(RpcError) as info:
            c.reset_fault()
        assert info.value.code == ErrorCode.STATE and info.value.message == "no fault latched"
    assert rec.calls == [
        ("status", []),
        ("get_target", []),
        ("set_target", [24_000_000, "both", False]),
        ("set_target", [12_000_000, "off", False]),
        ("set_target", [10_500_000, "both", True]),
        ("history", [20, None]),
        ("history", [5, 3]),
        ("runs", [20, None]),
        ("switch", ["on"]),
        ("start_cycling", [50_000_000, 1000, None, False, False, run_owner(), None, None]),
        ("start_cycling", [20_000_000, 0, 12_000_000, False, False, run_owner(), None, None]),
        ("start_cycling", [20_000_000, 5, None, False, False, run_owner(), "sweep-1", "why"]),
        ("annotate_run", [3, "seen", None, run_owner(), False]),
        ("annotate_run", [3, None, "x", run_owner(), True]),
        ("submit", [20_000_000, 3, None, False, "q", None, 2, False, run_owner()]),
        ("queue_cancel", [4, run_owner(), False]),
        ("queue_priority", [4, -3, run_owner(), False]),
        ("queue_priority", [5, 7, run_owner(), True]),
        ("queue_pause", [True]),
        ("queue_resume", [False]),
        ("stop_cycling", []),
        ("set_mode", ["open", None]),
        ("set_mode", ["open", 2_000_000]),
        ("estop", ["main socket"]),  # the path it took, for the fault latched
        ("set_drive", [{"frequency_hz": 40_500.0, "enabled": True}]),
        ("set_drive", [{}]),
        ("reset_fault", []),
    ]


def test_server_errors_raise_with_the_code(server: RpcServer) -> None:
    with Client(server.unix_path) as c:
        with pytest.raises(RpcError) as info:
            c.set_target(0)
        assert info.value.code == ErrorCode.INVALID_PARAMS and "target_ns" in str(info.value)
        with pytest.raises(RpcError) as info:
            c.call("no_such_method")
        assert info.value.code == ErrorCode.UNKNOWN_METHOD
        results = c.pipeline([("ping", []), ("set_mode", ["sideways"]), ("stats", [])])
        assert results[0] == "pong" and results[2] == {"all": {"count": 3}}
        assert isinstance(results[1], RpcError) and results[1].code == ErrorCode.INVALID_PARAMS


def test_subscription_iterates_notifications_and_counts_drops(server: RpcServer) -> None:
    with Client(server.unix_path) as c:
        sub = c.subscribe(timeout=1)
        assert sub.topics == ["stroke"]
        n = 3000  # 900 kB: past the 256 kB buffer and what the kernel holds (under the 4096 backlog)
        for i in range(n):
            while not server.publish("stroke", {"cycle": i, "pad": "y" * 300}):
                time.sleep(0.001)
        server.publish("state", {"state": "idle"})  # not subscribed: never seen
        # Read only once the server process has handled every stroke (the channel keeps order):
        # until then this client would be reading while they are still being sent.
        with Client(server.unix_path) as witness:
            witness.subscribe("state", timeout=5)
            server.publish("state", {"state": "idle"})
            assert witness.next_notification(5).topic == "state"
        seen: list[int] = []
        strokes = iter(sub)
        with contextlib.suppress(TimeoutError):  # when the last strokes were dropped
            while len(seen) + sub.dropped < n:
                note = next(strokes)
                assert note.topic == "stroke"
                seen.append(note.payload["cycle"])
        assert sub.dropped > 0, "this client never read while 900 kB were published: some must drop"
        assert len(seen) + sub.dropped == n and seen == sorted(seen)
        sub.close()
        assert c.unsubscribe() == []

        both = c.subscribe("stroke", "state", timeout=0.5)
        server.publish("state", {"state": "cycling"})
        note = next(iter(both))
        assert (note.topic, note.payload) == ("state", {"state": "cycling"})
        with pytest.raises(TimeoutError):
            next(iter(both))


def test_tcp_with_token_and_refusals(server: RpcServer) -> None:
    host, port = server.tcp_address  # type: ignore[misc]
    with Client(f"tcp://{host}:{port}?token={TOKEN}") as c:
        assert c.stats() == {"all": {"count": 3}}
    with Client(f"tcp://{host}:{port}", token=TOKEN) as c:
        assert c.ping() == "pong"
    with pytest.raises(RpcError) as info:
        Client(f"tcp://{host}:{port}", token="not-the-token-at-all")
    assert info.value.code == ErrorCode.UNAUTHORIZED
    env = os.environ.pop("USMSWITCH_TOKEN", None)
    try:
        with pytest.raises(ValueError, match="needs a token"):
            Client(f"tcp://{host}:{port}")
    finally:
        if env is not None:
            os.environ["USMSWITCH_TOKEN"] = env


def test_tcp_auth_with_the_first_call_is_one_write_and_a_wrong_token_carries_out_nothing(
    server: RpcServer, rec: Recorder
) -> None:
    """`usmswitchctl estop --tcp` waited for its auth's answer before it sent the estop: one round
    trip through the server more than the estop needs. With auth_with_first_call the two frames go
    in one write; the server takes them in order, so a wrong token is refused before the call is
    read, and the call raises it."""
    host, port = server.tcp_address  # type: ignore[misc]
    with Client(f"tcp://{host}:{port}", token=TOKEN, auth_with_first_call=True) as c:
        writes: list[bytes] = []
        send = c._sendall
        c._sendall = lambda data: (writes.append(data), send(data))[1]  # type: ignore[method-assign]
        assert c.call("estop", "a script") == {"method": "estop", "params": ["a script"]}
        assert c.ping() == "pong"  # the connection goes on, authenticated
    frames = list(msgpack.Unpacker(io.BytesIO(writes[0]), raw=False))
    assert [f[2] for f in frames] == ["auth", "estop"] and len(writes) == 2
    with Client(f"tcp://{host}:{port}", token="not-the-token-at-all", auth_with_first_call=True) as c:
        with pytest.raises(RpcError) as info:
            c.call("set_target", 12_000_000)
        assert info.value.code == ErrorCode.UNAUTHORIZED
        assert not c.connected
    assert [name for name, _ in rec.calls] == ["estop"]  # the refused connection's call never ran


def test_timeout_then_the_connection_still_works(server: RpcServer, rec: Recorder) -> None:
    rec.slow.set()
    with Client(server.unix_path, timeout=0.1) as c:
        with pytest.raises(TimeoutError):
            c.status()
        rec.slow.clear()
        time.sleep(0.5)  # the late status reply arrives now and must not be taken for the next one
        assert c.get_target() == {"method": "get_target", "params": []}


def test_broken_connection_retries_idempotent_calls_only(server: RpcServer) -> None:
    with Client(server.unix_path) as c, Client(server.unix_path, retry=False) as strict:
        assert c.ping() == "pong" and strict.ping() == "pong"
        pid = server.server_pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 20
        while server.server_pid == pid or not server.alive:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        # stats is idempotent: one transparent retry on a fresh connection.
        assert c.stats() == {"all": {"count": 3}}
        with pytest.raises(ConnectionClosed):
            strict.stats()
        strict.reconnect()
        assert strict.stats() == {"all": {"count": 3}}
        # switch is not: after a break it raises, the caller decides.
        os.kill(server.server_pid, signal.SIGKILL)  # type: ignore[arg-type]
        time.sleep(0.1)
        with pytest.raises(ConnectionError):
            c.switch()


def test_parse_address() -> None:
    assert parse_address("/run/usmswitch/usmswitchd.sock") == ("unix", "/run/usmswitch/usmswitchd.sock", None)
    assert parse_address("unix:/tmp/x.sock") == ("unix", "/tmp/x.sock", None)
    assert parse_address(Path("/tmp/y.sock"))[1] == "/tmp/y.sock"
    assert parse_address("tcp://127.0.0.1:7770?token=abc") == ("tcp", ("127.0.0.1", 7770), "abc")
    with pytest.raises(ValueError, match="needs a host and a port"):
        parse_address("tcp://127.0.0.1")
    with pytest.raises(ValueError, match="timeout must be a positive number of seconds"):
        Client("/nonexistent.sock", timeout=0)
    with pytest.raises(ValueError, match="target: duration '12': needs a unit"):
        Client.set_target(None, "12")  # type: ignore[arg-type]  # refused before any I/O
    with pytest.raises(ValueError, match="a float has no unit"):
        Client.start_cycling(None, 0.05)  # type: ignore[arg-type]
    with pytest.raises(FileNotFoundError):
        Client("/nonexistent-dir/usm.sock")
