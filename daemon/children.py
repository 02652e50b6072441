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
