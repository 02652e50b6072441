"""Records at lab scale (issue 36): what a run's statistics, the runs list and an export cost as the
records file grows, beside the full scan and `sqlite3 -csv` of the same rows in the same run.

Files are made by the control loop on the simulated rig in virtual time with the real record writer
(runs of 10,000 strokes); sizes from USMSWITCH_BENCH_RECORDS_SIZES (default "10000,100000"; the
issue's 10^6 and 10^7 take minutes and tens of minutes to make: add them by hand). Printed per size:
`stats --run` from the kept aggregate and by the scan, the runs list with every run's statistics,
an export of the newest run against sqlite3 -csv of its rows, and the file's size. Targets: the
kept stats and the runs list under 100 ms, the export within 2x sqlite3 -csv.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.table import print_table

MS = 1_000_000
RUN = 10_000
TARGET_STATS_MS = 100.0
TARGET_EXPORT_RATIO = 2.0


def _make(path: Path, strokes: int) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "daemon"))
    from test_loop import make_loop

    from usmswitch.daemon.records import RecordStore

    store = RecordStore(path, wait_when_behind=20_000)
    loop, _daq, _ = make_loop(target_ns=12 * MS, sink=store.submit, seed=21)
    loop.run_sink = store.submit_run
    done = 0
    while done < strokes:
        before = loop.cycle
        loop.run_cycles(30 * MS, min(RUN, strokes - done))
        done += loop.cycle - before
        if loop.state.value == "fault":
            loop.reset_fault()
    store.close()


def _best_ms(fn: object, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()  # type: ignore[operator]
        best = min(best, time.perf_counter() - t)
    return best * 1000


def main() -> int:
    from usmswitch.client.ctl.exports import _write_table_rows
    from usmswitch.client.records import RecordsFile
    from usmswitch.daemon.records import RecordStore
    from usmswitch.protocol.record import FIELDS
    from usmswitch.protocol.stats import stats_of_records

    sizes = [int(s) for s in os.environ.get("USMSWITCH_BENCH_RECORDS_SIZES", "10000,100000").split(",")]
    sqlite3_cli = shutil.which("sqlite3")
    rows, missed = [], []
    tmp = Path(tempfile.mkdtemp(prefix="bench-records-"))
    try:
        for n in sizes:
            path = tmp / f"records-{n}.sqlite"
            t0 = time.perf_counter()
            _make(path, n)
            made_s = time.perf_counter() - t0
            with RecordStore(path, readonly=True) as store:
                runs = store.runs(1000)
                last = runs[-1]
                kept_ms = _best_ms(lambda s=store, r=last: s.run_stats(r.run_id))
                scan_ms = _best_ms(
                    lambda s=store, r=last: stats_of_records(s.iter_records(run_id=r.run_id), r), 1
                )
                list_ms = _best_ms(lambda s=store, rs=runs: [s.run_stats(r.run_id) for r in rs])
            out = tmp / "export.csv"

            def export(path: Path = path, out: Path = out, run_id: int = last.run_id) -> None:
                with RecordsFile(path) as rf, open(out, "w", newline="") as fh:
                    _write_table_rows(rf.table_rows(run=run_id), fh)

            export_ms = _best_ms(export)
            cols = ", ".join(f'"{f}"' for f in FIELDS)
            sql = f"SELECT {cols} FROM cycles WHERE run_id = {last.run_id} ORDER BY cycle"
            peer_ms = float("nan")
            if sqlite3_cli:

                def peer(cmd: list[str] = [sqlite3_cli, "-csv", str(path), sql]) -> None:  # noqa: B006
                    with open(tmp / "peer.csv", "w") as fh:
                        subprocess.run(cmd, stdout=fh, check=True)

                peer_ms = _best_ms(peer)
            ratio = export_ms / peer_ms if peer_ms == peer_ms else float("nan")
            size = path.stat().st_size
            rows.append(
                [
                    f"{n:,}",
                    f"{made_s:.0f}",
                    f"{kept_ms:.1f}",
                    f"{scan_ms:.0f}",
                    f"{list_ms:.1f} ({len(runs)} runs)",
                    f"{export_ms:.0f}",
                    f"{peer_ms:.0f}",
                    f"{ratio:.2f}x",
                    f"{size / 1e6:.1f} MB ({size / n:.0f} B/stroke)",
                ]
            )
            if kept_ms > TARGET_STATS_MS or list_ms > TARGET_STATS_MS:
                missed.append(
                    f"{n}: stats {kept_ms:.1f} ms, runs list {list_ms:.1f} ms > {TARGET_STATS_MS:g} ms"
                )
            if ratio > TARGET_EXPORT_RATIO:
                missed.append(f"{n}: export {ratio:.2f}x sqlite3 -csv > {TARGET_EXPORT_RATIO:g}x")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print_table(
        [
            "strokes",
            "made s",
            "stats kept ms",
            "stats scan ms",
            "runs list ms",
            "export run ms",
            "sqlite3 -csv ms",
            "x peer",
            "file",
        ],
        rows,
        title=f"records at scale: the newest run ({RUN:,} strokes) read from a file of N strokes",
    )
    for m in missed:
        print(f"TARGET MISSED: {m}")
    return 1 if missed else 0


if __name__ == "__main__":
    raise SystemExit(main())
