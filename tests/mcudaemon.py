"""usmswitchd on a fake MCU (tests/faultmcu.py) over a pty: start it, run strokes, read its records
and hold them against the emulator's truth. Importable from any test (tests/ is on sys.path)."""

from __future__ import annotations

import contextlib
import sqlite3
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import daemonproc

from usmswitch.client import Client
from usmswitch.protocol.record import UNUSABLE

MS = 1_000_000
# The flag bits by value (docs/records.md), so these helpers read a records file of any version.
FAULT, STALL, MISMATCH, NOISE = 1 << 4, 1 << 2, 1 << 11, 1 << 12
#: A record is clean when none of these flags is set: its operating time was learned.
NOT_CLEAN = int(UNUSABLE) | MISMATCH


@contextlib.contextmanager
def daemon(tmp_path: Path, port: Path, *extra: str) -> Iterator[tuple[Client, object]]:
    """A serial-driver daemon on `port`, its client; stopped (and its exit checked) after."""
    sock = tmp_path / "d.sock"
    args = ["--driver", "serial", "--port", str(port), "--target", "12ms", *extra]
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args, sim=False))
    try:
        daemonproc.wait_serving(sock, proc)
        with Client(str(sock), timeout=10) as c:
            yield c, proc
    except Exception as exc:
        err = daemonproc.stop(proc)
        raise AssertionError(err.decode()[-3000:]) from exc
    else:
        err = daemonproc.stop(proc)
        assert proc.returncode == 0, err.decode()[-3000:]


def run(c: Client, period_ns: int, count: int, timeout_s: float = 20.0) -> dict:
    """Cycle `count` strokes and wait for the run's end (or a fault); the status after it."""
    c.start_cycling(period_ns, count)
    end = time.monotonic() + timeout_s
    while (st := c.status())["state"] == "cycling":
        assert time.monotonic() < end
        time.sleep(0.05)
    return st


@dataclass(frozen=True)
class Row:
    cycle: int
    direction: int
    flags: int
    t_start_ns: int | None
    t_arrive_ns: int | None
    operating_ns: int | None
    error_ns: int | None
    lateness_ns: int | None

    @property
    def clean(self) -> bool:
        return not self.flags & NOT_CLEAN


def rows(tmp_path: Path) -> list[Row]:
    """The daemon's stroke records, in cycle order."""
    con = sqlite3.connect(tmp_path / "state" / "records.sqlite")
    try:
        sql = (
            "SELECT cycle, direction, flags, t_start_ns, t_arrive_ns, operating_ns, error_ns, lateness_ns"
            " FROM cycles ORDER BY cycle"
        )
        return [Row(*r) for r in con.execute(sql)]
    finally:
        con.close()


def truth_of(row: Row, log: list) -> int | None:
    """The emulator's own operating time of the stroke a record is of (matched by its start, both
    on the host's monotonic clock to within the link's mapping), None if it made none there."""
    if row.t_start_ns is None:
        return None
    best = min(log, key=lambda s: abs(s.t_start_ns - row.t_start_ns), default=None)
    if best is None or abs(best.t_start_ns - row.t_start_ns) > 5 * MS or best.t_arrive_ns is None:
        return None
    return best.t_arrive_ns - best.t_start_ns


def untrue_clean(got: list[Row], log: list, tolerance_ns: int = 50_000) -> list[tuple[Row, int | None, str]]:
    """Clean records whose operating time is not the emulator's truth within `tolerance_ns`."""
    bad = []
    for r in got:
        if not r.clean:
            continue
        true = truth_of(r, log)
        if true is None or r.operating_ns is None or abs(r.operating_ns - true) > tolerance_ns:
            near = min((s.t_start_ns - r.t_start_ns for s in log), key=abs, default=None)
            bad.append((r, true, f"nearest device start {near} ns off"))
    return bad
