"""usmswitchd on a fake MCU (tests/faultmcu.py) over a pty: start it, run strokes, read its records
and hold them against the emulator's truth. Importable from any test (tests/ is on sys.path)."""

from __future__ import annotations

import bisect
import contextlib
import json
import sqlite3
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import daemonproc

from usmswitch.client import Client
from usmswitch.protocol.record import UNUSABLE, Flag

MS = 1_000_000
# The flag bits by value (docs/records.md), so these helpers read a records file of any version.
FAULT, STALL, MISMATCH, NOISE = 1 << 4, 1 << 2, 1 << 11, 1 << 12
#: A record is clean when none of these flags is set: its operating time was learned.
NOT_CLEAN = int(UNUSABLE) | MISMATCH
#: The daemon's stderr (its JSON log), kept beside its state once it stopped.
DAEMON_LOG = "daemon.log"


@contextlib.contextmanager
def daemon(tmp_path: Path, port: Path, *extra: str) -> Iterator[tuple[Client, object]]:
    """A serial-driver daemon on `port`, its client; stopped (and its exit checked) after."""
    sock = tmp_path / "d.sock"
    args = [
        "--driver",
        "serial",
        "--port",
        str(port),
        "--target",
        "12ms",
        *daemonproc.slow_link(tmp_path),
        *extra,
    ]
    proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args, sim=False))
    err = b""
    try:
        daemonproc.wait_serving(sock, proc)
        with Client(str(sock), timeout=10) as c:
            c.ping()  # not a silent connection: a test that waits 2 s before its first call keeps it
            yield c, proc
    except Exception as exc:
        err = daemonproc.stop(proc)
        raise AssertionError(err.decode()[-3000:]) from exc
    else:
        err = daemonproc.stop(proc)
        assert proc.returncode == 0, err.decode()[-3000:]
    finally:
        (tmp_path / DAEMON_LOG).write_bytes(err)  # rows() reads why a stroke was not learned


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
    why: str = ""  # the daemon's word on a stroke it did not learn (its log), for a failure to say

    @property
    def clean(self) -> bool:
        return not self.flags & NOT_CLEAN


def not_clean(got: list[Row]) -> list[str]:
    """The rows that are not clean, each as its cycle and its flags by name: what a failure says."""
    return [f"cycle {r.cycle}: {Flag(r.flags)!r}{f' ({r.why})' if r.why else ''}" for r in got if not r.clean]


def _not_learned(tmp_path: Path) -> dict[int, str]:
    """Cycle -> why, from the daemon's log lines on strokes it did not learn."""
    why: dict[int, str] = {}
    log = tmp_path / DAEMON_LOG
    for line in log.read_text(errors="replace").splitlines() if log.exists() else ():
        with contextlib.suppress(ValueError):
            entry = json.loads(line)
            event = str(entry.get("event", "")) if isinstance(entry, dict) else ""
            if event.startswith("stroke not") and "cycle" in entry:
                why[entry["cycle"]] = str(entry.get("why", event))
    return why


def rows(tmp_path: Path) -> list[Row]:
    """The daemon's stroke records, in cycle order."""
    con = sqlite3.connect(tmp_path / "state" / "records.sqlite")
    try:
        sql = (
            "SELECT cycle, direction, flags, t_start_ns, t_arrive_ns, operating_ns, error_ns, lateness_ns"
            " FROM cycles ORDER BY cycle"
        )
        why = _not_learned(tmp_path)
        return [Row(*r, why=why.get(r[0], "")) for r in con.execute(sql)]
    finally:
        con.close()


def truth_of(row: Row, log: list, window_ns: int = 25 * MS) -> int | None:
    """The emulator's own operating time of the stroke a record is of (matched by its start, the
    emulator's on the host's monotonic clock, the record's on the driver's), None if it made none
    within `window_ns`. For a short run on a quiet link, where the driver's timeline is the host's
    to within a handshake's half round trip; `untrue_clean` follows the timeline's offset."""
    if row.t_start_ns is None:
        return None
    best = min(log, key=lambda s: abs(s.t_start_ns - row.t_start_ns), default=None)
    if best is None or abs(best.t_start_ns - row.t_start_ns) > window_ns or best.t_arrive_ns is None:
        return None
    return best.t_arrive_ns - best.t_start_ns


def _first_offset(got: list[Row], starts: list, tolerance_ns: int, window_ns: int = 500 * MS) -> int:
    """The driver timeline's first offset from the host clock: it is fixed at the first handshake
    within half that round trip, which a busy host makes tens of ms. Of the emulator's starts within
    `window_ns` of the first stamped record, the one that pairs the most of the first ten records
    with a stroke of the same operating time (so not a neighbour's) gives it; 0 when none does."""
    stamped = [r for r in got if r.t_start_ns is not None][:10]
    if not stamped:
        return 0
    keys = [t for t, _ in starts]

    def pairs(offset: int) -> int:
        n = 0
        for r in stamped:
            i = bisect.bisect_left(keys, r.t_start_ns + offset)
            for j in (i - 1, i):
                if 0 <= j < len(starts) and abs(keys[j] - r.t_start_ns - offset) <= 2 * MS:
                    s = starts[j][1]
                    true = None if s.t_arrive_ns is None else s.t_arrive_ns - s.t_start_ns
                    n += r.operating_ns is None or (
                        true is not None and abs(r.operating_ns - true) <= tolerance_ns
                    )
        return n

    first = stamped[0].t_start_ns
    lo, hi = bisect.bisect_left(keys, first - window_ns), bisect.bisect_right(keys, first + window_ns)
    offsets = [0] + [keys[j] - first for j in range(lo, hi)]
    return max(offsets, key=lambda o: (pairs(o), -abs(o)))


def untrue_clean(
    got: list[Row], log: list, tolerance_ns: int = 50_000, step_ns: int = 15 * MS
) -> list[tuple[Row, int | None, str]]:
    """Clean records whose operating time is not the emulator's truth within `tolerance_ns`.

    Records are paired with the emulator's strokes by start instant, in order, following the
    offset of the driver's timeline from the host's clock: it is fixed at each handshake (within
    half its round trip) and kept across sessions (the timeline never goes back), so it moves by
    at most `step_ns` at a time (keep that under half the strokes' spacing)."""
    starts = sorted(((s.t_start_ns, s) for s in log), key=lambda p: p[0])
    keys = [t for t, _ in starts]
    offset = _first_offset(got, starts, tolerance_ns)
    bad = []
    for r in got:
        if r.t_start_ns is None:
            continue
        want = r.t_start_ns + offset
        i = bisect.bisect_left(keys, want)
        near = [starts[j] for j in (i - 1, i) if 0 <= j < len(starts)]
        pick = min(near, key=lambda p: abs(p[0] - want), default=None)
        true = None
        if pick is not None and abs(pick[0] - want) <= step_ns:
            offset = pick[0] - r.t_start_ns
            if pick[1].t_arrive_ns is not None:
                true = pick[1].t_arrive_ns - pick[1].t_start_ns
        if not r.clean:
            continue
        if true is None or r.operating_ns is None or abs(r.operating_ns - true) > tolerance_ns:
            near_ms = sorted((round((t - r.t_start_ns) / 1e6, 3) for t in keys), key=abs)[:3]
            bad.append((r, true, f"timeline offset {offset} ns; nearest starts at {near_ms} ms"))
    return bad
