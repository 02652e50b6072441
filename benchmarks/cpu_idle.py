"""The machine's idle while the abuse bench measures: its CPUs halting (as it comes) or polling.

An idle CPU halts, and wakes for the next interrupt through its C-state's exit or, in a virtual
machine, through the hypervisor. On the Firecracker VM these benchmarks run on (no cpuidle driver:
every idle vCPU executes HLT and leaves to the host) a fresh Unix request to a Python thread blocked
at SCHED_FIFO read p50 0.62 / p99 3.3 ms with the CPUs halting and p50 0.42 / p99 0.59 ms with
none ever idle; the panel's POST estop to a cycling daemon p99 8.97 -> 4.14 ms, the estop socket's
5.54 -> 2.23 (stop 51, 150-300 each). Real-time hosts are tuned against exactly this: `idle=poll`
or `processor.max_cstate=1` on the kernel's command line, or a /dev/cpu_dma_latency of 0 held open
where a cpuidle driver honours it (cyclictest holds one; docs/service.md).

`Polling` is `idle=poll` done from user space for the time of a measurement: one spinner per CPU at
SCHED_IDLE, which runs only where nothing else would; any other task that wakes preempts it at once.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Any

#: "poll" (the default: the CPUs kept from halting, as a tuned real-time host's are) or "halt".
MODES = ("poll", "halt")


def cpuidle_driver() -> str:
    """The kernel's cpuidle driver ("none": idle CPUs halt whatever /dev/cpu_dma_latency says)."""
    try:
        return Path("/sys/devices/system/cpu/cpuidle/current_driver").read_text().strip()
    except OSError:
        return "unknown"


def _on_cpu(cpu: int, policy: int, priority: int = 0) -> None:
    """This process on `cpu` alone (where allowed), at `policy` and `priority`."""
    with contextlib.suppress(OSError):
        os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, policy, os.sched_param(priority))


def _spin(cpu: int) -> None:
    """The body of one spinner: on `cpu` alone, at SCHED_IDLE, forever."""
    _on_cpu(cpu, os.SCHED_IDLE)
    while True:
        pass


class Polling:
    """A SCHED_IDLE spinner on each CPU this process may use, until `close()`."""

    def __init__(self, ctx: Any) -> None:
        self.procs = [ctx.Process(target=_spin, args=(cpu,), daemon=True) for cpu in os.sched_getaffinity(0)]
        for p in self.procs:
            p.start()

    def close(self) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.join(5)
        self.procs = []


def steal_ms() -> float:
    """Time the hypervisor held this machine's vCPUs from running since boot, summed over them, ms
    (/proc/stat's steal; 0.0 where there is none to read). A stall of a vCPU stops whatever runs
    on it, at any priority: on the Firecracker VM these benchmarks run on, a SCHED_FIFO thread
    spinning on an idle machine saw gaps of 1-4.6 ms a few times in 20 s while the steal rose
    (`vcpu_holds`, stop 58). Counted in ticks (10 ms): a window's share, not which request a gap hit."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    except OSError:
        return 0.0
    ticks = int(fields[8]) if len(fields) > 8 and fields[0] == "cpu" else 0
    return ticks * 1000.0 / os.sysconf("SC_CLK_TCK")


#: A holds probe's gaps shorter than this are the kernel's own (a tick, an interrupt), not a hold.
HOLD_NS = 1_000_000


def _spin_for_gaps(cpu: int, seconds: float, priority: int, conn: Any) -> None:
    """On `cpu`, read the clock in a bare loop for `seconds` and send back every gap over HOLD_NS.
    In bursts of 0.4 s with 0.1 s asleep between, so that the kernel's RT throttling (a real-time
    task is held for the rest of each second past 0.95 s of it) never makes a gap of its own."""
    with contextlib.suppress(OSError):
        _on_cpu(cpu, os.SCHED_FIFO if priority else os.SCHED_OTHER, priority)
    now = time.monotonic_ns
    gaps = []
    end = now() + int(seconds * 1e9)
    while now() < end:
        last = now()
        burst_end = min(end, last + 400_000_000)
        while last < burst_end:
            t = now()
            if t - last > HOLD_NS:
                gaps.append(t - last)
            last = t
        time.sleep(0.1)
    conn.send(gaps)


def vcpu_holds(ctx: Any, seconds: float, priority: int) -> str:
    """The machine held from under a spinning SCHED_FIFO `priority` thread (0: SCHED_OTHER, whose
    gaps include other tasks'), `seconds` on each CPU in turn: a line of the gaps over 1 ms and
    the steal counted meanwhile. Nothing in the guest runs above a real-time spinner for that long:
    such a gap is the hypervisor's (or an interrupt's) and stops whatever runs there."""
    held = []  # each CPU's gaps, ns
    stolen = steal_ms()
    for cpu in sorted(os.sched_getaffinity(0)):
        ours, theirs = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_spin_for_gaps, args=(cpu, seconds, priority, theirs), daemon=True)
        proc.start()
        held.append(ours.recv())
        proc.join(5)
    per_cpu = " / ".join(str(len(gaps)) for gaps in held)
    longest = max((g for gaps in held for g in gaps), default=0) / 1e6
    return (
        f"the machine's holds (a SCHED_{'FIFO' if priority else 'OTHER'} spinner, {seconds:g} s on each"
        f" CPU): gaps over 1 ms {per_cpu}, the longest {longest:.2f} ms; steal {steal_ms() - stolen:.0f} ms"
    )


def describe(mode: str) -> str:
    """The line the bench prints about the machine's idle."""
    driver = cpuidle_driver()
    if mode == "poll":
        return (
            f"the machine's idle: polling (a SCHED_IDLE spinner per CPU, idle=poll's equivalent; cpuidle"
            f" driver {driver}); BENCH_ABUSE_IDLE=halt measures with the CPUs halting as they come"
        )
    return (
        f"the machine's idle: halting as it comes (cpuidle driver {driver});"
        " BENCH_ABUSE_IDLE=poll keeps the CPUs awake"
    )


if __name__ == "__main__":  # python -m benchmarks.cpu_idle [seconds a CPU]: the holds alone
    import multiprocessing
    import sys

    from benchmarks.bench_loop import PRIORITY, fifo_allowed

    print(
        vcpu_holds(
            multiprocessing.get_context("spawn"),
            float(sys.argv[1]) if len(sys.argv) > 1 else 10.0,
            PRIORITY + 1 if fifo_allowed() else 0,
        )
    )
