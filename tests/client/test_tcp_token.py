"""Issue 35, item 12, through a real usmswitchd: TCP with no token configured gets one the daemon
makes (a file beside the socket for its group), wrong tokens are logged, and the estop reaches the
daemon over TCP however its slots are held."""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path

import daemonproc
from rawsock import Raw

from usmswitch.client import Client, ConnectionClosed, RpcError
from usmswitch.protocol.sockets import tcp_token_path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_tcp_without_a_token_gets_one_made_and_guesses_are_logged(tmp_path: Path) -> None:
    port = _free_port()
    cfg = tmp_path / "d.toml"
    cfg.write_text(f'[socket]\ntcp = "127.0.0.1:{port}"\nmax_tcp_clients = 4\n')
    sock = tmp_path / "d.sock"
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, "--config", str(cfg), socket=sock))
    try:
        daemonproc.wait_serving(sock, proc)
        path = tcp_token_path(sock)
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o640
        token = path.read_text().strip()
        assert len(token) >= 32
        with Client(f"tcp://127.0.0.1:{port}", token=token, timeout=10) as c:
            assert c.ping() == "pong"
        for guess in ("wrong-guess-0000000", "wrong-guess-1111111"):
            try:
                Client(f"tcp://127.0.0.1:{port}", token=guess, timeout=10).ping()
            except (RpcError, ConnectionClosed):
                pass
            else:
                raise AssertionError("a wrong token was taken")
        # Every TCP slot held by silent connections: the estop still gets through over TCP.
        held = [Raw(("127.0.0.1", port), socket.AF_INET) for _ in range(4)]
        with Client(f"tcp://127.0.0.1:{port}", token=token, timeout=10) as c:
            assert c.estop()["state"] == "fault"
        for raw in held:
            raw.close()
    finally:
        err = daemonproc.stop(proc).decode(errors="replace")
    assert "TCP auth failed from 127.0.0.1 (1 in a row" in err
    assert not path.exists()  # removed at stop
