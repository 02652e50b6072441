"""Run plots drawn from a real records file."""

from __future__ import annotations

import datetime
from dataclasses import replace
from pathlib import Path

import matplotlib
import matplotlib.text
import pytest

from usmswitch.client.plots import draw_run, legends_over_data, plot_run, run_marks
from usmswitch.daemon.loop import ControlLoop
from usmswitch.daemon.records import RecordStore
from usmswitch.predictor import ARPredictor
from usmswitch.protocol.record import CycleRecord
from usmswitch.sim import SimDaq


def recorded(tmp_path: Path, seed: int, *targets_and_counts: tuple[int, int]) -> list[CycleRecord]:
    """Strokes of the simulated rig through the loop into a real records file, read back: `count`
    strokes at each target in turn."""
    store = RecordStore(tmp_path / "records.sqlite")
    daq = SimDaq(seed=seed)
    daq.open()
    first_target = targets_and_counts[0][0]
    loop = ControlLoop(daq, [ARPredictor(nominal_ns=10_500_000) for _ in range(2)], target_ns=first_target,
                       sink=store.submit)  # fmt: skip
    for target_ns, count in targets_and_counts:
        loop.set_targets([target_ns, target_ns])
        loop.run_cycles(40_000_000, count)
    store.close()
    return list(RecordStore(tmp_path / "records.sqlite", readonly=True).iter_records())


def test_plot_of_a_recorded_run(tmp_path: Path) -> None:
    records = recorded(tmp_path, 4, (12_000_000, 300))
    assert len(records) == 300
    png = plot_run(records, tmp_path / "run.png")
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    svg = plot_run(records, tmp_path / "run.svg", title="seed 4").read_text()
    assert "seed 4" in svg


def test_nothing_to_plot_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no completed strokes"):
        plot_run([], tmp_path / "x.png")


def test_a_sweep_is_marked_by_run_and_target_and_every_axis_has_its_unit(tmp_path: Path) -> None:
    records = recorded(tmp_path, 5, (12_000_000, 60), (14_000_000, 60))
    # Two runs as the daemon stamps them (the loop alone leaves run_id to the daemon).
    records = [replace(r, run_id=1 if r.cycle <= 60 else 2) for r in records]
    marks = run_marks(records)
    assert [(m.cycle, m.kind) for m in marks] == [(1, "run"), (61, "run"), (61, "target"), (62, "target")]
    assert [m.label for m in marks if m.kind == "target"] == ["T on 14.000 ms", "T off 14.000 ms"]
    assert run_marks([replace(r, run_id=None) for r in records[:60]]) == []  # one T, no runs: no marks
    svg = plot_run(records, tmp_path / "sweep.svg").read_text()
    for text in ("run 2", "T on 14.000 ms", "cycle", "operating time t, predicted t_hat (ms)",
                 "error = total - T (µs)", "strokes (count)", "T = 12.000 ms, 14.000 ms"):  # fmt: skip
        assert text in svg, text


def test_the_title_names_the_run_the_rig_and_the_date_and_no_legend_covers_a_stroke(tmp_path: Path) -> None:
    """Issue 37's bites: the plots wrote `us` and `+-`, the legend sat on the strokes (upper right,
    where a drifting run's points are), and the title said neither which run, nor which rig, nor when."""
    import matplotlib.pyplot as plt

    records = [replace(r, run_id=7, rig="lab-a") for r in recorded(tmp_path, 6, (12_000_000, 400))]
    day = datetime.datetime.fromtimestamp(records[0].wall_ns / 1e9).strftime("%Y-%m-%d %H:%M:%S")
    fig = draw_run(records, title="after the bearing change")
    try:
        texts = [t.get_text() for t in fig.findobj(matplotlib.text.Text)]
        assert fig.get_suptitle() == f"after the bearing change\nrun 7, rig lab-a, {day}"
        assert not legends_over_data(fig)
    finally:
        plt.close(fig)
    shown = " ".join(texts)
    assert "µs" in shown and "±0.42 %" in shown
    assert " us" not in shown and "(us)" not in shown and "+-" not in shown


def test_a_legend_over_the_strokes_is_seen(tmp_path: Path) -> None:
    """The check itself can fail: a legend put on the points is reported."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot(range(100), [5] * 100, ".", label="strokes")
    ax.legend(loc="center")
    try:
        (found,) = legends_over_data(fig)
    finally:
        plt.close(fig)
    assert "its legend covers" in found
