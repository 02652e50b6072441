"""A bench's own usmswitchd process, ended as a service manager ends it."""

from __future__ import annotations

import signal
import subprocess


def stop_daemon(proc: subprocess.Popen[bytes], wait_s: float = 60) -> None:
    """SIGTERM (the daemon flushes its records and exits), SIGKILL if it has not within `wait_s`."""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(wait_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
