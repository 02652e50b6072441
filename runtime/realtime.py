"""Real-time scheduling for the loop thread: SCHED_FIFO, CPU affinity, locked memory.

Each option is asked for separately and may be refused (no CAP_SYS_NICE, RLIMIT_RTPRIO 0, a CPU
outside the cpuset, RLIMIT_MEMLOCK too small): a refusal is logged and the daemon carries on with
what it got. `apply_realtime` reports both, for the log and the status reply.

On Linux the scheduler and affinity calls with pid 0 act on the calling thread only: call
`apply_realtime` from the loop thread, then `lift_helpers` for the threads started before it (they
share the GIL with the loop: see there); `drop_realtime` puts a thread started by a real-time one
back on SCHED_OTHER.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import os
import platform
import resource
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import structlog

log = structlog.get_logger("usmswitch.realtime")

# mlockall flags: asm-generic values, except on the architectures that define their own.
_MCL = {"ppc": (0x2000, 0x4000), "sparc": (0x2000, 0x4000), "alpha": (8192, 16384)}
CAP_IPC_LOCK = 14
_PR_SET_NAME = 15


@dataclass(frozen=True, slots=True)
class RealtimeResult:
    """What `apply_realtime` got: each option name with a description, or the reason it was refused."""

    applied: dict[str, str] = field(default_factory=dict)
    refused: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """True when nothing asked for was refused."""
        return not self.refused


def apply_realtime(
    sched_fifo_priority: int = 0, cpu_affinity: Sequence[int] = (), mlockall: bool = False
) -> RealtimeResult:
    """Ask for SCHED_FIFO, a CPU set and locked memory for the calling thread; carry on if refused."""
    if isinstance(sched_fifo_priority, bool) or not isinstance(sched_fifo_priority, int):
        raise ValueError(f"sched_fifo_priority must be an integer 0..99, got {sched_fifo_priority!r}")
    if not 0 <= sched_fifo_priority <= 99:
        raise ValueError(f"sched_fifo_priority must be 0 (off) or 1..99, got {sched_fifo_priority}")
    cpus = list(cpu_affinity)
    for cpu in cpus:
        if isinstance(cpu, bool) or not isinstance(cpu, int) or cpu < 0:
            raise ValueError(f"cpu_affinity entries must be CPU numbers >= 0, got {cpu!r}")
    applied: dict[str, str] = {}
    refused: dict[str, str] = {}
    if cpus:
        try:
            os.sched_setaffinity(0, cpus)
            applied["cpu_affinity"] = ",".join(str(c) for c in sorted(set(cpus)))
        except OSError as exc:
            refused["cpu_affinity"] = (
                f"{_describe(exc)} (cpus {cpus}, allowed {sorted(os.sched_getaffinity(0))})"
            )
    if sched_fifo_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(sched_fifo_priority))
            applied["sched_fifo_priority"] = f"SCHED_FIFO {sched_fifo_priority}"
        except OSError as exc:
            rtprio = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
            refused["sched_fifo_priority"] = (
                f"{_describe(exc)} (priority {sched_fifo_priority}, RLIMIT_RTPRIO {_limit(rtprio)}; "
                "needs CAP_SYS_NICE or LimitRTPRIO)"
            )
    if mlockall:
        reason = _lock_memory()
        if reason is None:
            applied["mlockall"] = "MCL_CURRENT|MCL_FUTURE"
        else:
            refused["mlockall"] = reason
    result = RealtimeResult(applied, refused)
    for name, what in applied.items():
        log.info("realtime applied", option=name, value=what)
    for name, why in refused.items():
        log.warning("realtime refused, carrying on without it", option=name, reason=why)
    return result


def renice(increment: int, process: str, cost: str) -> bool:
    """Lower this process's priority by `increment` (os.nice); a refusal is a warning saying `cost`.

    A service manager's syscall filter or a container may deny setpriority: the process then runs
    at its parent's priority, which costs the loop some CPU under load but is no reason to stop.
    """
    if not increment:
        return True
    try:
        os.nice(increment)
        return True
    except OSError as exc:
        return _nice_refused(process, increment, exc, cost)


def renice_child(pid: int, nice: int, process: str, cost: str) -> bool:
    """Every thread of child `pid` (Linux's nice is per thread) to this process's nice + `nice`,
    never raising one; a refusal is the warning `renice` gives. Lowering the priority of one's own
    children is permitted, but a service manager's syscall filter may deny it all the same."""
    target = os.getpriority(os.PRIO_PROCESS, 0) + nice
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(ProcessLookupError):  # a thread that just ended
                now = os.getpriority(os.PRIO_PROCESS, int(tid))
                if now < target:
                    os.setpriority(os.PRIO_PROCESS, int(tid), target)
    except FileNotFoundError:  # the child just ended: its restart starts at `nice`
        return True
    except OSError as exc:
        return _nice_refused(process, nice, exc, cost)
    return True


def lift_child(pid: int, priority: int) -> bool:
    """SCHED_FIFO `priority` for every thread of child `pid`; False when refused (no CAP_SYS_NICE
    and an RLIMIT_RTPRIO below `priority`: a daemon without real-time) or when it has ended."""
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(ProcessLookupError):  # a thread that just ended
                os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
    except OSError:
        return False
    return True


def _nice_refused(process: str, nice: int, exc: OSError, cost: str) -> bool:
    log.warning(
        "nice refused, carrying on at the inherited priority",
        process=process,
        nice=nice,
        reason=_describe(exc),
        cost=cost,
    )
    return False


#: The loop's SCHED_FIFO priority when the config says "auto" and the process may use it: above
#: the kernel's threaded IRQ handlers' default (50) would starve them; at it, they share the CPU.
AUTO_PRIORITY = 50
CAP_SYS_NICE = 23


def server_fifo(tid: int, priority: int) -> bool:
    """SCHED_FIFO `priority` (0: SCHED_OTHER) for thread `tid` of the socket's server process (0:
    the calling thread); False and a warning when refused: it serves at SCHED_OTHER."""
    policy = os.SCHED_FIFO if priority else os.SCHED_OTHER
    try:
        os.sched_setscheduler(tid, policy, os.sched_param(priority))
    except ProcessLookupError:  # it just ended: its restart is started at `priority`
        return True
    except OSError as exc:
        log.warning(
            "the server process stays at SCHED_OTHER: an estop through it waits for the CPU with the"
            " machine's other work",
            refused=f"SCHED_FIFO {priority}",
            error=str(exc),
        )
        return False
    return True


def fifo_refusal(priority: int) -> str | None:
    """Why this process may not use SCHED_FIFO `priority` (None: it may): CAP_SYS_NICE (root has it,
    unless a container or a unit took it away) or an RLIMIT_RTPRIO at least that high allow it."""
    if _has_capability(CAP_SYS_NICE):
        return None
    rtprio = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
    if rtprio == resource.RLIM_INFINITY or rtprio >= priority:
        return None
    who = "root without CAP_SYS_NICE" if os.geteuid() == 0 else "no CAP_SYS_NICE"
    return f"{who}, RLIMIT_RTPRIO {_limit(rtprio)} < {priority}"


def resolve_priority(setting: int | str) -> tuple[int, str | None]:
    """The priority to ask for and, when that is 0 because of "auto", why (for the log and status)."""
    if setting != "auto":
        return int(setting), None
    why = fifo_refusal(AUTO_PRIORITY)
    return (0, why) if why else (AUTO_PRIORITY, None)


def scheduling_text(result: RealtimeResult, priority: int, not_permitted: str | None) -> str:
    """How the loop thread is scheduled, in words for `status` and `stats`."""
    if "sched_fifo_priority" in result.applied:
        return result.applied["sched_fifo_priority"]
    if "sched_fifo_priority" in result.refused:
        return f"SCHED_OTHER (SCHED_FIFO {priority} refused: {result.refused['sched_fifo_priority']})"
    if not_permitted:
        return f"SCHED_OTHER (SCHED_FIFO not permitted: {not_permitted})"
    return "SCHED_OTHER (realtime.sched_fifo_priority = 0)"


def lift_helpers(priority: int, above: Mapping[str, int] | None = None) -> list[str]:
    """SCHED_FIFO `priority` for every other thread of this process; the names of those lifted.

    The helper threads (record writer, socket bridge) share the GIL with the loop. At SCHED_OTHER
    an ordinary process on the machine can preempt one while it holds the GIL, and the loop then
    waits for a whole timeslice of someone else (milliseconds of start lateness): a priority
    inversion. At SCHED_FIFO they are never preempted by ordinary processes, never by the loop's
    core's own work, and give the GIL back within the switch interval. Threads they start later
    inherit the policy. Threads named in `above` get the priority given there instead (the
    estop's own: never queued behind a helper's burst at the same priority).
    """
    lifted = []
    me = threading.get_native_id()
    above = above or {}
    for t in threading.enumerate():
        tid = t.native_id
        if tid is None or tid == me or not t.is_alive():
            continue
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(above.get(t.name, priority)))
            lifted.append(t.name)
        except OSError as exc:  # gone meanwhile, or no permission: carry on at SCHED_OTHER
            log.warning("helper thread stays at SCHED_OTHER", thread=t.name, reason=_describe(exc))
    return lifted


def name_thread(name: str) -> None:
    """The calling thread's name as the kernel shows it (`ps -L`, /proc/PID/task/TID/comm; 15
    bytes at most): which thread of the daemon or server runs at which priority, for operators
    and tests."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        libc.prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0)


def drop_realtime() -> bool:
    """Put the calling thread back on SCHED_OTHER (helper threads inherit the loop's policy)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        return True
    except OSError:
        return False


def _lock_memory() -> str | None:
    """mlockall(MCL_CURRENT | MCL_FUTURE), or the reason it was not done."""
    soft = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
    if soft != resource.RLIM_INFINITY and not _has_capability(CAP_IPC_LOCK):
        # With a finite limit, MCL_FUTURE turns every later allocation past the limit into a
        # failure (a MemoryError in the loop). Refuse rather than arm that trap.
        return (
            f"RLIMIT_MEMLOCK is {_limit(soft)} bytes and no CAP_IPC_LOCK: later allocations past the "
            "limit would fail; set LimitMEMLOCK=infinity or grant CAP_IPC_LOCK"
        )
    current, future = _mcl_flags()
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        rc = libc.mlockall(current | future)
    except (OSError, AttributeError) as exc:
        return f"mlockall unavailable: {exc}"
    if rc != 0:
        return f"{_describe(OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno())))} from mlockall"
    return None


def _mcl_flags() -> tuple[int, int]:
    machine = platform.machine().lower()
    for prefix, flags in _MCL.items():
        if machine.startswith(prefix):
            return flags
    return (1, 2)


def _has_capability(cap: int) -> bool:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) >> cap & 1)
    except OSError:
        pass
    return False


def _describe(exc: OSError) -> str:
    name = errno.errorcode.get(exc.errno or 0, "error")
    return f"{name}: {exc.strerror or exc}"


def _limit(value: int) -> str:
    return "unlimited" if value == resource.RLIM_INFINITY else str(value)
