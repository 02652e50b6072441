"""The PostgreSQL shipper in a process of its own (`python -m usmswitch.daemon.shipper_process`).

The daemon starts the fleet's process: this module is the daemon's handle on it (spawn, watch,
restart, stop) and the process's set-up as one of the daemon's (priority, signals, logs, exit);
what the process does, shipping and the pipe's words, is usmswitch.fleet.shipper.

Why a process: catching up a backlog is seconds of CPU-bound Python (reading rows, formatting
COPY data) and network waits that end at random instants. In the loop's process every return from
such a wait competes for the GIL, even with the shipper waiting its turn between rows, and moved
the loop's start lateness p99 to 1.5-1.9x idle (bench_abuse, "shipper catching up a backlog").
In a process of its own at nice 10 it shares nothing with the loop but the CPU, where the loop's
SCHED_FIFO wins, as the socket's server process does (docs/protocol.md, "Architecture").

The daemon (`ShipperProcess`) spawns it with the settings on its stdin's first line (the URL with
its password never appears in the process list), then writes `w` (records committed) and at the
end `stop NS` (drain for at most NS ns). The child writes its status as a JSON line on stdout when
it changes (at most 5 times a second) and logs to the daemon's stderr in the daemon's format.
A child that dies is started again after a pause; the records wait in SQLite meanwhile.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import quote

import structlog

from usmswitch.fleet.pg_schema import redact_url
from usmswitch.runtime.children import KILLED_REAP_S, end_child, wait_exit
from usmswitch.runtime.process_exit import exit_now
from usmswitch.runtime.realtime import lift_child

log = structlog.get_logger("usmswitch.shipper")

RESTART_PAUSE_S = 2.0
#: How long past its drain a stopping shipper may take to end before it is killed.
EXIT_GRACE_S = 0.01
#: The most stop() takes beyond its drain: the grace, then the wait for a killed one.
STOP_OVERHEAD_NS = int((EXIT_GRACE_S + KILLED_REAP_S) * 1e9) + 1_000_000
NICE = 10
#: The child's SCHED_FIFO priority while it drains at the daemon's stop: the lowest there is.
DRAIN_PRIORITY = 1


class ShipperProcess:
    """The daemon's handle on the shipper process: the PostgresShipper interface the daemon uses."""

    #: The most stop() takes beyond its drain (usmswitch.fleet.hooks.Shipper).
    stop_overhead_ns = STOP_OVERHEAD_NS

    def __init__(
        self,
        records_path: str | Path,
        url: str,
        rig: str,
        *,
        log_format: str = "auto",
        log_level: str = "info",
        gate: Any = lambda: None,
    ) -> None:
        if importlib.util.find_spec("psycopg") is None:  # found, not imported: the daemon never loads it
            raise RuntimeError("records.postgres_url needs psycopg 3: pip install 'usmswitch[postgres]'")
        self.settings = {
            "records": str(records_path),
            "url": url,
            "rig": rig,
            "log_format": log_format,
            "log_level": log_level,
        }
        self.where = redact_url(url)
        #: Called before each status line is handled (the loop's wait_turn).
        self.gate = gate
        self._committed_cycle = 0  # the last stroke committed here, as the record writer said
        self._heard = False  # a status line came from the child
        self._status: dict[str, Any] = {
            "url": self.where,
            "connected": False,
            "shipped_cycle": 0,
            "lag": 0,
            "shipped": 0,
            "duplicates": 0,
            "runs_shipped": 0,
            "error": None,
            "error_count": 0,
        }
        self._proc: subprocess.Popen[bytes] | None = None
        self._lock = threading.Lock()  # the pipe to the child: wake (writer thread) and stop
        self._stopping = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Spawn the process and the thread that reads its status (and restarts it if it dies)."""
        self._committed_cycle = max(self._committed_cycle, _last_cycle(self.settings["records"]))
        self._spawn()
        self._thread = threading.Thread(target=self._watch, name="usmswitch-shipper", daemon=True)
        self._thread.start()

    def _spawn(self) -> None:
        proc = subprocess.Popen(
            [sys.executable, "-m", "usmswitch.daemon.shipper_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            close_fds=True,
        )
        assert proc.stdin is not None
        proc.stdin.write(json.dumps(self.settings).encode() + b"\n")
        proc.stdin.flush()
        os.set_blocking(proc.stdin.fileno(), False)  # a wake never waits for the child
        self._proc = proc

    def _watch(self) -> None:
        while True:
            proc = self._proc
            assert proc is not None and proc.stdout is not None
            for line in proc.stdout:
                self.gate()
                with contextlib.suppress(ValueError):
                    self._status = json.loads(line)
                    self._heard = True
            code = proc.wait()
            if self._stopping:
                return
            message = f"postgres {self.where}: the shipper process exited (status {code}); restarting"
            log.error("postgres shipper process died", exit_status=code, url=self.where)
            self._status = {**self._status, "connected": False, "error": message}
            time.sleep(RESTART_PAUSE_S)
            if self._stopping:
                return
            with self._lock:
                self._spawn()

    def _send(self, text: str) -> None:
        with self._lock:
            proc = self._proc
            if proc is None or proc.stdin is None:
                return
            # Full: a wake is pending anyway. Gone: the watcher restarts it.
            with contextlib.suppress(OSError):
                os.write(proc.stdin.fileno(), text.encode())

    def wake(self, records: list[Any] | None = None) -> None:
        """Records were committed (the record writer's thread): a few bytes down a pipe."""
        if records:
            self._committed_cycle = max(self._committed_cycle, records[-1].cycle)
        self._send("w\n")

    def stop(self, drain_timeout_ns: int = 2_000_000_000) -> bool:
        """Ship what is committed for up to `drain_timeout_ns`, then end; True when caught up.

        A shipper still busy EXIT_GRACE_S after that (a statement the database is slow to answer,
        a process starved of CPU) is killed: its transaction rolls back, and what it held ships
        again, once, at the next start."""
        self._stopping = True
        proc = self._proc
        if proc is None:
            return False
        # The drain is the exit's last work, the loop has stopped: at nice 10 beside a busy
        # machine's ordinary processes the child got the CPU too seldom to end within its budget
        # (SIGTERM under the abuse bench's heaviest reads: killed behind, 23-26 ms of the exit).
        # Refused (a daemon without real-time), it drains at nice 10 as it shipped.
        lift_child(proc.pid, DRAIN_PRIORITY)
        self._send(f"stop {drain_timeout_ns}\n")
        killed = wait_exit(proc, drain_timeout_ns / 1e9 + EXIT_GRACE_S) is None
        if killed:
            end_child(proc, 0.0)
        if self._thread is not None and not killed:
            self._thread.join(5)  # a killed one's pipe closes when the kernel is done with it
        if killed:  # its last status predates the final commits: the lag as we know it
            shipped = self._status.get("shipped_cycle") or 0
            lag = max(self._status.get("lag") or 0, self._committed_cycle - shipped)
            self._status = {**self._status, "lag": lag, "error": "stopped before its drain finished"}
        status = self._status
        return status["lag"] == 0 and status["error"] is None

    def status(self) -> dict[str, Any]:
        """The child's last status (the PostgresShipper.status() figures). Before its first word (a
        busy machine starts it late) the lag is what is committed here: a lag of 0 then said "all
        shipped" of records it had not seen."""
        out = dict(self._status)
        if not self._heard:
            out["lag"] = self._committed_cycle
        return out


def _last_cycle(path: str) -> int:
    """The records file's last stroke (0 when none or unreadable): until the shipper's first word,
    all of the file may be unshipped, never none of it."""
    try:
        con = sqlite3.connect(f"file:{quote(str(Path(path).resolve()))}?mode=ro", uri=True)
        try:
            return con.execute("SELECT coalesce(max(cycle), 0) FROM cycles").fetchone()[0]
        finally:
            con.close()
    except sqlite3.Error:
        return 0


def main() -> int:
    """The process's body: the settings from stdin, then ship until told to stop (or orphaned)."""
    import signal

    from usmswitch.fleet.shipper import serve
    from usmswitch.runtime.logsetup import configure_logging
    from usmswitch.runtime.realtime import drop_realtime, renice

    # Started again by the daemon's watcher thread, which runs SCHED_FIFO when the loop does: the
    # child (and every thread it starts) belongs at SCHED_OTHER, below everything of the rig's.
    drop_realtime()

    # The daemon owns shutdown: a Ctrl-C to the terminal's group or systemd's SIGTERM to the
    # cgroup must not cut the drain short; the child ends on `stop` or when its stdin closes.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    settings = json.loads(sys.stdin.readline())
    configure_logging(settings["log_format"], settings["log_level"], sys.stderr)
    renice(NICE, "shipper", "shipping competes with the loop for CPU at the loop's nice")
    serve(settings, sys.stdin, sys.stdout)
    return 0


if __name__ == "__main__":
    exit_now(main())  # shipped, stopped and reported: nothing is left for the teardown to do
