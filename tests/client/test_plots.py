"""Run plots drawn from a real records file."""

from __future__ import annotations

from pathlib import Path

import pytest

from usmswitch.client.plots import plot_run
from usmswitch.daemon.loop import ControlLoop
from usmswitch.daemon.records import RecordStore
from usmswitch.predictor import ARPredictor
from usmswitch.sim import SimDaq


def test_plot_of_a_recorded_run(tmp_path: Path) -> None:
    store = RecordStore(tmp_path / "records.sqlite")
    daq = SimDaq(seed=4)
    daq.open()
    loop = ControlLoop(daq, [ARPredictor(nominal_ns=10_500_000) for _ in range(2)], target_ns=12_000_000,
                       sink=store.submit)  # fmt: skip
    loop.run_cycles(40_000_000, 300)
    store.close()
    records = list(RecordStore(tmp_path / "records.sqlite", readonly=True).iter_records())
    assert len(records) == 300
    png = plot_run(records, tmp_path / "run.png")
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    svg = plot_run(records, tmp_path / "run.svg", title="seed 4").read_text()
    assert "seed 4" in svg


def test_nothing_to_plot_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no completed strokes"):
        plot_run([], tmp_path / "x.png")
