"""Start lateness of the software-timed path: usmswitchd on the real-time sim, beside cyclictest.

The daemon runs as a real subprocess (server process, record writer and all), closed loop at
T = 12 ms, and every stroke's lateness (actual start - (command + delay)) is read back from its
SQLite records. cyclictest (rt-tests) measures the kernel's own timer wake-up latency with the same
scheduling policy in the same run: the floor any user-space loop on this machine stands on. A third
row runs 8 client processes hammering `stats` on the daemon's socket during the run (issue 5: the
server must not disturb the loop).

Targets (issue 4): p50 <= 2 us, p99 <= 20 us and below cyclictest's p99, loop-thread CPU <= 20 % of
a core. Issue 5: p99 with 8 clients <= 1.2x without. p99.9 and max are reported, not targeted: this
VM stalls for milliseconds a few times a minute.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.table import print_table
from usmswitch.client import Client, RpcError

MS = 1_000_000
PERIOD = "15ms"
STROKES = int(os.environ.get("BENCH_LOOP_STROKES", "5000"))
LOADED_STROKES = int(os.environ.get("BENCH_LOOP_LOADED_STROKES", "3000"))
CLIENTS = 8
PRIORITY = 50


def percentiles(values: list[int]) -> tuple[float, float, float, float]:
    v = sorted(values)
    n = len(v)

    def at(q: float) -> float:
        return v[min(n - 1, max(0, int(q * n + 0.5) - 1))]

    return at(0.50), at(0.99), at(0.999), v[-1]


def fifo_allowed() -> bool:
    try:
        pid = os.fork()
    except OSError:
        return False
    if pid == 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PRIORITY))
            os._exit(0)
        except OSError:
            os._exit(1)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status) == 0


def thread_cpu_s(pid: int) -> float:
    """utime + stime of the process's main thread (the control loop) in seconds."""
    fields = Path(f"/proc/{pid}/task/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _hammer(path: str, stop_at: float, out: multiprocessing.Queue) -> None:
    n = 0
    with Client(path, timeout=10) as c:
        while time.monotonic() < stop_at:
            c.stats()
            n += 1
    out.put(n)


def run_daemon(strokes: int, fifo: bool, clients: int) -> dict[str, float]:
    tmp = Path(tempfile.mkdtemp(prefix="usm-bench-"))
    sock = tmp / "d.sock"
    cmd = [
        sys.executable, "-m", "usmswitch.daemon.cli", "--sim", "--state-dir", str(tmp / "state"),
        "--socket", str(sock), "--log-format", "json", "--log-level", "warning", "--target", "12ms",
        "--period", PERIOD, "--count", str(strokes), "--priority", str(PRIORITY if fifo else 0),
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        end = time.monotonic() + 30
        while True:
            try:
                with Client(str(sock), timeout=5) as c:
                    c.stats()
                break
            except (OSError, RpcError):
                if proc.poll() is not None or time.monotonic() > end:
                    raise RuntimeError(proc.stderr.read().decode()[-2000:]) from None
                time.sleep(0.05)
        cpu0, t0 = thread_cpu_s(proc.pid), time.monotonic()
        duration = strokes * 15e-3
        ctx = multiprocessing.get_context("spawn")
        q = ctx.Queue()
        hammers = [
            ctx.Process(target=_hammer, args=(str(sock), time.monotonic() + duration - 1, q))
            for _ in range(clients)
        ]
        for h in hammers:
            h.start()
        with Client(str(sock), timeout=10) as c:
            # The start-up run begins once the daemon's loop has run its first slack: the socket
            # may answer before it (state idle, then cycling), so wait for it, then for its end.
            # (Not "cycle 0": status names the next cycle, 1 before any stroke: the bench then
            # waited for nothing and read 0 strokes, twice at stop 42 and once at stop 43.)
            begun = time.monotonic() + 10
            while c.status()["state"] != "cycling":
                if time.monotonic() > begun:
                    raise RuntimeError("the daemon's start-up run did not begin within 10 s")
                time.sleep(0.01)
            while (last := c.status())["state"] == "cycling":
                time.sleep(0.2)
        cpu1, t1 = thread_cpu_s(proc.pid), time.monotonic()
        requests = sum(q.get(timeout=60) for _ in hammers)
        for h in hammers:
            h.join(10)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    con = sqlite3.connect(tmp / "state" / "records.sqlite")
    lates = [r[0] for r in con.execute("SELECT lateness_ns FROM cycles WHERE lateness_ns IS NOT NULL")]
    con.close()
    shutil.rmtree(tmp, ignore_errors=True)
    if len(lates) <= 20:  # once, beside a soak: no start-up run recorded (an IndexError here then)
        raise RuntimeError(
            f"usmswitchd recorded {len(lates)} strokes of {strokes} (it said: state {last['state']},"
            f" cycle {last['cycle']}, fault {last.get('fault')!r}): {' '.join(cmd)}"
        )
    p50, p99, p999, mx = percentiles(lates[20:])  # the first strokes include start-up
    return {
        "n": len(lates),
        "p50": p50 / 1e3,
        "p99": p99 / 1e3,
        "p99.9": p999 / 1e3,
        "max": mx / 1e3,
        "cpu": 100 * (cpu1 - cpu0) / (t1 - t0),
        "req_s": requests / (t1 - t0) if clients else 0.0,
    }


def ensure_cyclictest() -> str | None:
    path = shutil.which("cyclictest")
    if path is None and os.geteuid() == 0:
        subprocess.run(
            ["apt-get", "install", "-y", "-qq", "rt-tests"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        path = shutil.which("cyclictest")
    return path


def run_cyclictest(exe: str, fifo: bool, loops: int) -> dict[str, float]:
    """cyclictest's wake-up latency in us, one thread, 1 ms interval, its histogram for percentiles."""
    cmd = [exe, "-q", "-m", "-t1", "-i1000", f"-l{loops}", "-h20000"]
    if fifo:
        cmd.append(f"-p{PRIORITY}")
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=loops / 1000 + 60).stdout
    counts: list[tuple[int, int]] = []
    mx = 0
    for line in out.splitlines():
        if line.startswith("#"):
            if "Max Latencies" in line:
                mx = int(line.split(":")[1].split()[0])
            continue
        parts = line.split()
        if len(parts) >= 2 and parts[0].isdigit():
            counts.append((int(parts[0]), int(parts[1])))
    total = sum(c for _, c in counts)
    marks: dict[float, float] = {}
    acc = 0
    for us, c in counts:
        acc += c
        for q in (0.5, 0.99, 0.999):
            if q not in marks and acc >= q * total:
                marks[q] = us
    return {"n": total, "p50": marks[0.5], "p99": marks[0.99], "p99.9": marks[0.999], "max": mx}


def python_sleep(n: int = 2000) -> dict[str, float]:
    """Plain time.sleep to a deadline, for contrast with sleep-then-spin."""
    lates = []
    for _ in range(n):
        target = time.monotonic_ns() + 2 * MS
        time.sleep((target - time.monotonic_ns()) / 1e9)
        lates.append(time.monotonic_ns() - target)
    p50, p99, p999, mx = percentiles(lates)
    return {"n": n, "p50": p50 / 1e3, "p99": p99 / 1e3, "p99.9": p999 / 1e3, "max": mx / 1e3}


def main() -> int:
    fifo = fifo_allowed()
    policy = "SCHED_FIFO" if fifo else "SCHED_OTHER"
    print(f"policy {policy} (priority {PRIORITY}); period {PERIOD}; {os.cpu_count()} CPUs", flush=True)
    rows = []
    quiet = run_daemon(STROKES, fifo, 0)
    rows.append(("usmswitchd loop, no load", policy, quiet))
    loaded = run_daemon(LOADED_STROKES, fifo, CLIENTS)
    rows.append((f"usmswitchd loop, {CLIENTS} clients on stats", policy, loaded))
    if fifo:
        rows.append(
            ("usmswitchd loop, no load", "SCHED_OTHER", run_daemon(max(1000, STROKES // 3), False, 0))
        )
    exe = ensure_cyclictest()
    ct = None
    if exe:
        ct = run_cyclictest(exe, fifo, 20_000)
        rows.append(("cyclictest (kernel timer)", policy, ct))
        if fifo:
            rows.append(("cyclictest (kernel timer)", "SCHED_OTHER", run_cyclictest(exe, False, 10_000)))
    rows.append(("python time.sleep alone", "SCHED_OTHER", python_sleep()))
    print_table(
        ["what", "policy", "n", "p50 us", "p99 us", "p99.9 us", "max us", "loop CPU %", "stats req/s"],
        [
            (
                name, pol, int(r["n"]), f"{r['p50']:.1f}", f"{r['p99']:.1f}", f"{r['p99.9']:.1f}",
                f"{r['max']:.0f}", f"{r['cpu']:.1f}" if "cpu" in r else "-",
                f"{r['req_s']:.0f}" if r.get("req_s") else "-",
            )
            for name, pol, r in rows
        ],
        title="start lateness: actual start - (command + delay), from the daemon's records",
    )  # fmt: skip
    checks = [
        ("p50 <= 2 us", quiet["p50"] <= 2.0),
        ("p99 <= 20 us", quiet["p99"] <= 20.0),
        ("p99 below cyclictest's p99", ct is None or quiet["p99"] < ct["p99"]),
        ("loop CPU <= 20 % of a core", quiet["cpu"] <= 20.0),
        (f"p99 with {CLIENTS} clients <= 1.2x without", loaded["p99"] <= 1.2 * max(quiet["p99"], 1.0)),
    ]
    for name, ok in checks:
        print(f"  {'ok  ' if ok else 'MISS'} {name}")
    return 0 if all(ok for _, ok in checks) else 1
