"""Issue 36: a call that outlives the client's timeout is named, with how long it has waited, and
told apart from a daemon gone (a ping on a new connection): `usmswitchctl stats --run N` on a big
run used to print "no answer from the daemon" while the server computed on. Through a real Unix
socket to a real daemon whose records file holds 100,000 strokes (tests/conftest.py)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from daemonproc import child_pid, daemon_args, spawn, stop, wait_serving

from usmswitch.client import Client, ReplyTimeout
from usmswitch.client.ctl import args as ctl_args


@pytest.fixture
def big_daemon(records_100k: Path, tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], Path]]:
    state = tmp_path / "state"
    state.mkdir()
    shutil.copy(records_100k, state / "records.sqlite")
    sock = tmp_path / "d.sock"
    proc = spawn(daemon_args(tmp_path, "--no-autostart", "--priority", "0", socket=sock))
    try:
        wait_serving(sock, proc)
        yield proc, sock
    finally:
        stop(proc)


def test_a_slow_call_is_named_and_the_daemon_said_to_be_up(big_daemon: tuple) -> None:
    proc, sock = big_daemon
    # The statistics of 100,000 strokes by cycle range: a full scan in the server process (~1-5 s),
    # far past a 50 ms timeout.
    with Client(str(sock), timeout=0.05) as c, pytest.raises(ReplyTimeout) as caught:
        c.stats(cycles=(1, 100_000))
    exc = caught.value
    assert exc.method == "stats" and exc.waited_s >= 0.05 and exc.ping_ms is not None
    text = str(exc)
    assert text.startswith("stats: no reply from") and "the daemon is up" in text, text
    assert "slow request, not a daemon gone" in text
    # usmswitchctl says the same, exit 3.
    ctl = [sys.executable, "-m", "usmswitch.client.ctl.main", "--socket", str(sock), "--timeout", "50ms"]
    done = subprocess.run([*ctl, "stats", "--first", "1", "--last", "100000"], capture_output=True, text=True)
    assert done.returncode == ctl_args.EXIT_CONNECT, done.stderr
    assert "timed out: stats: no reply" in done.stderr and "the daemon is up" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_a_server_that_answers_nothing_is_said_so(big_daemon: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    proc, sock = big_daemon
    server = child_pid(proc, "usmswitch.server.rpc_process")
    probes = []
    probe = Client._ping_ms
    monkeypatch.setattr(Client, "_ping_ms", lambda self: probes.append(1) or probe(self))
    with Client(str(sock), timeout=0.3) as c:
        os.kill(server, signal.SIGSTOP)
        try:
            with pytest.raises(ReplyTimeout) as caught:
                c.ping()
        finally:
            os.kill(server, signal.SIGCONT)
    exc = caught.value
    assert exc.method == "ping" and exc.ping_ms is None
    assert "a ping on a new connection got no answer either" in str(exc)
    # One probe: the probe's own ping, timed out, probed again, 100 deep (31 s for a 0.3 s timeout).
    assert len(probes) == 1, f"{len(probes)} probes"
