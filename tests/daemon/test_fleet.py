"""Issue 16's "done when": three daemons (three simulated rigs) on one machine ship into one
PostgreSQL database; a query across rigs gives each rig's error std as its own SQLite file does,
and each metrics page shows the same counts as the database."""

from __future__ import annotations

import sqlite3
import statistics
import time
from collections import Counter
from pathlib import Path
from typing import Any

import daemonproc
import pytest
from test_metrics import DIRECTION, OUTCOME_SQL, page_counts, samples, scrape

from usmswitch.client import Client

RIGS = ("rigA", "rigB", "rigC")
STROKES = 60


def wait_for(predicate: Any, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def test_three_rigs_ship_into_one_database_and_their_pages_agree(pg: Any, tmp_path: Path):
    server, db, url = pg
    procs, socks = {}, {}
    try:
        for seed, rig in enumerate(RIGS, start=1):
            d = tmp_path / rig
            d.mkdir()
            socks[rig] = d / "d.sock"
            args = daemonproc.daemon_args(
                d, "--rig", rig, "--seed", str(seed), "--period", "20ms", "--count", str(STROKES),
                "--postgres", url, "--metrics", "127.0.0.1:0",
            )  # fmt: skip
            procs[rig] = daemonproc.spawn(args)
        status: dict[str, dict[str, Any]] = {}
        for rig in RIGS:
            daemonproc.wait_serving(socks[rig], procs[rig])

        def settled(rig: str) -> bool:
            with Client(str(socks[rig]), timeout=5) as c:
                status[rig] = c.status()
            pgst = status[rig]["records"]["postgres"]
            return status[rig]["state"] == "idle" and status[rig]["cycle"] > STROKES and pgst["lag"] == 0

        for rig in RIGS:
            wait_for(lambda rig=rig: settled(rig), 30, f"{rig}'s run done and shipped")
        pages = {rig: samples(scrape(status[rig]["metrics_url"])[2]) for rig in RIGS}
        with_run = {}
        for rig in RIGS:
            with Client(str(socks[rig]), timeout=5) as c:
                with_run[rig] = c.stats(1)
    finally:
        errs = {rig: daemonproc.stop(p) for rig, p in procs.items()}
    assert {rig: p.returncode for rig, p in procs.items()} == dict.fromkeys(RIGS, 0), errs

    # One query across the rigs.
    rows = server.query(
        db,
        "SELECT rig, count(*), count(error_ns), stddev_samp(error_ns)::float8 FROM usmswitch_cycles"
        " GROUP BY rig ORDER BY rig",
    )
    assert [r[0] for r in rows] == list(RIGS)
    by_outcome = f"SELECT rig, direction, {OUTCOME_SQL} AS o, count(*) FROM usmswitch_cycles"
    counts = server.query(db, by_outcome + " GROUP BY rig, direction, o")
    stds = []
    for rig, n, n_err, std in rows:
        con = sqlite3.connect(tmp_path / rig / "state" / "records.sqlite")
        errors = [e for (e,) in con.execute("SELECT error_ns FROM cycles WHERE error_ns IS NOT NULL")]
        local = Counter(
            {(DIRECTION[d], o): k for d, o, k in con.execute(f"SELECT direction, {OUTCOME_SQL} AS o, count(*)"
                                                            " FROM cycles GROUP BY direction, o")}
        )  # fmt: skip
        con.close()
        assert n == STROKES and n_err == len(errors)
        # The database's (numeric, 4 decimals of ns) = the file's.
        assert std == pytest.approx(statistics.stdev(errors), abs=1e-3)
        assert std == pytest.approx(with_run[rig]["all"]["error_std_ns"], abs=0.1)  # = the daemon's stats
        in_db = Counter({(DIRECTION[d], o): k for r, d, o, k in counts if r == rig})
        assert in_db == local == page_counts(pages[rig], rig), rig
        stds.append(std)
    assert len(set(stds)) == 3  # three rigs of their own, not one rig's strokes thrice
