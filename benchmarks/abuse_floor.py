"""The machine's own floor beside each path's estop (benchmarks/bench_abuse.py), measured in the same
window under the same load: a fresh Unix connection's request and answer to the least server there
is, one Python thread that accepts, reads a frame and answers it, at the priority the daemon's
estop thread runs at.

An estop's time is this exchange and the daemon's work (the drive off, the reply packed) and, by
the other paths, more hops. On a 2-core VM whose timer wakes a SCHED_FIFO thread 53 us late on
average and 3.4 ms at worst idle (cyclictest, stop 50), a path's p99 over 5 ms may be the machine's
more than the daemon's: this column says which, window by window.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
from pathlib import Path
from typing import Any

import msgpack

from benchmarks.abuse_loads import connect_unix

_PING = msgpack.packb([0, 1, "ping", []])
_PONG = msgpack.packb([1, 1, None, "pong"])


def serve_floor(path: str, priority: int) -> None:
    """The body of the floor's process: answer each connection's one frame, then close it."""
    if priority:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(128)
    while True:
        conn, _ = listener.accept()
        with conn:
            conn.settimeout(1.0)
            with contextlib.suppress(OSError):
                if conn.recv(512):
                    conn.sendall(_PONG)


class Floor:
    """The floor's server in a process of its own (`ctx`: a multiprocessing context) and its
    client: `exchange()` times one fresh connection's request and answer, in ms."""

    def __init__(self, ctx: Any, tmp: Path, priority: int) -> None:
        self.path = str(tmp / "floor.sock")
        self.proc = ctx.Process(target=serve_floor, args=(self.path, priority), daemon=True)
        self.proc.start()
        end = time.monotonic() + 30
        while not os.path.exists(self.path):
            if time.monotonic() > end or not self.proc.is_alive():
                raise RuntimeError("the floor's server did not start")
            time.sleep(0.02)

    def exchange(self) -> float:
        t0 = time.perf_counter_ns()
        with connect_unix(self.path) as s:
            s.sendall(_PING)
            got = b""
            while len(got) < len(_PONG):
                data = s.recv(512)
                if not data:
                    raise ConnectionError("the floor's server closed without answering")
                got += data
        return (time.perf_counter_ns() - t0) / 1e6

    def sample(self, n: int, rng: Any) -> list[float]:
        """`n` exchanges, each after a random 5-35 ms (as the paths' estops are spaced), in ms."""
        took = []
        for _ in range(n):
            time.sleep(rng.uniform(0.005, 0.035))
            took.append(self.exchange())
        return took

    def close(self) -> None:
        self.proc.kill()
        self.proc.join(5)
