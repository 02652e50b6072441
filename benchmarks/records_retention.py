"""Retention at lab scale (issue 36: "the file stays inside its configured bound"), the second table
of benchmarks/bench_records.py: the real daemon in virtual time with `[records] keep_bytes` set,
cycled well past the bound, records.sqlite and its -wal sized every second.

"Within its bound" (docs/records.md, "Retention"): a run in progress is never moved, and SQLite keeps
the pages a file once took (it reuses them for the strokes after a move, it does not give them back),
so the bound is held as: records.sqlite never larger than keep_bytes + the largest run's bytes; its
used pages (the file less its free pages, what keep_bytes counts) within keep_bytes once the last run
has ended; the -wal never larger than a checkpoint's worth (1,000 pages, 4 MB) + 1.1x the largest
run's bytes (a move is one transaction, and writes its run's pages and the tree's above them: 1.06x
measured); every stroke made in one of the two files, none dropped.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.daemon_proc import stop_daemon

MS = 1_000_000
#: At scale 1: RUNS runs of RUN_STROKES strokes (~175 bytes each: ~70 MB in all) against a bound of
#: BOUND_BYTES (~2 runs): ~4 min on this 2-core machine. USMSWITCH_BENCH_RETENTION_SCALE scales the
#: runs and the bound alike (0: skip the measurement); USMSWITCH_BENCH_RETENTION_RUNS sets how many.
RUNS = 10
RUN_STROKES = 40_000
BOUND_BYTES = 16_000_000
#: The -wal's size at which SQLite checkpoints it (wal_autocheckpoint's 1,000 pages, the daemon's).
WAL_PAGES = 1000
#: What a move writes to the -wal, in its run's bytes (1.06 measured moving a run of 10,000 strokes).
MOVE_WAL = 1.1


def _file_bytes(state: Path) -> tuple[int, int]:
    """(records.sqlite, records.sqlite-wal) sizes now (0 for one that is not there)."""
    out = []
    for name in ("records.sqlite", "records.sqlite-wal"):
        try:
            out.append((state / name).stat().st_size)
        except FileNotFoundError:
            out.append(0)
    return out[0], out[1]


def _used_bytes(db: Path) -> int:
    """The file's pages less its free ones, as retention counts them (a read-only look)."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        pages = con.execute("PRAGMA page_count").fetchone()[0]
        free = con.execute("PRAGMA freelist_count").fetchone()[0]
        return (pages - free) * con.execute("PRAGMA page_size").fetchone()[0]
    finally:
        con.close()


def _count(db: Path, sql: str) -> int:
    if not db.exists():
        return 0
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return int(con.execute(sql).fetchone()[0] or 0)
    finally:
        con.close()


def measure_retention() -> tuple[list[list[str]], list[str]]:
    """The retention table's row and the targets it missed (none and none when scaled to 0)."""
    from benchmarks.bench_records import _connect

    scale = float(os.environ.get("USMSWITCH_BENCH_RETENTION_SCALE", "1"))
    if scale <= 0:
        return [], []
    runs = int(os.environ.get("USMSWITCH_BENCH_RETENTION_RUNS", str(RUNS)))
    run_strokes = int(RUN_STROKES * scale)
    bound = int(BOUND_BYTES * scale)
    tmp = Path(tempfile.mkdtemp(prefix="bench-retention-"))
    state = tmp / "state"
    db = state / "records.sqlite"
    config = tmp / "usmswitchd.toml"
    config.write_text(f"[records]\nkeep_bytes = {bound}\n")
    sock = tmp / "d.sock"
    args = [sys.executable, "-m", "usmswitch.daemon.cli", "--config", str(config), "--sim"]
    args += ["--sim-clock", "virtual", "--state-dir", str(state), "--socket", str(sock), "--no-autostart"]
    args += ["--target", "12ms", "--seed", "22", "--priority", "0", "--log-format", "json"]
    log = open(tmp / "daemon.log", "wb")  # noqa: SIM115 (the daemon writes it until the finally below)
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=log)
    peak_file = peak_wal = 0

    def sample() -> None:
        nonlocal peak_file, peak_wal
        f, w = _file_bytes(state)
        peak_file, peak_wal = max(peak_file, f), max(peak_wal, w)

    try:
        client = _connect(sock, proc)
        t0 = time.monotonic()
        used0 = _used_bytes(db)
        run_bytes = 0
        for k in range(runs):
            client.start_cycling(30 * MS, run_strokes)
            while True:
                time.sleep(1.0)
                sample()
                st = client.status()
                if st["state"] == "fault":
                    raise RuntimeError(f"retention bench: the daemon faulted: {st.get('fault')} (log: {tmp})")
                if st["state"] != "cycling" and st["records"]["backlog"] == 0:
                    break
            if not run_bytes:  # the first run's pages (nothing moves before the bound is passed)
                run_bytes = _used_bytes(db) - used0
            print(
                f"  retention: run {k + 1}/{runs} ended at {time.monotonic() - t0:.0f} s,"
                f" records.sqlite {_file_bytes(state)[0] / 1e6:.1f} MB (peak {peak_file / 1e6:.1f}),"
                f" used {_used_bytes(db) / 1e6:.2f} MB, -wal peak {peak_wal / 1e6:.1f} MB",
                file=sys.stderr,
                flush=True,
            )
        # Moves follow a run's end as it is written: wait for them to finish (a minute at most
        # would be the writer's own next look).
        wait_end = time.monotonic() + 90
        while (used := _used_bytes(db)) > bound and time.monotonic() < wait_end:
            sample()
            time.sleep(0.2)
        cycled = time.monotonic() - t0
        sample()
        final_file, final_wal = _file_bytes(state)
        status = client.status()["records"]
        client.close()
    finally:
        stop_daemon(proc)
        log.close()
    archive = state / "records-archive.sqlite"
    kept = _count(db, "SELECT count(*) FROM cycles")
    archived = _count(archive, "SELECT count(*) FROM cycles")
    moved = _count(archive, "SELECT count(*) FROM runs")
    logged = sum('"run archived"' in line for line in (tmp / "daemon.log").read_text().splitlines())
    page_size = _count(db, "PRAGMA page_size")
    shutil.rmtree(tmp, ignore_errors=True)
    asked = runs * run_strokes
    lost = asked - kept - archived
    file_cap = bound + run_bytes
    wal_cap = WAL_PAGES * page_size + MOVE_WAL * run_bytes
    ok = peak_file <= file_cap and peak_wal <= wal_cap and used <= bound
    mb = 1e6
    row = [
        f"{bound / mb:.0f} MB",
        f"{runs} x {run_strokes:,} = {asked:,} ({cycled / 60:.1f} min)",
        f"{run_bytes / mb:.1f} MB",
        f"{peak_file / mb:.1f} / {final_file / mb:.1f} MB (<= {file_cap / mb:.1f})",
        f"{used / mb:.1f} MB",
        f"{peak_wal / mb:.1f} / {final_wal / mb:.1f} MB (<= {wal_cap / mb:.1f})",
        f"{archived:,} ({moved} runs, {logged} logged)",
        f"{kept:,}",
        f"{status['dropped']} / {lost}",
        "yes" if ok else "NO",
    ]
    missed = []
    if peak_file > file_cap:
        missed.append(
            f"retention: records.sqlite reached {peak_file / mb:.1f} MB > keep_bytes {bound / mb:.0f} MB"
            f" + the largest run's {run_bytes / mb:.1f} MB"
        )
    if peak_wal > wal_cap:
        missed.append(f"retention: the -wal reached {peak_wal / mb:.1f} MB > {wal_cap / mb:.1f} MB")
    if used > bound:
        missed.append(
            f"retention: {used / mb:.1f} MB used after the last run > keep_bytes {bound / mb:.0f} MB"
        )
    if status["dropped"] or lost or logged != moved:
        missed.append(
            f"retention: {status['dropped']} dropped, {lost} strokes in neither file,"
            f" {moved} runs moved but {logged} logged"
        )
    return [row], missed


HEADERS = [
    "keep_bytes",
    "cycled (runs x strokes, wall)",
    "a run",
    "records.sqlite peak / final (bound)",
    "used, after the last run",
    "-wal peak / final (bound)",
    "strokes archived (runs moved, logged)",
    "kept",
    "dropped / lost",
    "file within its bound",
]
