"""A real systemd, booted as PID 1 of a PID namespace of its own, for the service tests.

On a machine where we are root and no systemd runs (CI, these sandboxes), `unshare` gives systemd a
PID namespace, a mount namespace and a UTS namespace, and `nsenter` reaches it. The mount namespace
keeps the machine untouched:

* /tmp is a private tmpfs: at boot systemd-tmpfiles empties /tmp, which would otherwise be the
  machine's own (every other process there would lose its files);
* /etc, /opt, /usr and /var are overlays whose upper layers live on a tmpfs: the units, the
  sysusers user and group, the config, a venv the docs install under /opt and the state directory
  written by the test vanish with the namespace;
  the host's own usmswitch config, state and logs are hidden in them (a machine where the service
  was installed), so a test sees only what it made.

systemd boots to basic.target only (journald, sysusers, tmpfiles; no getty, no database servers
that would bind the machine's ports). `close()` ends it by its pid (SIGKILL from the parent
namespace takes the whole namespace with it).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path

SYSTEMD = Path("/lib/systemd/systemd")
#: Where the overlays' upper layers live (a tmpfs mounted there inside the namespace only).
SCRATCH = "/mnt"
OVERLAID = ("/etc", "/opt", "/usr", "/var")


class BootError(RuntimeError):
    """systemd could not be booted here; the message says why (for the skip line)."""


def _boot_script() -> str:
    lines = [
        "mount -t tmpfs tmpfs /tmp",
        f"mount -t tmpfs tmpfs {SCRATCH}",
    ]
    for top in OVERLAID:
        name = top.strip("/")
        upper, work = f"{SCRATCH}/upper/{name}", f"{SCRATCH}/work/{name}"
        lines.append(f"mkdir -p {upper} {work}")
        lines.append(f"mount -t overlay overlay -o lowerdir={top},upperdir={upper},workdir={work} {top}")
    # What the host has of usmswitch is hidden (whiteouts in the upper layers; the host's files are
    # untouched): the tests see only what they install.
    lines.append("rm -rf /etc/usmswitch /var/lib/usmswitch /var/lib/private/usmswitch /var/log/usmswitch")
    lines.append(f"exec {SYSTEMD} --system --unit=basic.target")
    return " && ".join(lines)


class BootedSystemd:
    """One systemd in its namespaces; `run` executes a command inside them."""

    def __init__(self) -> None:
        if not SYSTEMD.exists():
            raise BootError(f"{SYSTEMD} is missing (apt: systemd)")
        if os.geteuid() != 0:
            raise BootError("booting systemd in a namespace needs root")
        unshare = shutil.which("unshare")
        if unshare is None or shutil.which("nsenter") is None:
            raise BootError("unshare/nsenter missing (apt: util-linux)")
        cmd = [unshare, "--pid", "--fork", "--mount-proc", "--mount", "--uts", "--propagation", "private"]
        self.proc = subprocess.Popen(
            [*cmd, "sh", "-c", _boot_script()],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        self.pid = self._find_init()
        self._wait_running()

    def _find_init(self) -> int:
        """The pid (in our namespace) of the systemd that unshare's child exec'd."""
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                out = self.proc.stdout.read().decode(errors="replace") if self.proc.stdout else ""
                raise BootError(
                    f"unshare refused or systemd exited (status {self.proc.returncode}): {out.strip()}"
                )
            children = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children")
            for pid in children.read_text().split() if children.exists() else ():
                try:
                    exe = os.readlink(f"/proc/{pid}/exe")
                except OSError:
                    continue
                if exe.endswith("/systemd"):
                    return int(pid)
            time.sleep(0.05)
        self.close()
        raise BootError("systemd did not start within 20 s")

    def _wait_running(self) -> None:
        deadline = time.monotonic() + 60
        state = ""
        while time.monotonic() < deadline:
            state = self.run(["systemctl", "is-system-running"], check=False).stdout.strip()
            if state in ("running", "degraded"):
                return
            time.sleep(0.1)
        self.close()
        raise BootError(f"systemd did not finish booting within 60 s (state {state!r})")

    def run(
        self,
        cmd: Sequence[str],
        *,
        check: bool = True,
        timeout: float = 60,
        as_user: tuple[int, int, Sequence[int]] | None = None,
        env: dict[str, str] | None = None,
        cwd: str | None = None,
    ) -> subprocess.CompletedProcess[str]:
        """`cmd` inside the namespaces; `as_user` = (uid, gid, supplementary gids) drops root first."""
        prefix = ["nsenter", "-t", str(self.pid), "-m", "-p", "-u"]
        if cwd is not None:
            prefix += [f"--wd={cwd}"]
        if as_user is not None:
            uid, gid, groups = as_user
            prefix += [
                "setpriv",
                f"--reuid={uid}",
                f"--regid={gid}",
                "--groups=" + ",".join(str(g) for g in groups),
                "--",
            ]
        proc = subprocess.run(
            [*prefix, *cmd], capture_output=True, text=True, timeout=timeout, env=env, check=False
        )
        if check and proc.returncode != 0:
            raise AssertionError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
        return proc

    def systemctl(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        return self.run(["systemctl", "--no-pager", *args], check=check)

    def show(self, unit: str, *props: str) -> dict[str, str]:
        out = self.systemctl("show", unit, "-p", ",".join(props)).stdout
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def wait_for(self, unit: str, timeout: float = 30, **want: str) -> dict[str, str]:
        """Poll `systemctl show` until every property has the wanted value; the last values."""
        deadline = time.monotonic() + timeout
        got: dict[str, str] = {}
        while time.monotonic() < deadline:
            got = self.show(unit, *want)
            if all(got.get(k) == v for k, v in want.items()):
                return got
            time.sleep(0.1)
        raise AssertionError(f"{unit}: wanted {want} within {timeout} s, have {got}")

    def journal(self, unit: str) -> str:
        return self.run(["journalctl", "--no-pager", "-o", "cat", "-u", unit], check=False).stdout

    def close(self) -> None:
        """End the namespace's init by its pid; everything in the namespace dies with it."""
        for pid in (getattr(self, "pid", None), self.proc.pid):
            if pid:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=10)
