"""RecordsFile: a records file written by the daemon's own writer, read back for analysis."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from usmswitch.client import RecordsFile, RecordsFileError
from usmswitch.daemon.loop import ControlLoop
from usmswitch.daemon.records import RecordStore
from usmswitch.predictor import ARPredictor
from usmswitch.protocol.record import Flag
from usmswitch.sim import SimDaq

MS = 1_000_000


@pytest.fixture(scope="module")
def state_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """300 closed-loop strokes on the simulated rig, through the daemon's record writer."""
    d = tmp_path_factory.mktemp("state")
    store = RecordStore(d / "records.sqlite", driver="sim", rig="bench-1")
    daq = SimDaq(seed=11, faults={"schedule": {150: ["stall"]}})
    daq.open()
    preds = [ARPredictor(order=1, window=100, nominal_ns=10_500_000) for _ in range(2)]
    loop = ControlLoop(daq, preds, target_ns=12 * MS, sink=store.submit)
    loop.run_cycles(40 * MS, 300)  # stops at the stall
    loop.reset_fault()
    loop.run_cycles(40 * MS, 300 - loop.cycle + 1)
    assert store.close()
    return d


def test_records_come_back_in_order_with_every_field(state_dir: Path) -> None:
    with RecordsFile(state_dir) as f:  # a state directory or the file itself
        recs = list(f)
        assert len(f) == len(recs) == f.last_cycle == 300
        assert [r["cycle"] for r in recs] == list(range(1, 301))
        assert recs[0]["driver"] == "sim" and recs[0]["rig"] == "bench-1"
        stall = [r for r in recs if r["flags"] & Flag.STALL]
        assert len(stall) == 1 and stall[0]["operating_ns"] is None
        assert [r["cycle"] for r in f.records(first=10, last=12)] == [10, 11, 12]
        # The same rows as SQLite holds, field for field.
        db = sqlite3.connect(state_dir / "records.sqlite")
        (err,) = db.execute("SELECT error_ns FROM cycles WHERE cycle = 77").fetchone()
        assert recs[76]["error_ns"] == err


def test_columns_as_arrays_and_a_dataframe(state_dir: Path) -> None:
    with RecordsFile(state_dir / "records.sqlite") as f:
        err = f.column("error_ns")
        assert err.dtype == np.float64 and err.shape == (300,)
        assert np.isnan(err).sum() == 1  # the stall has no error
        assert f.column("cycle").dtype == np.int64
        total, target = f.column("total_ns"), f.column("target_ns")
        assert np.array_equal(err, total - target, equal_nan=True)
        with pytest.raises(ValueError, match="numeric record field"):
            f.column("coefficients")
        df = f.dataframe(first=101)
        assert len(df) == 200 and df.index[0] == 0 and df["cycle"].iloc[0] == 101  # as read_sql
        assert df["error_ns"].std() == pytest.approx(np.nanstd(err[100:], ddof=1), rel=1e-9)
        # No column hides a DataFrame attribute: flags and mode are renamed, each flag a bool column.
        import pandas as pd

        assert not [c for c in df.columns if hasattr(pd.DataFrame, c)]
        assert df["stall"].sum() == (df["flag_bits"] & 4 != 0).sum() and df["loop_mode"].iloc[0] == "closed"
        by_cycle = f.dataframe(index_col="cycle")
        assert by_cycle.index.name == "cycle" and by_cycle.index[0] == 1
        runs = f.runs()
        if runs:
            one = f.dataframe(run=runs[-1]["run_id"])
            assert set(one["run_id"]) == {runs[-1]["run_id"]}


def test_a_missing_or_foreign_file_is_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(RecordsFileError, match="no records file"):
        RecordsFile(tmp_path / "nope.sqlite")
    other = tmp_path / "other.sqlite"
    sqlite3.connect(other).execute("CREATE TABLE t (x)").connection.commit()
    with pytest.raises(RecordsFileError, match="not a usmswitch records file"):
        RecordsFile(other)
