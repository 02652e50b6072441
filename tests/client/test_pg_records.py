"""A rig's records read back from the PostgreSQL copy, as from its SQLite file: the Python reader
(`open_records`, `PostgresRecords`) and `usmswitchctl export --from postgresql://...`."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pgserver
import pytest

from usmswitch.client import PostgresRecords, RecordsFile, RecordsFileError, open_records
from usmswitch.daemon.records import RecordStore
from usmswitch.fleet.shipper import PostgresShipper
from usmswitch.protocol.record import RunRecord

BIN = Path(sys.executable).parent / "usmswitchctl"
CTL = [str(BIN)] if BIN.exists() else [sys.executable, "-m", "usmswitch.client.ctl"]


def ctl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CTL, *args], capture_output=True, text=True, timeout=60, check=False)


def ship(path: Path, url: str, rig: str, last_cycle: int) -> None:
    shipper = PostgresShipper(path, url, rig, retry_ns=(20_000_000, 200_000_000), poll_ns=50_000_000)
    shipper.start()
    end = time.monotonic() + 30
    while shipper.shipped_cycle < last_cycle or shipper.runs_shipped < 2:
        assert time.monotonic() < end, shipper.status()
        time.sleep(0.02)
    assert shipper.stop()


@pytest.fixture
def shipped(pg: Any, tmp_path: Path) -> tuple[Any, str, Path]:
    """Two rigs in one database: rigA (two runs, 600 strokes) and rigB (120 strokes)."""
    server, db, url = pg
    a, b = tmp_path / "a" / "records.sqlite", tmp_path / "b" / "records.sqlite"
    for path, rig, n in ((a, "rigA", 600), (b, "rigB", 120)):
        store = RecordStore(path, driver="sim", rig=rig)
        half = n // 2
        store.submit_run(
            RunRecord(run_id=1, kind="cycling", first_cycle=1, started_wall_ns=1, settings={"count": half})
        )
        for rec in pgserver.synthetic_records(1, half, run_id=1):
            store.submit(rec)
        store.submit_run(RunRecord(2, "cycling", half + 1, 2, {"count": 0}, n, 3, "stopped"))
        for rec in pgserver.synthetic_records(half + 1, n - half, seed=3, run_id=2):
            store.submit(rec)
        assert store.close()
        ship(path, url, rig, n)
    return server, url, a


def test_the_database_reads_as_the_file_does(shipped: tuple[Any, str, Path]):
    server, url, file_a = shipped
    with open_records(url, rig="rigA") as pg, RecordsFile(file_a) as f:
        assert isinstance(pg, PostgresRecords)
        assert list(pg) == list(f) and len(pg) == len(f) == pg.last_cycle == 600
        assert pg.runs() == f.runs() and pg.run(2)["end_reason"] == "stopped"
        assert list(pg.records(run=2)) == list(f.records(run=2))
        assert list(pg.records(first=10, last=12, chunk=2)) == list(f.records(first=10, last=12))
        for field in ("error_ns", "temperature_c", "cycle"):
            assert np.array_equal(pg.column(field), f.column(field), equal_nan=True)
            assert pg.column(field).dtype == f.column(field).dtype
        with pytest.raises(RecordsFileError, match=r"no run 9 in .* \(runs 1\.\.2\)"):
            pg.run(9)
        assert pg.rigs() == ["rigA", "rigB"]
    # A database of several rigs: name one; an unknown name says which there are.
    with pytest.raises(RecordsFileError, match=r"several rigs: name one \(rigA, rigB\)"):
        open_records(url)
    with pytest.raises(RecordsFileError, match=r"no strokes of rig 'rigC' \(rigs: rigA, rigB\)"):
        open_records(url, rig="rigC")
    with pytest.raises(RecordsFileError, match="password authentication failed") as info:
        open_records(server.url(url.rsplit("/", 1)[1], password="nope"), rig="rigA")
    assert "nope" not in str(info.value) and ":***@" in str(info.value)


def test_a_database_without_usmswitch_tables_is_named(pg: Any):
    _, _, url = pg
    with pytest.raises(RecordsFileError, match="holds no usmswitch records"):
        open_records(url)


def test_usmswitchctl_exports_from_postgres_what_it_exports_from_the_file(
    shipped: tuple[Any, str, Path], tmp_path: Path
):
    _, url, file_a = shipped
    from_pg, from_file = tmp_path / "pg.csv", tmp_path / "file.csv"
    r = ctl("export", "--from", url, "--rig", "rigA", "--csv", str(from_pg))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"600 records written to {from_pg}"
    assert ctl("export", "--from", str(file_a.parent), "--csv", str(from_file)).returncode == 0
    assert from_pg.read_bytes() == from_file.read_bytes()
    run2 = ctl("export", "--from", url, "--rig", "rigA", "--run", "2", "--first", "500", "--csv", "-")
    assert run2.returncode == 0 and len(run2.stdout.splitlines()) == 1 + 101  # header + cycles 500..600
    # Errors are usage errors that say what is wrong, without the password; no file is left.
    bad = ctl("export", "--from", url, "--csv", str(tmp_path / "x.csv"))
    assert bad.returncode == 2 and "several rigs: name one (rigA, rigB)" in bad.stderr
    wrong = url.replace(pgserver.PASSWORD, "guess")
    bad = ctl("export", "--from", wrong, "--rig", "rigA", "--csv", str(tmp_path / "x.csv"))
    assert bad.returncode == 2 and "password authentication failed" in bad.stderr
    assert "guess" not in bad.stderr
    assert not (tmp_path / "x.csv").exists() and not (tmp_path / "x.csv.partial").exists()
    both = ctl("export", "--from", url, "--state-dir", str(file_a.parent), "--csv", "-")
    assert both.returncode == 2 and "give --from or --state-dir, not both" in both.stderr


def test_the_experiments_read_a_run_from_postgres_as_from_the_file(
    shipped: tuple[Any, str, Path], tmp_path: Path
):
    _, url, file_a = shipped
    summaries = {}
    sources = {"pg": ["--from-records", url, "--rig", "rigA"], "file": ["--from-records", str(file_a)]}
    for name, source in sources.items():
        out = tmp_path / name
        cmd = [sys.executable, "-m", "usmswitch.experiments", "closed-loop", *source, "--run", "2"]
        r = subprocess.run(
            [*cmd, "--out", str(out)], capture_output=True, text=True, timeout=120, check=False
        )
        assert r.returncode == 0, r.stderr[-2000:]
        summaries[name] = json.loads((out / "summary.json").read_text())
    assert summaries["pg"]["closed_loop"] == summaries["file"]["closed_loop"]
    assert summaries["pg"]["closed_loop"][0]["strokes"] == 100  # 150 per direction, 100 settling
    where = summaries["pg"]["meta"]["where"]
    assert where.endswith("(rig rigA), run 2") and ":***@" in where  # no password in the report
