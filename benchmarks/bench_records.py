"""Records at lab scale (issue 36): what a run's statistics, the runs list, an export and a small
read beside big ones cost as the records file grows, beside `sqlite3 -csv` of the same rows.

Files are made by the real daemon (usmswitchd --sim --sim-clock virtual, started by `start_cycling`
over its socket): nine runs of N/100 strokes, then one run of the rest, the daemon's and its server
process's RSS sampled every second and the writer's `dropped` read at the end. They are made once and
kept under ~/.cache/usmswitch-bench (USMSWITCH_BENCH_CACHE), outside the repo. Making runs at ~1,100-1,700
strokes/s on this 2-core machine (shared, loaded): 10^6 in ~15-20 min, 10^7 in ~2-2.5 h.
Sizes from USMSWITCH_BENCH_RECORDS_SIZES (default "10000,100000"; add 1000000 and 3000000 or
10000000 by hand, or make them ahead: `python -m benchmarks.bench_records make 1000000`).

Printed per size, against a daemon serving the file (real clock, idle): `stats --run` of the
newest (biggest) run and the panel's runs list (every run's stats) over the socket; an export of the
newest run in process (the code usmswitchctl runs) and by `usmswitchctl export --from` (a process:
its ~0.3-0.5 s Python start-up included) beside `sqlite3 -csv` of the same rows, over the socket
(`Client.export_csv`, the server's reader processes' chunks, a few asked ahead) and as the panel's
CSV (`GET /api/runs/N.csv`, the same chunks); the target is judged in process, by socket and by
panel (usmswitchctl as a process is shown, its start-up not the export's); `runs [1]`
while four exports of the whole file over the socket are in flight; the daemon's
and server's RSS; the file's size; how the file was made (seconds, RSS through the run, dropped).
Targets (issue 36's "Done when"): stats and the runs list under 100 ms, the export within 2x
sqlite3 -csv, the small read beside four big ones under 100 ms, nothing dropped.

Then a second table, retention (benchmarks/records_retention.py): a daemon in virtual time with
`[records] keep_bytes` set (16 MB, ~2 runs) cycled well past it (10 runs of 40,000 strokes, ~70 MB,
~4 min; USMSWITCH_BENCH_RETENTION_SCALE scales runs and bound, 0 skips it,
USMSWITCH_BENCH_RETENTION_RUNS sets the runs), records.sqlite and its -wal sized every second. Target:
the file within its bound, as docs/records.md ("Retention") defines it: records.sqlite never larger
than keep_bytes + the largest run (a run in progress is never moved, and the pages it took are kept
for reuse), its used pages within keep_bytes once the last run has ended, the -wal never larger than
a checkpoint's 4 MB + 1.1x the largest run; every stroke in the file or the archive, none dropped.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

from benchmarks.daemon_proc import stop_daemon
from benchmarks.table import print_table

MS = 1_000_000
#: Strokes of each of the first runs (the runs list's rows); the last run takes the rest.
SMALL_RUNS = 9


def cache_dir() -> Path:
    """Where made files are kept between bench runs (not the repo): USMSWITCH_BENCH_CACHE or
    ~/.cache/usmswitch-bench."""
    return Path(os.environ.get("USMSWITCH_BENCH_CACHE", "~/.cache/usmswitch-bench")).expanduser()


def rss_bytes(pid: int) -> int:
    """A process's resident memory now (0 once it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def children(pid: int) -> list[int]:
    """The direct children of a process."""
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as fh:
            return [int(p) for p in fh.read().split()]
    except OSError:
        return []


def made(strokes: int) -> tuple[Path, dict[str, Any]]:
    """The state directory of a file of `strokes` strokes and how it was made: made once (minutes
    to hours: see the bench's docstring), then reused."""
    d = cache_dir() / f"records-{strokes}"
    info = d / "made.json"
    if not info.is_file():
        make(d, strokes)
    return d, json.loads(info.read_text())


def make(dest: Path, strokes: int) -> None:
    """Run usmswitchd on the simulated rig in virtual time until the file holds `strokes` strokes:
    SMALL_RUNS runs of 1/100 of them, then one run of the rest; the daemon's and the server
    process's RSS sampled every second through it, the writer's counters read at the end."""

    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}-", dir=dest.parent))
    sock = tmp / "d.sock"
    args = [sys.executable, "-m", "usmswitch.daemon.cli", "--sim", "--sim-clock", "virtual"]
    args += ["--state-dir", str(tmp / "state"), "--socket", str(sock), "--no-autostart"]
    args += ["--target", "12ms", "--seed", "21", "--priority", "0", "--log-format", "json"]
    log = open(tmp / "daemon.log", "wb")  # noqa: SIM115 (the daemon writes it until the finally below)
    t0 = time.monotonic()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=log)
    samples: list[tuple[float, int, int, int, int]] = []  # (s, strokes, daemon RSS, server RSS, backlog)
    try:
        client = _connect(sock, proc)
        small = max(1, strokes // 100)
        plan = [small] * SMALL_RUNS + [strokes - SMALL_RUNS * small]
        last_log = 0.0
        for count in plan:
            client.start_cycling(30 * MS, count)
            while True:
                time.sleep(1.0)
                st = client.status()
                rec = st["records"]
                kids = children(proc.pid)
                server = sum(rss_bytes(k) for k in kids)
                now = time.monotonic() - t0
                samples.append((now, rec["written"], rss_bytes(proc.pid), server, rec["backlog"]))
                if now - last_log >= 60:
                    last_log = now
                    print(
                        f"  making {dest.name}: {rec['written']:,} strokes in {now:.0f} s,"
                        f" daemon {samples[-1][2] / 1e6:.0f} MB, backlog {rec['backlog']:,}",
                        file=sys.stderr,
                        flush=True,
                    )
                if st["state"] == "fault":
                    raise RuntimeError(f"{dest.name}: the daemon faulted: {st.get('fault')} (log: {tmp})")
                if st["state"] != "cycling" and rec["backlog"] == 0:
                    break
        status = client.status()
        client.close()
    finally:
        stop_daemon(proc)
        log.close()
    seconds = time.monotonic() - t0
    rec = status["records"]
    info = {
        "strokes": rec["written"],
        "asked": strokes,
        "seconds": seconds,
        "dropped": rec["dropped"],
        "rejected": rec["rejected"],
        "exit": proc.returncode,
        "samples": samples,
    }
    (tmp / "made.json").write_text(json.dumps(info))
    shutil.rmtree(dest, ignore_errors=True)
    os.replace(tmp, dest)


def _connect(sock: Path, proc: subprocess.Popen[bytes]) -> Any:
    from usmswitch.client import Client

    end = time.monotonic() + 60
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"usmswitchd exited {proc.returncode} (its log: {sock.parent}/daemon.log)")
        try:
            c = Client(str(sock), timeout=30)
            if c.status()["ready"]:
                return c
            c.close()
        except OSError:
            if time.monotonic() > end:
                raise
        time.sleep(0.1)


TARGET_MS = 100.0
TARGET_EXPORT_RATIO = 2.0


def _best_ms(fn: Any, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * 1000


def _serve(state: Path, tmp: Path) -> tuple[subprocess.Popen[bytes], Path]:
    sock = tmp / "d.sock"
    args = [sys.executable, "-m", "usmswitch.daemon.cli", "--sim", "--state-dir", str(state)]
    args += ["--socket", str(sock), "--no-autostart", "--priority", "0", "--log-format", "json"]
    args += ["--web", "127.0.0.1:0"]  # the panel's CSV beside the socket's
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _connect(sock, proc).close()
    return proc, sock


def _measure(n: int) -> tuple[list[str], list[str]]:
    from usmswitch.client import Client
    from usmswitch.protocol.record import FIELDS

    state_dir, info = made(n)
    state = state_dir / "state"
    db = state / "records.sqlite"
    size = sum(p.stat().st_size for p in state.glob("records.sqlite*"))
    tmp = Path(tempfile.mkdtemp(prefix="bench-records-"))
    missed = []
    proc, sock = _serve(state, tmp)
    try:
        with Client(str(sock), timeout=600) as c:
            web_url = c.status()["web_url"]
            runs = c.runs(1000)
            last = runs[-1]
            kept_ms = _best_ms(lambda: c.stats(last["run_id"]))
            list_ms = _best_ms(lambda: [c.stats(r["run_id"]) for r in runs])
        out = tmp / "export.csv"
        ctl = [sys.executable, "-m", "usmswitch.client.ctl", "export", "--from", str(db)]
        ctl += ["--run", str(last["run_id"]), "--csv", str(out)]
        export_ms = _best_ms(lambda: subprocess.run(ctl, check=True, capture_output=True), 2)
        from usmswitch.client.ctl.exports import _csv_chunks_from

        def in_process() -> None:
            with open(out, "w", newline="") as fh:
                _csv_chunks_from(db, 1, None, last["run_id"], None, None).write(fh, False)

        inproc_ms = _best_ms(in_process, 2)
        cols = ", ".join(f'"{f}"' for f in FIELDS)
        sql = f"SELECT {cols} FROM cycles WHERE run_id = {last['run_id']} ORDER BY cycle"
        peer = [shutil.which("sqlite3") or "sqlite3", "-csv", str(db), sql]

        def run_peer() -> None:
            with open(tmp / "peer.csv", "w") as fh:
                subprocess.run(peer, stdout=fh, check=True)

        peer_ms = _best_ms(run_peer, 2)

        def by_socket() -> None:
            with Client(str(sock), timeout=600) as c, open(tmp / "socket.csv", "w") as fh:
                for _n, _last, text in c.export_csv(run=last["run_id"]):
                    fh.write(text)

        by_socket()  # the lane's reader processes start at their first reads: not timed
        socket_ms = _best_ms(by_socket, 2)

        def by_panel() -> None:  # GET /api/runs/N.csv, as a browser's download
            url = f"{web_url}api/runs/{last['run_id']}.csv"
            with urllib.request.urlopen(url, timeout=600) as resp, open(tmp / "panel.csv", "wb") as fh:
                while data := resp.read(1 << 20):
                    fh.write(data)

        panel_ms = _best_ms(by_panel, 2)
        ratio = inproc_ms / peer_ms
        ratios = {"in process": ratio, "socket": socket_ms / peer_ms, "panel": panel_ms / peer_ms}
        # A small read while four big ones are in flight in the server process.
        stop = threading.Event()

        def big() -> None:
            with Client(str(sock), timeout=3600) as b:
                while not stop.is_set():
                    for _ in b.export_csv():  # every stroke of the file, a chunk a call
                        if stop.is_set():
                            break

        bigs = [threading.Thread(target=big, daemon=True) for _ in range(4)]
        for t in bigs:
            t.start()
        time.sleep(1.0)
        small = []
        with Client(str(sock), timeout=600) as s:
            for _ in range(20):
                t0 = time.perf_counter()
                s.runs(1)
                small.append((time.perf_counter() - t0) * 1000)
                time.sleep(0.1)
        stop.set()
        for t in bigs:
            t.join(600)
        server = sum(rss_bytes(k) for k in children(proc.pid))
        daemon = rss_bytes(proc.pid)
    finally:
        stop_daemon(proc, 120)
        shutil.rmtree(tmp, ignore_errors=True)
    samples = info["samples"]
    half = samples[len(samples) // 2 :] or samples
    rss_made = f"{min(s[2] for s in half) / 1e6:.0f}-{max(s[2] for s in samples) / 1e6:.0f} MB"
    row = [
        f"{n:,}",
        f"{info['seconds'] / 60:.1f} min, {rss_made}, {info['dropped']} dropped",
        f"{kept_ms:.1f}",
        f"{list_ms:.1f} ({len(runs)})",
        f"{inproc_ms:.0f} / {socket_ms:.0f} / {panel_ms:.0f} / {export_ms:.0f}",
        f"{peer_ms:.0f}",
        f"{ratio:.2f}x / {socket_ms / peer_ms:.2f}x / {panel_ms / peer_ms:.2f}x / {export_ms / peer_ms:.2f}x",
        f"{statistics.median(small):.1f} / {max(small):.1f}",
        f"{daemon / 1e6:.0f} / {server / 1e6:.0f} MB",
        f"{size / 1e6:.0f} MB ({size / n:.0f} B/stroke)",
    ]
    if kept_ms > TARGET_MS or list_ms > TARGET_MS:
        missed.append(f"{n:,}: stats {kept_ms:.1f} ms, runs list {list_ms:.1f} ms > {TARGET_MS:g} ms")
    for where, r in ratios.items():
        if r > TARGET_EXPORT_RATIO:
            missed.append(f"{n:,}: export ({where}) {r:.2f}x sqlite3 -csv > {TARGET_EXPORT_RATIO:g}x")
    if max(small) > TARGET_MS:
        missed.append(f"{n:,}: a small read beside four big ones took {max(small):.0f} ms > {TARGET_MS:g} ms")
    if info["dropped"]:
        missed.append(f"{n:,}: {info['dropped']} records dropped while making the file")
    return row, missed


def main() -> int:
    sizes = [int(s) for s in os.environ.get("USMSWITCH_BENCH_RECORDS_SIZES", "10000,100000").split(",")]
    rows, missed = [], []
    for n in sizes:
        row, m = _measure(n)
        rows.append(row)
        missed += m
    print_table(
        [
            "strokes",
            "made (virtual time: wall, daemon RSS 2nd half-max, dropped)",
            "stats --run ms",
            "runs list ms (runs)",
            "export run ms (in process / socket / panel / usmswitchctl --from)",
            "sqlite3 -csv ms",
            "x peer (in process / socket / panel / usmswitchctl)",
            "runs [1] beside 4 socket exports ms p50/max",
            "daemon / server RSS",
            "file",
        ],
        rows,
        title="records at scale: the newest run (the rest after 9 runs of N/100) of a file of N strokes",
    )
    from benchmarks.records_retention import HEADERS, measure_retention

    retained, retention_missed = measure_retention()
    if retained:
        print()
        print_table(HEADERS, retained, title="retention: keep_bytes, cycled well past it in virtual time")
    missed += retention_missed
    for m in missed:
        print(f"TARGET MISSED: {m}")
    return 1 if missed else 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["make"]:
        for arg in sys.argv[2:]:
            d, i = made(int(arg))
            print(f"{d}: {i['strokes']:,} strokes in {i['seconds'] / 60:.1f} min, {i['dropped']} dropped")
        raise SystemExit(0)
    raise SystemExit(main())
