"""sd_notify against a fake NOTIFY_SOCKET: a real AF_UNIX datagram socket, as systemd listens."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from usmswitch.daemon import sdnotify
from usmswitch.daemon.sdnotify import Notifier, watchdog_interval_ns


@pytest.fixture
def listener(tmp_path: Path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify"
    sock.bind(str(path))
    sock.settimeout(5)
    yield sock, str(path)
    sock.close()


def received(sock: socket.socket) -> list[str]:
    """Every datagram waiting on `sock`."""
    out = []
    sock.setblocking(False)
    try:
        while True:
            out.append(sock.recv(4096).decode())
    except BlockingIOError:
        pass
    finally:
        sock.settimeout(5)
    return out


def test_ready_status_stopping_reach_the_socket(listener):
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready("cycling at T = 12 ms")
    assert sock.recv(4096) == b"READY=1\nSTATUS=cycling at T = 12 ms"
    assert n.status("fault: stall\nREADY=1")
    # A newline in a value cannot smuggle in another assignment.
    assert sock.recv(4096) == b"STATUS=fault: stall READY=1"
    assert n.stopping("drive off, flushing records")
    assert sock.recv(4096) == b"STOPPING=1\nSTATUS=drive off, flushing records"
    assert n.notify(READY=True, MAINPID=os.getpid())
    assert sock.recv(4096) == f"READY=1\nMAINPID={os.getpid()}".encode()
    n.close()


def test_abstract_socket_names(tmp_path: Path):
    name = f"usmswitch-test-{os.getpid()}-{tmp_path.name}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(5)
    try:
        assert Notifier({"NOTIFY_SOCKET": "@" + name}).watchdog()
        assert sock.recv(4096) == b"WATCHDOG=1"
    finally:
        sock.close()


def test_without_notify_socket_everything_is_a_no_op():
    n = Notifier({})
    assert not n.enabled
    assert not n.ready() and not n.watchdog() and not n.maybe_watchdog(0)
    with pytest.raises(ValueError, match="'ready'"):
        n.notify(ready=1)  # still checked: a bug shows up in tests run outside systemd


def test_bad_notify_socket_is_named():
    with pytest.raises(ValueError, match="'relative/path'"):
        Notifier({"NOTIFY_SOCKET": "relative/path"})


def test_a_vanished_socket_fails_quietly(listener, tmp_path: Path):
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.status("up")
    sock.close()
    os.unlink(path)
    assert not n.status("still up?")
    assert n.failures == 1


def test_watchdog_interval_is_half_of_watchdog_usec():
    assert watchdog_interval_ns({"WATCHDOG_USEC": "10000000"}) == 5_000_000_000
    assert watchdog_interval_ns({}) is None
    assert watchdog_interval_ns({"WATCHDOG_USEC": "100000", "WATCHDOG_PID": str(os.getpid())}) == 50_000_000
    assert watchdog_interval_ns({"WATCHDOG_USEC": "100000", "WATCHDOG_PID": "1"}, pid=4242) is None
    for bad in ("-5", "ten", "0"):
        with pytest.raises(ValueError, match=repr(bad)):
            watchdog_interval_ns({"WATCHDOG_USEC": bad})


def test_maybe_watchdog_pings_every_half_period(listener):
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "100000"})  # ping every 50 ms
    sent = [t for t in range(0, 201_000_000, 1_000_000) if n.maybe_watchdog(1_000_000_000 + t)]
    assert sent == [0, 50_000_000, 100_000_000, 150_000_000, 200_000_000]
    assert received(sock) == ["WATCHDOG=1"] * 5


def test_module_level_notify_uses_the_environment(listener, monkeypatch):
    sock, path = listener
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setattr(sdnotify, "_default", None)
    assert sdnotify.notify(READY=1, STATUS="ready")
    assert sock.recv(4096) == b"READY=1\nSTATUS=ready"
