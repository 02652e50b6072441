"""RPC throughput and latency of `stats`, beside a bare asyncio msgpack server measured in the same run.

Targets (issue 5): >= 15k req/s and p99 <= 200 us with 1 client process, >= 40k req/s with 8;
(issue 26) req/s at or above the peer's and p99 at or below it, with 1 and with 8 clients.
Also measured, for the architecture decision (docs/protocol.md): the wake-up lateness of a
stand-in loop thread in the server's host process (sleep, then spin to a deadline every 10.5 ms),
without load and with 8 clients hammering `stats` on the server in a process and in a thread.
The control loop's own lateness under load is measured with the real loop once it is wired.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.table import print_table
from usmswitch.server.rpc import RpcServer

DURATION_NS = 2_000_000_000
ROUNDS = 3
PERIOD_NS = 10_500_000
SPIN_NS = 1_000_000
WARM_UP = 200  # calls each client makes before the window

# A stats result of realistic size (the loop's snapshot: two directions and the combined one).
_DIR = {
    "count": 50_000,
    "strokes": 50_000,
    **{f"{k}_{s}_ns": 10_512_345.6 for k in ("operating", "total", "error") for s in ("mean", "std")},
    **{f"{k}_max_abs_ns": 10_999_999 for k in ("operating", "total", "error")},
    "max_abs_error_pct": 0.4123,
    **{f"abs_error_p{q}_ns": 123_456 for q in (50, 95, 99)},
    **{f"lateness_p{q}_ns": 12_345 for q in ("50", "99", "99_9")},
    "lateness_max_ns": 99_999,
    "late": 3,
    "stalls": 0,
    "bounces": 12,
    "faults": 0,
}
STATS = {
    "state": "cycling",
    "mode": "closed",
    "fault": "",
    "cycle": 100_001,
    "target_on_ns": 12_000_000,
    "target_off_ns": 12_000_000,
    "spurious_edges": 0,
    "overruns": 0,
    "driver_bounces": 24,
    "all": _DIR,
    "on": {**_DIR, "order": 1, "coefficients": [0.998], "ready": True},
    "off": {**_DIR, "order": 1, "coefficients": [0.997], "ready": True},
}

# The peer: the least a Python asyncio msgpack-RPC server can do (decode, answer pre-packed).
BARE_SERVER = """
import asyncio, msgpack, os, socket, sys
result = msgpack.packb(msgpack.unpackb(bytes.fromhex(sys.argv[2])))
class P(asyncio.Protocol):
    def connection_made(self, t):
        self.t = t
        self.u = msgpack.Unpacker(raw=False)
    def data_received(self, data):
        self.u.feed(data)
        out = [b"\\x94\\x01" + msgpack.packb(m[1]) + b"\\xc0" + result for m in self.u]
        self.t.write(b"".join(out))
async def main():
    server = await asyncio.get_running_loop().create_unix_server(P, sys.argv[1])
    print("ready", flush=True)
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
asyncio.run(main())
"""

# One client process: sequential `stats` calls through usmswitch's Client between two instants.
CLIENT = """
import json, sys, time
from usmswitch.client import Client
path, start_ns, end_ns, warm_up = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
c = Client(path)
for _ in range(warm_up):
    c.call("stats")
while time.monotonic_ns() < start_ns:
    time.sleep(0.001)
lat = []
clock = time.perf_counter_ns
t0, cpu0 = clock(), time.process_time_ns()
while time.monotonic_ns() < end_ns:
    a = clock()
    c.call("stats")
    lat.append(clock() - a)
elapsed, cpu = clock() - t0, time.process_time_ns() - cpu0
lat.sort()
p50, p99 = lat[len(lat) // 2], lat[int(len(lat) * 0.99)]
print(json.dumps({"n": len(lat), "elapsed_ns": elapsed, "cpu_ns": cpu, "p50": p50, "p99": p99}))
"""


def process_cpu_s(pid: int) -> float:
    """CPU seconds (user and system) of every thread of `pid` so far."""
    ticks = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{tid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        ticks += int(fields[11]) + int(fields[12])
    return ticks / os.sysconf("SC_CLK_TCK")


def run_clients(path: str, n: int, duration_ns: int, server_pid: int | None = None) -> dict[str, float]:
    """Start n client processes against path; total req/s, the worst client's p50/p99, and the
    CPU each request cost the clients and (with `server_pid`) the server."""
    start = time.monotonic_ns() + 1_500_000_000 + n * 100_000_000
    end = start + duration_ns
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", CLIENT, path, str(start), str(end), str(WARM_UP)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(n)
    ]
    results = []
    cpu0 = process_cpu_s(server_pid) if server_pid is not None else 0.0
    for p in procs:
        out, _ = p.communicate(timeout=60)
        if p.returncode != 0:
            raise RuntimeError(f"a benchmark client failed (exit {p.returncode})")
        results.append(json.loads(out))
    calls = sum(r["n"] for r in results)
    # The server's CPU is read over the clients' whole life (their warm-up and start included):
    # a little high, alike for both servers.
    server_cpu = process_cpu_s(server_pid) - cpu0 if server_pid is not None else float("nan")
    return {
        "rate": sum(r["n"] / (r["elapsed_ns"] / 1e9) for r in results),
        "p50_us": max(r["p50"] for r in results) / 1000,
        "p99_us": max(r["p99"] for r in results) / 1000,
        "client_cpu_us": sum(r["cpu_ns"] for r in results) / calls / 1000,
        "server_cpu_us": server_cpu / (calls + WARM_UP * n) * 1e6,
    }


def stand_in_loop(duration_ns: int) -> list[int]:
    """Wake every PERIOD_NS (sleep, then spin the last SPIN_NS) and record how late each wake is."""
    late = []
    clock = time.perf_counter_ns
    deadline = clock() + PERIOD_NS
    end = clock() + duration_ns
    while deadline < end:
        remaining = deadline - clock() - SPIN_NS
        if remaining > 0:
            time.sleep(remaining / 1e9)
        while clock() < deadline:
            pass
        late.append(clock() - deadline)
        deadline += PERIOD_NS
    return late


def lateness_under_load(path: str | None) -> tuple[float, float, float]:
    """The stand-in loop's lateness p50/p99/max (us), with 8 clients on `path` (None: no load)."""
    box: dict[str, dict[str, float]] = {}
    if path is not None:
        hammer = threading.Thread(
            target=lambda: box.update(r=run_clients(path, 8, DURATION_NS + 1_000_000_000))
        )
        hammer.start()
        time.sleep(1.5 + 0.8 + 0.5)  # the clients start together after their warm-up
    late = stand_in_loop(DURATION_NS)
    if path is not None:
        hammer.join()
    late.sort()
    return statistics.median(late) / 1000, late[int(len(late) * 0.99)] / 1000, late[-1] / 1000


def main() -> int:
    """Measure, print the tables, and return 1 if a throughput or latency target is missed."""
    import msgpack

    tmp = Path(tempfile.mkdtemp(prefix="benchrpc-"))
    bare_path = str(tmp / "bare.sock")
    bare = subprocess.Popen(
        [sys.executable, "-c", BARE_SERVER, bare_path, msgpack.packb(STATS).hex()],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert bare.stdout is not None
    bare.stdout.readline()
    servers = {}
    for isolation in ("process", "thread"):
        # At the daemon's nice, as the daemon runs it while its loop is at SCHED_FIFO (5 above
        # when the loop is refused it: daemon/service.py).
        srv = RpcServer(
            {},
            unix_path=tmp / f"{isolation}.sock",
            snapshot_methods=["stats"],
            isolation=isolation,
            nice=0,
        )
        srv.snapshot("stats", STATS)
        srv.start()
        servers[isolation] = srv
    try:
        rows = []
        measured: dict[tuple[str, int], dict[str, float]] = {}
        # Ours and the peer's measured in turn, ROUNDS times each, and each figure the median of
        # its rounds: one 2 s window of either moves by 10 % from run to run on 2 cores, more than
        # the difference the rows compare, and a drift of the machine lands on both alike.
        for n in (1, 8):
            rounds: dict[str, list[dict[str, float]]] = {}
            for _ in range(ROUNDS):
                for name, path, pid in (
                    ("bare asyncio (peer)", bare_path, bare.pid),
                    ("RpcServer", str(servers["process"].unix_path), servers["process"].server_pid),
                ):
                    rounds.setdefault(name, []).append(run_clients(path, n, DURATION_NS, pid))
            for name, runs in rounds.items():
                keys = ("rate", "p50_us", "p99_us", "server_cpu_us", "client_cpu_us")
                r = {k: statistics.median(x[k] for x in runs) for k in keys}
                measured[(name, n)] = r
                peer = measured.get(("bare asyncio (peer)", n), r)
                ratio = f"{r['rate'] / peer['rate']:.2f}"
                cpu = (f"{r['server_cpu_us']:.1f}", f"{r['client_cpu_us']:.1f}")
                rows.append(
                    [name, n, f"{r['rate']:.0f}", ratio, f"{r['p50_us']:.0f}", f"{r['p99_us']:.0f}", *cpu]
                )
        print_table(
            ["server", "clients", "req/s", "x peer", "p50 us", "p99 us", "server CPU us", "client CPU us"],
            rows,
            title=f"stats over the Unix socket, {os.cpu_count()} CPUs, median of {ROUNDS} rounds of "
            f"{DURATION_NS / 1e9:g} s, ours and the peer's in turn; CPU per request, the server's "
            "process and the clients' (ours busy-polls while a core is spare: docs/protocol.md)",
        )
        mine1, mine8 = measured[("RpcServer", 1)], measured[("RpcServer", 8)]
        peer1, peer8 = measured[("bare asyncio (peer)", 1)], measured[("bare asyncio (peer)", 8)]
        targets = [
            # issue 26: at or above the peer, in the same run
            ("1 client req/s >= peer", mine1["rate"] >= peer1["rate"]),
            ("1 client p99 <= peer", mine1["p99_us"] <= peer1["p99_us"]),
            ("8 clients req/s >= peer", mine8["rate"] >= peer8["rate"]),
            ("8 clients p99 <= peer", mine8["p99_us"] <= peer8["p99_us"]),
            # issue 5
            ("1 client req/s >= 15000", mine1["rate"] >= 15_000),
            ("1 client p99 <= 200 us", mine1["p99_us"] <= 200),
            ("8 clients req/s >= 40000", mine8["rate"] >= 40_000),
        ]
        print()
        print_table(["target", "met"], [[t, "yes" if ok else "NO"] for t, ok in targets])

        print()
        rows = []
        quiet = lateness_under_load(None)
        rows.append(["no load", *(f"{x:.0f}" for x in quiet)])
        for isolation in ("process", "thread"):
            lat = lateness_under_load(str(servers[isolation].unix_path))
            rows.append([f"8 clients, server in a {isolation}", *(f"{x:.0f}" for x in lat)])
        print_table(
            ["stand-in loop thread in the server's host process", "p50 us", "p99 us", "max us"],
            rows,
            title=f"wake-up lateness, sleep then spin to a deadline every {PERIOD_NS / 1e6:g} ms",
        )
        return 0 if all(ok for _, ok in targets) else 1
    finally:
        for srv in servers.values():
            srv.stop()
        if bare.stdin is not None:
            bare.stdin.close()
        bare.wait(timeout=10)
        for p in tmp.iterdir():
            p.unlink()
        tmp.rmdir()


if __name__ == "__main__":
    sys.exit(main())
