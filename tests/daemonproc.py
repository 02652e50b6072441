"""usmswitchd as a real subprocess for tests: start it, wait until its socket serves, stop it.

Importable from any test (tests/conftest.py puts this folder on sys.path first).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

from usmswitch.client import Client, RpcError

MS = 1_000_000


def daemon_args(tmp: Path, *extra: str, sim: bool = True, socket: Path | None = None) -> list[str]:
    """The usmswitchd command line for a daemon whose state and socket live under `tmp`."""
    sock = socket or tmp / "d.sock"
    args = [sys.executable, "-m", "usmswitch.daemon.cli", "--state-dir", str(tmp / "state")]
    args += ["--socket", str(sock), "--log-format", "json"]
    if sim:
        args.append("--sim")
    return [*args, *extra]


def slow_link(tmp: Path) -> list[str]:
    """`--config` of a serial link given 100 ms for a reply (a slow link's setting, docs/config.md),
    for a daemon on the firmware emulator: the fake device is a process or thread on the test's own
    busy machine, and its PONG came later than the 25 ms a real board is given (loaded runs: a clean
    stroke read MISMATCH, "no PONG came to check the device clock at the stroke's end")."""
    conf = tmp / "mcu-link.toml"
    conf.write_text('[driver]\nreply_timeout = "100ms"\n')
    return ["--config", str(conf)]


def spawn(args: list[str], **popen: object) -> subprocess.Popen[bytes]:
    """Start a daemon with stdout discarded and stderr (its JSON log) kept for the test."""
    popen.setdefault("stdout", subprocess.DEVNULL)
    popen.setdefault("stderr", subprocess.PIPE)
    return subprocess.Popen(args, **popen)  # type: ignore[call-overload]


def wait_serving(sock: Path, proc: subprocess.Popen[bytes], timeout_s: float = 20.0) -> None:
    """Return once the daemon is ready (`status.ready`: every part runs; the socket answers a moment
    before, while the rest starts)."""
    end = time.monotonic() + timeout_s
    while True:
        if proc.poll() is not None:
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise AssertionError(f"daemon exited {proc.returncode}: {err[-3000:]}")
        try:
            with Client(str(sock), timeout=5) as c:
                c.stats()
                if c.status()["ready"]:
                    return
            time.sleep(0.02)
        except (OSError, RpcError):
            if time.monotonic() > end:
                raise
            time.sleep(0.05)


def stop(proc: subprocess.Popen[bytes], timeout_s: float = 20.0) -> bytes:
    """SIGTERM and wait; returns what the daemon logged on stderr."""
    return stop_timed(proc, timeout_s)[0]


def stop_timed(proc: subprocess.Popen[bytes], timeout_s: float = 20.0) -> tuple[bytes, float]:
    """SIGTERM and wait; (what the daemon logged on stderr, seconds from the signal to its exit)."""
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        # Where it hangs: SIGABRT makes the daemon print every thread's stack (faulthandler).
        proc.send_signal(signal.SIGABRT)
        _, err = proc.communicate(timeout=30)
        tail = (err or b"").decode(errors="replace")[-12_000:]
        raise AssertionError(f"no exit {timeout_s:.0f} s after SIGTERM; its stderr ends:\n{tail}") from None
    return err or b"", time.monotonic() - t0


def child_pid(proc: subprocess.Popen[bytes], module: str) -> int:
    """The pid of the daemon's one child running `module` (usmswitch.server.rpc_process, ...)."""
    found = subprocess.run(
        ["pgrep", "-P", str(proc.pid), "-f", module], capture_output=True, text=True, check=False
    ).stdout.split()
    assert len(found) == 1, found
    return int(found[0])
