"""systemd's notify protocol: READY=1, STATUS=..., WATCHDOG=1, STOPPING=1 on $NOTIFY_SOCKET.

A few lines instead of a dependency: each message is one datagram of "KEY=value" lines sent to
the AF_UNIX datagram socket systemd names in $NOTIFY_SOCKET (a path, or "@name" in the abstract
namespace). Without $NOTIFY_SOCKET (a terminal, a test) every call is a no-op returning False.
Sending never blocks and never raises into the loop: a failure returns False.

The watchdog ping must prove the loop is alive, so the loop sends it (`maybe_watchdog(now_ns)` in
its slack, and at least that often while idle), not a free-running thread.
"""

from __future__ import annotations

import os
import re
import socket
from collections.abc import Mapping
from typing import Any

_FIELD = re.compile(r"^[A-Z][A-Z0-9_]*$")


def watchdog_interval_ns(env: Mapping[str, str] | None = None, pid: int | None = None) -> int | None:
    """Half of $WATCHDOG_USEC in ns (how often to ping), or None when the watchdog is not for us."""
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    if not usec.isdigit() or int(usec) == 0:
        raise ValueError(f"WATCHDOG_USEC must be a positive integer of microseconds, got {usec!r}")
    owner = env.get("WATCHDOG_PID")
    if owner:
        if not owner.isdigit():
            raise ValueError(f"WATCHDOG_PID must be a process id, got {owner!r}")
        if int(owner) != (os.getpid() if pid is None else pid):
            return None  # meant for another process (we were forked or exec'ed by it)
    return int(usec) * 1000 // 2


def _address(value: str) -> str | bytes:
    if value.startswith("@"):
        return b"\0" + value[1:].encode()  # abstract namespace: no file, a leading NUL
    if value.startswith("/"):
        return value
    raise ValueError(f"NOTIFY_SOCKET must be an absolute path or '@abstract-name', got {value!r}")


class Notifier:
    """One connection to systemd's notify socket (or none, and every call is a no-op)."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        raw = env.get("NOTIFY_SOCKET", "")
        self.address: str | bytes | None = _address(raw) if raw else None
        self.watchdog_interval_ns = watchdog_interval_ns(env)
        self._next_watchdog_ns: int | None = None
        self._sock: socket.socket | None = None
        #: Datagrams that could not be sent (socket gone, buffer full).
        self.failures = 0

    @property
    def enabled(self) -> bool:
        """True when systemd is listening ($NOTIFY_SOCKET set)."""
        return self.address is not None

    def notify(self, **fields: Any) -> bool:
        """Send one message of KEY=value lines (`notify(READY=1, STATUS="cycling")`); True if sent."""
        if not fields:
            raise ValueError("notify needs at least one field, e.g. READY=1")
        lines = []
        for key, value in fields.items():
            if not _FIELD.match(key):
                raise ValueError(f"notify field names are upper-case words like READY, got {key!r}")
            text = str(int(value)) if isinstance(value, bool) else str(value)
            # A newline would start a new field: systemd would read injected assignments.
            lines.append(f"{key}={text.replace(chr(10), ' ')}")
        if self.address is None:
            return False
        return self._send("\n".join(lines).encode())

    def ready(self, status: str = "") -> bool:
        """Tell systemd start-up is done (Type=notify): dependants start, `systemctl start` returns."""
        return self.notify(READY=1, STATUS=status) if status else self.notify(READY=1)

    def status(self, text: str) -> bool:
        """The one-line status `systemctl status` shows."""
        return self.notify(STATUS=text)

    def stopping(self, status: str = "") -> bool:
        """Tell systemd shutdown has begun (so a slow stop is not mistaken for a hang)."""
        return self.notify(STOPPING=1, STATUS=status) if status else self.notify(STOPPING=1)

    def watchdog(self) -> bool:
        """Ping the watchdog now."""
        return self.notify(WATCHDOG=1)

    def maybe_watchdog(self, now_ns: int) -> bool:
        """Ping if half the watchdog period has passed since the last ping; cheap when not due."""
        if self.watchdog_interval_ns is None or self.address is None:
            return False
        if self._next_watchdog_ns is not None and now_ns < self._next_watchdog_ns:
            return False
        self._next_watchdog_ns = now_ns + self.watchdog_interval_ns
        return self.watchdog()

    def close(self) -> None:
        """Release the socket (later calls reopen it)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _send(self, data: bytes) -> bool:
        try:
            if self._sock is None:
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                sock.setblocking(False)
                self._sock = sock
            self._sock.sendto(data, self.address)  # type: ignore[arg-type]
            return True
        except OSError:
            self.failures += 1
            self.close()
            return False


_default: Notifier | None = None


def notify(**fields: Any) -> bool:
    """Send KEY=value fields to systemd through a process-wide Notifier (no-op without $NOTIFY_SOCKET)."""
    global _default
    if _default is None:
        _default = Notifier()
    return _default.notify(**fields)
