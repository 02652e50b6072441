"""Waiting for a child process to exit without polling.

`Popen.wait(timeout)` polls with sleeps that grow to 50 ms, so a child that exits at once is
reaped up to 50 ms late: at shutdown that alone broke the 100 ms SIGTERM-to-exit target. A pidfd
(Linux >= 5.3) becomes readable the moment the child exits; `select` on it waits exactly that long.
"""

from __future__ import annotations

import contextlib
import os
import select
import subprocess


def wait_exit(proc: subprocess.Popen[bytes], timeout_s: float) -> int | None:
    """The child's exit status once it has exited, or None after `timeout_s` (it still runs)."""
    pidfd_open = getattr(os, "pidfd_open", None)
    if pidfd_open is not None and proc.returncode is None:
        with contextlib.suppress(OSError):  # no pidfds here (old kernel, reaped already): poll
            fd = pidfd_open(proc.pid)
            try:
                ready, _, _ = select.select([fd], [], [], timeout_s)
            finally:
                os.close(fd)
            if not ready:
                return None
            timeout_s = 1.0  # it has exited: reaping it is immediate (or another thread just did)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return None


#: How long a child killed at stop is waited for. Its exit runs at its own priority: a niced
#: child on a busy machine can take 50 ms and more to be torn down after SIGKILL, time the
#: daemon's exit must not wait for (a killed process holds no lock and serves nobody; whoever
#: reaps orphans reaps it).
KILLED_REAP_S = 0.005


def end_child(proc: subprocess.Popen[bytes], grace_s: float) -> int | None:
    """Give a child told to stop `grace_s` to exit, then SIGKILL it; its exit status, or None when
    it was killed and is still being torn down (it cannot run another instruction)."""
    code = wait_exit(proc, grace_s)
    if code is not None:
        return code
    with contextlib.suppress(ProcessLookupError):
        proc.kill()
    return wait_exit(proc, KILLED_REAP_S)
