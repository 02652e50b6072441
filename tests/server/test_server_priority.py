"""The socket's server process beside a real-time loop (issue 35: an estop through the main socket,
TCP or the panel waited 15-600 ms for the CPU behind the machine's ordinary processes): its event
loop runs SCHED_FIFO two below the loop, the panel's thread (server/http_doors.py) one below that,
the metrics page's one below the panel's, its worker threads SCHED_FIFO 1 at most, a restarted
server is put back there; the records reads' processes (server/records_reads.py) at SCHED_OTHER,
holding no GIL of the event loop's; with the loop at SCHED_OTHER the server stays at SCHED_OTHER. A
real daemon (subprocess)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from pathlib import Path

import daemonproc
import pytest

from usmswitch.client import Client

SERVER = "usmswitch.server.rpc_process"
READER = "usmswitch.server.records_reads"


def _readers(server: int) -> list[int]:
    """The server's records reader processes."""
    found = subprocess.run(["pgrep", "-P", str(server), "-f", READER], capture_output=True, text=True)
    return [int(pid) for pid in found.stdout.split()]


def _policies(pid: int) -> dict[int, tuple[int, int]]:
    """Every thread of `pid`: (policy, SCHED_FIFO priority)."""
    out = {}
    for tid in map(int, os.listdir(f"/proc/{pid}/task")):
        with contextlib.suppress(ProcessLookupError):
            out[tid] = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
    return out


def _named(pid: int, *names: str) -> list[int]:
    """The threads of `pid` the kernel knows by one of `names` (prctl PR_SET_NAME)."""
    found = []
    for tid in map(int, os.listdir(f"/proc/{pid}/task")):
        with contextlib.suppress(FileNotFoundError):
            if Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip() in names:
                found.append(tid)
    return found


def _http_thread(pid: int, name: str = "rpc-http") -> int | None:
    """The thread serving the panel (named rpc-http; /metrics: rpc-metrics), if there is one."""
    return next(iter(_named(pid, name)), None)


def _estop_threads_above_the_helpers(daemon: int) -> bool:
    """The daemon's threads an estop or a stop passes through (the urgent channel's, the estop
    socket's, the stop signals') at SCHED_FIFO 49, the loop at 50, every other helper at 46: below
    the server's event loop (48) and HTTP doors (47), so no record writer's or bridge's burst holds
    an estop back."""
    urgent = _named(daemon, "rpc-urgent", "rpc-estop", "stop-signal")
    policies = _policies(daemon)
    others = {p for tid, p in policies.items() if tid not in urgent and tid != daemon}
    return (
        len(urgent) == 3
        and all(policies.get(tid) == (os.SCHED_FIFO, 49) for tid in urgent)
        and others <= {(os.SCHED_FIFO, 46), (os.SCHED_FIFO, 50)}
    )


def _until(what: str, check: object, timeout_s: float = 10.0) -> None:
    """Wait for `check()` (the service sets the server's priority after the loop's own)."""
    end = time.monotonic() + timeout_s
    while not check():  # type: ignore[operator]
        if time.monotonic() > end:
            raise AssertionError(f"not within {timeout_s:g} s: {what}")
        time.sleep(0.05)


def _scheduling(sock: Path) -> str:
    with Client(str(sock), timeout=10) as c:
        scheduling = c.status()["scheduling"]
        while scheduling.startswith("not yet set"):
            time.sleep(0.02)
            scheduling = c.status()["scheduling"]
    return str(scheduling)


def test_the_server_event_loop_runs_real_time_below_the_loop_and_its_workers_at_fifo_1(
    tmp_path: Path,
) -> None:
    sock = tmp_path / "d.sock"
    args = ("--period", "20ms", "--priority", "50", "--web", "127.0.0.1:0", "--metrics", "127.0.0.1:0")
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args))
    try:
        daemonproc.wait_serving(sock, proc)
        if not _scheduling(sock).startswith("SCHED_FIFO 50"):
            pytest.skip(f"this process may not use SCHED_FIFO: {_scheduling(sock)}")
        for round_ in ("first", "restarted"):
            server = daemonproc.child_pid(proc, SERVER)
            _until(
                f"the daemon's estop threads at SCHED_FIFO 49, its other helpers at 46 ({round_})",
                lambda: _estop_threads_above_the_helpers(proc.pid),
            )
            _until(
                f"the {round_} server's event loop at SCHED_FIFO 48",
                lambda server=server: _policies(server)[server] == (os.SCHED_FIFO, 48),
            )
            # The panel and /metrics on a thread of their own, one below: never ahead of an estop
            # on the Unix and TCP doors' loop (a burst of feed handshakes put 45 ms there).
            http = _http_thread(server)
            assert http is not None, "no rpc-http thread: the HTTP doors share the event loop"
            _until(
                f"the {round_} server's HTTP doors at SCHED_FIFO 47",
                lambda server=server, http=http: _policies(server).get(http) == (os.SCHED_FIFO, 47),
            )
            # /metrics a step below the panel: a scrape's rendering never ahead of the panel's estop.
            metrics = _http_thread(server, "rpc-metrics")
            assert metrics is not None, "no rpc-metrics thread: /metrics shares the panel's loop"
            _until(
                f"the {round_} server's metrics page at SCHED_FIFO 46",
                lambda server=server, t=metrics: _policies(server).get(t) == (os.SCHED_FIFO, 46),
            )
            with Client(str(sock), timeout=30) as c:  # a read of each lane starts its process
                c.history(5)
                c.history(2000)
            workers = {tid: p for tid, p in _policies(server).items() if tid not in (server, http, metrics)}
            # None of them above FIFO 1: a worker's bulk never outranks the event loop's estop.
            assert all(p in ((os.SCHED_FIFO, 1), (os.SCHED_OTHER, 0)) for p in workers.values()), workers
            readers = _readers(server)
            assert len(readers) == 2, f"one reader process a lane: {readers}"
            for reader in readers:  # below everything real-time, from their birth
                assert set(_policies(reader).values()) == {(os.SCHED_OTHER, 0)}, reader
            if round_ == "first":
                # Restarted by the daemon's bridge thread (SCHED_FIFO 46): put back at 48, its
                # new urgent channel's thread in the daemon at 49.
                os.kill(server, signal.SIGKILL)
                _until(
                    "a restarted server",
                    lambda old=server: _child_or_none(proc) not in (None, old),
                )
                daemonproc.wait_serving(sock, proc)
    finally:
        daemonproc.stop(proc)


def test_with_the_loop_at_sched_other_the_server_stays_there(tmp_path: Path) -> None:
    sock = tmp_path / "d.sock"
    args = ("--period", "20ms", "--priority", "0", "--web", "127.0.0.1:0")
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args))
    try:
        daemonproc.wait_serving(sock, proc)
        assert _scheduling(sock).startswith("SCHED_OTHER")
        server = daemonproc.child_pid(proc, SERVER)
        assert _http_thread(server) is not None
        with Client(str(sock), timeout=30) as c:
            c.history(5)
            c.history(2000)
        assert {p for p in _policies(server).values()} == {(os.SCHED_OTHER, 0)}
        assert len(_readers(server)) == 2
    finally:
        daemonproc.stop(proc)


def _child_or_none(proc: object) -> int | None:
    try:
        return daemonproc.child_pid(proc, SERVER)  # type: ignore[arg-type]
    except AssertionError:  # none (the old one being reaped) or two for a moment
        return None
