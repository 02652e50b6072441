"""Busy polling in the server process: a lone script's next call finds the server awake; clients
that need every core, and an idle daemon, find it asleep."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from usmswitch.client import Client
from usmswitch.server.busy_poll import ACTIVE_NS, BusyPoll, usable_cpus
from usmswitch.server.rpc import RpcServer


class _Loop:
    """Records call_soon; `turn()` runs what was scheduled, as one pass of an event loop."""

    def __init__(self) -> None:
        self.ready: list[Callable[[], object]] = []

    def call_soon(self, fn: Callable[[], object]) -> None:
        self.ready.append(fn)

    def turn(self) -> None:
        ready, self.ready = self.ready, []
        for fn in ready:
            fn()


def _poll(cpus: int, window_ns: int = 200_000) -> tuple[BusyPoll, _Loop, list[int]]:
    loop, now = _Loop(), [0]
    return BusyPoll(loop, window_ns, cpus, clock=lambda: now[0]), loop, now  # type: ignore[arg-type]


def test_a_lone_client_keeps_the_loop_polling_until_the_window_after_its_request():
    bp, loop, now = _poll(cpus=2)
    bp.request("a", 1_000)
    assert bp.polling and len(loop.ready) == 1
    for t in (1_000, 100_000, 200_999):  # before the window's end: polled again next pass
        now[0] = t
        loop.turn()
        assert len(loop.ready) == 1
    bp.request("a", 150_000)  # a request inside the window extends it, no second poller
    now[0] = 349_999
    loop.turn()
    assert len(loop.ready) == 1 and bp.windows == 1
    now[0] = 350_000
    loop.turn()
    assert not loop.ready and not bp.polling  # the loop sleeps in epoll again


def test_clients_that_need_every_core_stop_the_poll_and_open_none():
    bp, loop, now = _poll(cpus=2)  # one core beside the server's: one client may be polled for
    bp.request("a", 0)
    bp.request("b", 10_000)
    assert bp.declined == 1
    loop.turn()
    assert not bp.polling and not loop.ready  # stopped at its next pass, not at the window's end
    bp.request("a", 20_000)
    assert bp.declined == 2 and not loop.ready
    # b falls silent: after ACTIVE_NS it no longer counts, and a's requests are polled for again.
    bp.request("a", 10_000 + ACTIVE_NS + 1)
    assert bp.polling and loop.ready
    assert set(bp.active) == {"a"}


def test_on_four_cores_three_clients_are_polled_for_and_a_closed_one_is_forgotten():
    bp, loop, _ = _poll(cpus=4)
    for c in ("a", "b", "c"):
        bp.request(c, 0)
    assert bp.polling and bp.declined == 0
    bp.request("d", 1)
    assert bp.declined == 1
    bp.forget("d")
    bp.request("a", 2)
    assert bp.declined == 1 and bp.until_ns == 200_002


def test_one_core_is_never_polled_and_the_window_must_be_positive():
    bp, loop, _ = _poll(cpus=1)
    bp.request("a", 0)
    assert not bp.polling and not loop.ready and bp.declined == 1
    for bad in (0, -1, True, 1.5):
        with pytest.raises(ValueError, match="window_ns must be a positive integer"):
            BusyPoll(loop, bad, 2)  # type: ignore[arg-type]


def test_the_server_refuses_a_negative_window():
    with pytest.raises(ValueError, match="busy_poll_ns must be an integer >= 0"):
        RpcServer({}, unix_path="/tmp/x.sock", busy_poll_ns=-1)


# -- the server process: what the kernel counts ----------------------------------------------------
def _sleeps_and_cpu(pid: int) -> tuple[int, float]:
    """Voluntary context switches (each a sleep in epoll) and CPU seconds of every thread of pid."""
    sleeps, ticks = 0, 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{tid}/status") as f:
            sleeps += sum(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches"))
        with open(f"/proc/{pid}/task/{tid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        ticks += int(fields[11]) + int(fields[12])
    return sleeps, ticks / os.sysconf("SC_CLK_TCK")


def _cpu_times() -> tuple[int, int]:
    """(idle, total) jiffies of the whole machine (/proc/stat)."""
    with open("/proc/stat") as f:
        fields = [int(x) for x in f.readline().split()[1:]]
    return fields[3] + fields[4], sum(fields)


def _idle_cores(before: tuple[int, int], after: tuple[int, int]) -> float:
    """How many cores were idle, on average, between two `_cpu_times()`."""
    total = after[1] - before[1]
    return 0.0 if total <= 0 else (after[0] - before[0]) / total * (os.cpu_count() or 1)


def _sleeps_per_call(srv: RpcServer, calls: int = 400) -> float:
    pid = srv.server_pid
    assert pid is not None
    with Client(str(srv.unix_path)) as c:
        for _ in range(50):
            c.call("stats")
        before, _ = _sleeps_and_cpu(pid)
        for _ in range(calls):
            c.call("stats")
        after, _ = _sleeps_and_cpu(pid)
    return (after - before) / calls


def test_a_lone_scripts_calls_find_the_server_awake_only_with_busy_polling(sockdir: Path):
    if usable_cpus() < 2:
        pytest.skip("one usable CPU: the server never busy-polls (no core is spare)")
    servers = {}
    for window_ns in (0, 200_000):
        srv = RpcServer(
            {},
            unix_path=sockdir / f"rpc{window_ns}.sock",
            snapshot_methods=["stats"],
            busy_poll_ns=window_ns,
            nice=0,
        )
        srv.snapshot("stats", {"count": 1})
        srv.start()
        servers[window_ns] = srv
    try:
        sleeps, idle = {}, {}
        for window_ns, srv in servers.items():
            before = _cpu_times()
            sleeps[window_ns] = _sleeps_per_call(srv)
            idle[window_ns] = _idle_cores(before, _cpu_times())
    finally:
        for srv in servers.values():
            srv.stop()
    # Without it the server sleeps in epoll between a script's calls (once a call on an idle
    # machine; less where the machine's load delays it past the next request). With it, it is
    # awake when the next call comes, but where this machine held the client back past the window.
    ok = sleeps[200_000] < min(0.25, sleeps[0] / 4)
    if not ok and idle[200_000] < 0.5:
        # The claim is for a core to spare: with none, the poller is preempted and sleeps anyway.
        pytest.xfail(
            f"{idle[200_000]:.2f} of {os.cpu_count()} cores idle during the polled calls (sleeps per"
            f" call {sleeps}): the machine is too busy now to judge busy polling"
        )
    assert ok, f"sleeps per call, by window: {sleeps}; cores idle: {idle}"


def test_an_idle_server_sleeps_after_the_window(sockdir: Path):
    srv = RpcServer({}, unix_path=sockdir / "rpc.sock", snapshot_methods=["stats"], nice=0)
    srv.snapshot("stats", {"count": 1})
    srv.start()
    try:
        pid = srv.server_pid
        assert pid is not None
        _sleeps_per_call(srv, 100)
        time.sleep(0.1)
        _, cpu0 = _sleeps_and_cpu(pid)
        time.sleep(1.0)
        _, cpu1 = _sleeps_and_cpu(pid)
    finally:
        srv.stop()
    # Its sweeper's wake-ups every 50 ms cost well under a tick; a poll left running would cost 1 s.
    assert cpu1 - cpu0 <= 0.05, f"the idle server used {cpu1 - cpu0:.2f} s of CPU in 1 s"
