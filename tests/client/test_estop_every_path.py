"""Issue 35, items 1-3 and 9, through a real usmswitchd (subprocess, sim): the estop by every
documented path whatever else holds the doors, `set_drive` under FAULT, no-op settings."""

from __future__ import annotations

import socket
import sqlite3
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import daemonproc
import pytest
from rawsock import Raw

from usmswitch.client import Client, ErrorCode, RpcError
from usmswitch.protocol.wire import estop_socket_path


class Rig:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.sock = tmp / "d.sock"
        self.estop_sock = estop_socket_path(self.sock)
        args = daemonproc.daemon_args(tmp, "--target", "12ms", "--period", "20ms")
        self.proc = daemonproc.spawn(args)
        daemonproc.wait_serving(self.sock, self.proc)

    def client(self) -> Client:
        return Client(str(self.sock), timeout=10)

    def reset(self) -> None:
        with self.client() as c:
            if c.status()["state"] == "fault":
                c.reset_fault()

    def state(self) -> str:
        with self.client() as c:
            return str(c.status()["state"])

    def ctl(self, *argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "usmswitch.client.ctl", "--socket", str(self.sock), *argv],
            capture_output=True,
            text=True,
            timeout=60,
        )

    def hold_every_slot(self) -> list[Raw]:
        """Issue 35, item 2's load: 64 subscribed main connections and 16 estop-socket holders
        (each answered: well behaved, just holding)."""
        held = []
        for _ in range(64):
            raw = Raw(str(self.sock))
            assert raw.call("subscribe", ["stroke", "state"])[2] is None
            held.append(raw)
        for _ in range(16):
            raw = Raw(str(self.estop_sock))
            assert raw.call("ping")[3] == "pong"
            held.append(raw)
        return held


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    r = Rig(tmp_path_factory.mktemp("estop"))
    yield r
    if r.proc.poll() is None:
        daemonproc.stop(r.proc)


def test_usmswitchctl_estop_gets_through_every_slot_held(rig: Rig) -> None:
    """Item 1 and 2: with the estop socket's slots held, `usmswitchctl estop` worked 0 of 5 (exit 3,
    or killed by SIGPIPE: 141, nothing printed) and the rig kept cycling."""
    rig.reset()
    held = rig.hold_every_slot()
    try:
        for _ in range(3):
            r = rig.ctl("estop")
            assert r.returncode == 0, (r.returncode, r.stdout, r.stderr)
            assert "emergency stop: state fault" in r.stdout
    finally:
        for raw in held:
            raw.close()
    assert rig.state() == "fault"


def test_client_estop_gets_through_every_slot_held(rig: Rig) -> None:
    """Item 2: 64 subscribed Unix connections plus 16 estop holders: Client.estop() 0 of 5."""
    rig.reset()
    held = rig.hold_every_slot()
    try:
        for _ in range(3):
            with Client(str(rig.sock), timeout=10) as c:
                assert c.estop()["state"] == "fault"
    finally:
        for raw in held:
            raw.close()
    assert rig.state() == "fault"


def test_the_fault_names_the_path_that_pressed_the_estop(rig: Rig) -> None:
    """Issue 37's bites: every estop latched `estop (socket)`, the panel's too (its own test says
    `estop (panel)`; TCP's is test_ctl's). The estop socket names itself whatever a caller says."""

    def pressed(press: Callable[[], object]) -> str:
        rig.reset()
        press()
        with rig.client() as c:
            return str(c.status()["fault"])

    def raw_estop(path: Path, *params: str) -> None:
        raw = Raw(str(path))
        try:
            assert raw.call("estop", *params)[2] is None
        finally:
            raw.close()

    assert pressed(lambda: rig.client().estop()) == "estop (estop socket)"
    assert pressed(lambda: rig.client().estop(by="lab script")) == "estop (lab script, estop socket)"
    assert pressed(lambda: rig.ctl("estop")) == "estop (usmswitchctl, estop socket)"
    assert pressed(lambda: raw_estop(rig.estop_sock, "panel")) == "estop (panel, estop socket)"
    assert pressed(lambda: raw_estop(rig.sock)) == "estop (main socket or TCP)"
    aside = rig.tmp / "estop-socket-aside"
    rig.estop_sock.rename(aside)  # gone: the client's estop takes the main socket
    try:
        assert pressed(lambda: rig.client().estop()) == "estop (main socket)"
        assert pressed(lambda: rig.ctl("estop")) == "estop (usmswitchctl, main socket)"
    finally:
        aside.rename(rig.estop_sock)
    rig.reset()


def test_set_drive_is_refused_with_fault_while_fault_is_latched(rig: Rig) -> None:
    """Item 3: set_drive after an estop succeeded (exit 0) and said enabled: true in FAULT."""
    rig.reset()
    with rig.client() as c:
        c.estop()
        with pytest.raises(RpcError) as err:
            c.set_drive(frequency_hz=40_000.0)
        assert err.value.code == ErrorCode.FAULT
        assert c.set_drive()["enabled"] is False  # reading is answered: the drive is off
    r = rig.ctl("drive", "--frequency", "40kHz")
    assert r.returncode == 4, (r.stdout, r.stderr)
    rig.reset()
    with rig.client() as c:
        assert c.set_drive(frequency_hz=40_000.0)["frequency_hz"] == 40_000.0


def _events(rig: Rig, kind: str) -> int:
    db = sqlite3.connect(f"file:{rig.tmp / 'state' / 'records.sqlite'}?mode=ro", uri=True)
    try:
        return int(db.execute("SELECT count(*) FROM events WHERE kind = ?", (kind,)).fetchone()[0])
    finally:
        db.close()


def test_no_op_settings_store_nothing(rig: Rig) -> None:
    """Item 9: each no-op set_mode stored an event row (326-552 rows a second)."""
    rig.reset()
    with rig.client() as c:
        mode = c.status()["mode"]
        c.set_mode(mode)  # settles the mode as it is
        target = c.get_target()["target_on_ns"]
        c.set_target(target)
        c.stop_cycling()
        modes, targets = _events(rig, "mode"), _events(rig, "target")
        for _ in range(20):
            c.set_mode(mode)
            c.set_target(target)
        c.stats()  # the record writer commits events in its own time: give it a moment's turn
    with rig.client() as c:
        c.set_mode("open" if mode == "closed" else "closed")  # a real change is stored
        c.set_mode(mode)
    # Events are committed by the record writer: wait (bounded) until the two real changes are in.
    for _ in range(200):
        if _events(rig, "mode") >= modes + 2:
            break
        subprocess.run(["sleep", "0.05"], check=True)
    assert _events(rig, "mode") == modes + 2
    assert _events(rig, "target") == targets


def test_a_daemon_closing_under_a_send_is_an_error_not_a_silent_sigpipe(tmp_path: Path) -> None:
    """Item 1: SIGPIPE was SIG_DFL for every command: a socket closed under the CLI's send killed it
    (exit 141, nothing printed). A listener that accepts and closes at once stands in for a door
    that drops us; the CLI must say so and exit 3."""
    path = tmp_path / "d.sock"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.listen(64)
    stop = threading.Event()

    def drop_everyone() -> None:
        listener.settimeout(0.1)
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            conn.close()

    thread = threading.Thread(target=drop_everyone, daemon=True)
    thread.start()
    try:
        for argv in (["estop"], ["status"]):
            r = subprocess.run(
                [sys.executable, "-m", "usmswitch.client.ctl", "--socket", str(path), *argv],
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert r.returncode == 3, (argv, r.returncode, r.stderr)
            assert "usmswitchctl:" in r.stderr and "Traceback" not in r.stderr
    finally:
        stop.set()
        thread.join()
        listener.close()
