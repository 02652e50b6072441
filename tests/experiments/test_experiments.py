"""usmswitch-experiment on small inputs: every experiment runs, and its summary agrees with the records."""

from __future__ import annotations

import contextlib
import json
import re
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import numpy as np
import pytest

from usmswitch.client import Client
from usmswitch.experiments.cli import main
from usmswitch.experiments.closed_loop import SETTLE
from usmswitch.predictor import aic_table

SCALE = "0.01"  # 1,000 reliability strokes, 40-240 for the others


def run(*args: str) -> int:
    return main(list(args))


@contextlib.contextmanager
def virtual_daemon(tmp_path: Path) -> Iterator[Client]:
    """A daemon on the simulated rig in virtual time, idle, and a client of it."""
    args = daemonproc.daemon_args(
        tmp_path, "--sim-clock", "virtual", "--no-autostart", "--log-level", "warning"
    )
    proc = daemonproc.spawn(args)
    try:
        daemonproc.wait_serving(tmp_path / "d.sock", proc)
        with Client(tmp_path / "d.sock", timeout=30) as c:
            yield c
    finally:
        daemonproc.stop(proc)


@pytest.fixture(scope="module")
def everything(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("all")
    assert run("all", "--scale", SCALE, "--seed", "3", "--out", str(out)) == 0
    return out


def _records(out: Path, run_id: int) -> list[sqlite3.Row]:
    con = sqlite3.connect(out / "records.sqlite")
    con.row_factory = sqlite3.Row
    rows = con.execute("SELECT * FROM cycles WHERE run_id = ? ORDER BY cycle", (run_id,)).fetchall()
    con.close()
    return rows


def test_all_writes_the_summary_figures_and_report(everything: Path) -> None:
    summary = json.loads((everything / "summary.json").read_text())
    assert summary["meta"]["seed"] == 3
    for key in ("open_loop", "speed", "identify", "temperature", "aic", "closed_loop", "reliability"):
        assert key in summary, key
    r = summary["reliability"]
    assert set(r) >= {"cycles", "arrived", "late", "stalls", "target_ns", "seconds"}
    assert (
        r["cycles"] == r["arrived"] == 1000 and r["late"] == r["stalls"] == 0 and r["target_ns"] == 10_500_000
    )
    assert set(summary["aic"]) >= {"orders", "values", "criterion"} and summary["aic"]["orders"] == [1, 2, 3]
    rows = summary["closed_loop"]
    assert {(row["target_ns"], row["frequency_hz"]) for row in rows} == {
        (12_000_000, 40_000.0),
        (24_000_000, 40_500.0),
    }
    for row in rows:
        assert set(row) >= {
            "target_ns",
            "frequency_hz",
            "model",
            "strokes",
            "std_ns",
            "max_abs_error_ns",
            "floor_ns",
        }
        assert 50_000 < row["std_ns"] < 200_000 and row["floor_ns"] > 0
    figures = sorted(p.name for p in (everything / "figures").iterdir())
    assert len(figures) == 16 and all((everything / "figures" / f).stat().st_size > 5000 for f in figures)
    report = (everything / "report.md").read_text()
    for paper_number in ("95.3 µs", "102.7 µs", "3574.2", "3660.5", "100,000", "0.41 %", "0.85 %"):
        assert paper_number in report, paper_number
    for f in figures:
        if f.endswith(".png"):
            assert f"(figures/{f})" in report


def test_figures_and_report_write_micro_and_plus_minus_and_title_the_run_rig_and_date(
    everything: Path,
) -> None:
    """Issue 37's bites: figures and report wrote `us` and `+-`, a legend covered data (save() now
    refuses one that does: every figure here passed it), and no title said which run, rig or day."""
    summary = json.loads((everything / "summary.json").read_text())
    day = summary["meta"]["started"].replace("T", " ")
    svgs = sorted((everything / "figures").glob("*.svg"))
    assert len(svgs) == 8
    for svg in svgs:
        text = svg.read_text()  # matplotlib keeps each text drawn as paths in a comment beside them
        assert f"rig sim-seed-3, {day}" in text, svg.name
        assert re.search(r"<!-- runs? \d+(-\d+)?, rig sim-seed-3", text), svg.name
        assert not re.search(r"\bus\b|\+-", " ".join(re.findall(r"<!-- (.*?) -->", text))), svg.name
    fig11 = (everything / "figures" / "fig11_13_closed_loop_24ms.svg").read_text()
    (run_24,) = [
        c["run_id"] for c in summary["closed_loop_runs"]["conditions"] if c["target_ns"] == 24_000_000
    ]
    assert f"<!-- run {run_24}, rig sim-seed-3" in fig11 and "±" in fig11
    report = (everything / "report.md").read_text()
    assert "µs" in report and "±" in report
    assert not re.search(r"\d us\b|\bus per\b|\+-", report), re.findall(r".{30}(?:\d us\b|\+-).{10}", report)


def test_a_figure_with_a_legend_over_its_data_is_refused_by_name(tmp_path: Path) -> None:
    from usmswitch.experiments.figures import new_figure, save

    fig, ax = new_figure()
    ax[0][0].plot(range(50), [1.0] * 50, ".", label="strokes")
    ax[0][0].legend(loc="center")
    with pytest.raises(ValueError, match="figure covered: a legend over the data"):
        save(fig, tmp_path, "covered")


def test_the_summary_agrees_with_the_records(everything: Path) -> None:
    summary = json.loads((everything / "summary.json").read_text())
    rel = summary["reliability"]
    recs = _records(everything, rel["run_id"])
    assert len(recs) == rel["cycles"] and all(r["t_arrive_ns"] is not None for r in recs)
    assert max(r["operating_ns"] for r in recs) == rel["operating_max_ns"]
    for cond in summary["closed_loop_runs"]["conditions"]:
        recs = _records(everything, cond["run_id"])
        seen = {0: 0, 1: 0}
        errors = []
        for r in recs:  # the controller's own figure: total - T, cold start left out
            seen[r["direction"]] += 1
            if seen[r["direction"]] > SETTLE:
                errors.append(r["error_ns"])
        ours = next(
            row
            for row in summary["closed_loop"]
            if row["target_ns"] == cond["target_ns"] and "controlling" in row["model"]
        )
        assert ours["strokes"] == len(errors)
        assert ours["std_ns"] == pytest.approx(np.std(errors, ddof=1), abs=0.1)
        assert ours["max_abs_error_ns"] == max(abs(e) for e in errors)
        # The offline paper AR(1) on the same strokes is the controller's own prediction.
        paper = next(
            row
            for row in summary["closed_loop"]
            if row["target_ns"] == cond["target_ns"] and row["model"] == "paper AR(1)"
        )
        assert paper["std_ns"] == pytest.approx(ours["std_ns"], abs=1.0)  # t_hat rounded to 1 ns in the loop


def test_open_loop_and_aic_agree_with_the_records(everything: Path) -> None:
    summary = json.loads((everything / "summary.json").read_text())
    o = summary["open_loop"]
    recs = _records(everything, o["run_id"])
    assert len(recs) == o["strokes"] and all(r["delay_ns"] == 0 for r in recs)  # open loop: no delay
    on = [r["operating_ns"] for r in recs if r["direction"] == 0]
    assert o["on"]["n"] == len(on) and o["on"]["mean_ns"] == pytest.approx(np.mean(on), abs=0.1)
    assert (o["on"]["min_ns"], o["on"]["max_ns"]) == (min(on), max(on))
    assert {r["frequency_hz"] for r in recs} == {39_600.0}
    a = summary["aic"]
    on = [r["operating_ns"] for r in _records(everything, a["run_id"]) if r["direction"] == 0]
    table = aic_table(on, 3, "paper", "fit")
    assert a["values"] == [round(v - table.n_rows * np.log(1e6), 1) for v in table.values]


def _strokes_in(db: Path) -> bool:
    """Whether the records file being written has a stroke committed (read, then closed at once)."""
    if not (db.parent / f"{db.name}-wal").exists():
        return False
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        try:
            return bool(con.execute("SELECT count(*) FROM cycles").fetchone()[0])
        finally:
            con.close()
    except sqlite3.OperationalError:  # the schema not there yet
        return False


def test_no_wal_or_shm_left_when_done_or_interrupted(everything: Path, tmp_path: Path) -> None:
    """Issue 37's bites: `make paper`, done or Ctrl-C'd, left records.sqlite-wal and -shm beside
    the records file (the store's read-only readers closed after its writer: SQLite keeps them)."""
    assert sorted(p.name for p in everything.glob("records.sqlite*")) == ["records.sqlite"]
    exe = Path(sys.executable).parent / "usmswitch-experiment"
    out = tmp_path / "cut"
    proc = subprocess.Popen(
        [str(exe), "reliability", "--scale", "0.5", "--seed", "2", "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        # Mid-run: strokes committed. The -wal file alone came with the file's schema, before any
        # stroke: a Ctrl-C then (a loaded machine) kept nothing, and the check below failed.
        while not _strokes_in(out / "records.sqlite"):
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else b""
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0  # cut short, as asked
    assert sorted(p.name for p in out.glob("records.sqlite*")) == ["records.sqlite"]
    con = sqlite3.connect(f"file:{out / 'records.sqlite'}?mode=ro", uri=True)
    try:
        assert con.execute("SELECT count(*) FROM cycles").fetchone()[0] > 0  # what was made is kept
    finally:
        con.close()


def test_an_experiment_waits_for_its_record_writer_however_long_its_close_takes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The record writer's close work (the runs' statistics: 37 runs' quantiles at the end of `all`,
    3.5 s on a quiet machine) outlasted the store's bounded wait (10 s) beside make test's load: the
    store gave up, and the writer, still holding the file, removed -wal and -shm only once done (in
    the test's process: after the check) or never (the CLI's process had exited). An experiment is
    no daemon with a shutdown to bound: it waits for its writer, whatever the machine's load."""
    from usmswitch.daemon.records import RecordStore
    from usmswitch.daemon.run_aggregates import AggregateKeeper

    flush = AggregateKeeper.flush

    def slow_flush(self: AggregateKeeper, conn: sqlite3.Connection) -> None:
        time.sleep(1.5)  # a loaded machine's close work, past the wait shortened below
        flush(self, conn)

    monkeypatch.setattr(AggregateKeeper, "flush", slow_flush)
    monkeypatch.setattr(RecordStore.close, "__defaults__", (500_000_000,))  # 10 s: the test need not
    out = tmp_path / "r"
    assert run("reliability", "--scale", "0.005", "--seed", "4", "--out", str(out)) == 0
    assert sorted(p.name for p in out.glob("records.sqlite*")) == ["records.sqlite"]
    con = sqlite3.connect(f"file:{out / 'records.sqlite'}?mode=ro", uri=True)
    try:
        runs = con.execute("SELECT count(*) FROM runs").fetchone()[0]
        kept = con.execute("SELECT count(*) FROM run_aggregates WHERE summary IS NOT NULL").fetchone()[0]
    finally:
        con.close()
    assert runs >= 1 and kept == runs  # the statistics the writer closed with are in the file


def test_a_seed_replays(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    assert run("reliability", "--scale", "0.005", "--seed", "11", "--out", str(a)) == 0
    assert run("reliability", "--scale", "0.005", "--seed", "11", "--out", str(b)) == 0
    ra, rb = (json.loads((p / "summary.json").read_text())["reliability"] for p in (a, b))
    ra.pop("seconds"), rb.pop("seconds")
    assert ra == rb


def test_from_a_daemons_records_the_same_figures_as_the_records(tmp_path: Path) -> None:
    """A daemon (virtual-time sim) makes a closed-loop run; the experiment reads its records file."""
    with virtual_daemon(tmp_path) as c:
        run_info = c.run(count=300, period="25ms", target="12ms").wait()
        # A live rig without a position sensor: the speed profile says what it needs.
        r = subprocess.run(
            [sys.executable, "-m", "usmswitch.experiments", "speed", "--socket", str(tmp_path / "d.sock"),
             "--out", str(tmp_path / "live")],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert r.returncode == 1
        notes = json.loads((tmp_path / "live" / "summary.json").read_text())["meta"]["notes"]
        assert "speed: skipped: the speed profile needs the simulated rig" in notes[0]
    out = tmp_path / "from"
    db = tmp_path / "state" / "records.sqlite"
    assert run("closed-loop", "--from-records", str(db), "--out", str(out)) == 0
    summary = json.loads((out / "summary.json").read_text())
    con = sqlite3.connect(db)
    rows = con.execute(
        "SELECT direction, error_ns FROM cycles WHERE run_id = ? ORDER BY cycle", (run_info["run_id"],)
    ).fetchall()
    con.close()
    seen = {0: 0, 1: 0}
    errors = []
    for d, e in rows:
        seen[d] += 1
        if seen[d] > SETTLE:
            errors.append(e)
    ours = summary["closed_loop"][0]
    assert ours["model"] == "kalman (default), controlling" and ours["target_ns"] == 12_000_000
    assert ours["strokes"] == len(errors) == 100
    assert ours["std_ns"] == pytest.approx(np.std(errors, ddof=1), abs=0.1)
    assert ours["max_abs_error_ns"] == max(abs(e) for e in errors)
    assert summary["meta"]["where"].endswith(f"run {run_info['run_id']}")


def test_bad_usage(tmp_path: Path) -> None:
    assert run("speed", "--from-records", str(tmp_path / "none.sqlite")) == 2
    assert run("aic", "--run", "3") == 2
    assert run("aic", "--scale", "2") == 2
    assert run("aic", "--queue") == 2  # the daemon's queue: with --socket
    assert run("aic", "--priority", "3") == 2  # with --queue
    assert run("aic", "--socket", str(tmp_path / "d.sock"), "--queue", "--take-over") == 2
    assert run("aic", "--socket", str(tmp_path / "d.sock"), "--queue", "--priority", "1001") == 2
    assert run("aic", "--from-records", str(tmp_path / "none.sqlite"), "--out", str(tmp_path / "o")) == 1


def test_the_console_script_runs(tmp_path: Path) -> None:
    t0 = time.monotonic()
    exe = Path(sys.executable).with_name("usmswitch-experiment")
    r = subprocess.run(
        [str(exe), "aic", "--scale", "0.1", "--seed", "5", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "seed 5" in r.stderr and (tmp_path / "report.md").exists()
    assert time.monotonic() - t0 < 120


def test_drive_sensitivity_measures_the_rigs_drive_and_prints_the_config(tmp_path: Path) -> None:
    # Commissioning on the simulated rig: detuning up slows it, a lower voltage slows it; the measured
    # chords, told to the kalman model, predict the first drive step of the quality scenarios
    # (benchmarks/bench_quality.py measures how well, on other seeds).
    from usmswitch.daemon.config import load_config

    out = tmp_path / "ds"
    assert run("drive-sensitivity", "--seed", "5", "--out", str(out)) == 0
    ds = json.loads((out / "summary.json").read_text())["drive_sensitivity"]
    assert 0.05 < ds["per_khz"] < 0.4 and ds["stderr_per_khz"] < 0.02
    assert -0.5 < ds["per_100v"] < -0.05 and ds["stderr_per_100v"] < 0.02
    lines = dict(line.split(" = ") for line in ds["config"].splitlines())
    cfg = load_config(overrides={f"control.{k}": v.strip('"') for k, v in lines.items()})
    assert cfg.control.sensitivity_frequency == pytest.approx(ds["per_khz"], rel=1e-3)


def test_from_records_reads_the_model_and_mode_and_picks_the_last_closed_loop_run(tmp_path: Path) -> None:
    """Issue 25: any run was labelled "paper AR(1), controlling" and the last run (an open-loop one,
    say) was taken without a word."""
    with virtual_daemon(tmp_path) as c:
        closed = c.run(count=260, period="25ms", target="12ms").wait()
        c.set_mode("open", "1ms")
        opened = c.run(count=260, period="25ms", target="12ms").wait()
    db = str(tmp_path / "state" / "records.sqlite")
    cmd = [sys.executable, "-m", "usmswitch.experiments", "closed-loop", "--from-records", db]
    r = subprocess.run([*cmd, "--out", str(tmp_path / "a")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"run {closed['run_id']} of " in r.stderr and "closed loop, model kalman" in r.stderr
    rows = json.loads((tmp_path / "a" / "summary.json").read_text())["closed_loop"]
    assert (
        rows[0]["model"] == "kalman (default), controlling"
        and rows[0]["measured"] == "closed loop: t - t_hat"
    )
    r = subprocess.run(
        [*cmd, "--run", str(opened["run_id"]), "--out", str(tmp_path / "b")], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    rows = json.loads((tmp_path / "b" / "summary.json").read_text())["closed_loop"]
    assert rows[0]["model"] == "open loop (fixed delay), not controlling"
    report = (tmp_path / "a" / "report.md").read_text()
    assert (
        "switch time within (Fig. 12-13)" in report
        and "equals the prediction error by construction" in report
    )


def test_the_report_names_the_data_it_really_read(everything: Path, tmp_path: Path) -> None:
    report = (everything / "report.md").read_text()
    assert "Data: `records.sqlite` in this folder" in report and (everything / "records.sqlite").exists()
    db = everything / "records.sqlite"
    assert run("open-loop", "--from-records", str(db), "--out", str(tmp_path / "r")) == 0
    report = (tmp_path / "r" / "report.md").read_text()
    assert f"Data: read from {db}" in report and "`records.sqlite` in this folder" not in report
    assert not (tmp_path / "r" / "records.sqlite").exists()


@pytest.mark.parametrize("name", ["open-loop", "closed-loop", "drive-sensitivity", "all"])
def test_each_experiment_has_its_own_help(name: str) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "usmswitch.experiments", name, "--help"], capture_output=True, text=True
    )
    assert r.returncode == 0 and f"usage: usmswitch-experiment {name} " in r.stdout
    assert "--from-records" in r.stdout and "--take-over" in r.stdout
    if name != "all":
        assert "Fig." in r.stdout or "Table" in r.stdout or "Commissioning" in r.stdout, r.stdout


def test_a_figure_with_clipped_text_is_refused_by_name(tmp_path: Path) -> None:
    """Fig. 14's title was cut at the figure's edge; `save` now checks every title and label."""
    from usmswitch.experiments.figures import new_figure, save

    fig, ax = new_figure(1, 2, width=3.0, height=2.0)
    ax[0][1].set_title("T = 24 ms, 40.5 kHz (Fig. 14), a title far too long for its panel")
    with pytest.raises(ValueError, match="figure narrow: text outside the figure"):
        save(fig, tmp_path, "narrow")


def test_the_report_shows_the_rig_models_table_1_and_the_drive_sensitivity(everything: Path) -> None:
    summary = json.loads((everything / "summary.json").read_text())
    report = (everything / "report.md").read_text()
    row = summary["identify"]["rows"][1]  # 40 kHz
    assert row["model"] == {"wn2": 296.7, "two_xi_wn": 23.74, "k_wn": 642.9}
    assert f"| {row['wn2']} / 296.7 / 296.7 |" in report
    d = summary["drive_sensitivity"]
    assert "## Drive sensitivity" in report and f"{d['per_khz']:+.4f}" in report
    assert f"{d['stderr_per_100v']:.4f}" in report and "sensitivity_frequency" in report


def test_aic_on_a_run_too_short_to_fit_says_so(everything: Path, tmp_path: Path) -> None:
    db = everything / "records.sqlite"
    with sqlite3.connect(db) as con:
        short = con.execute(
            "SELECT run_id FROM cycles GROUP BY run_id HAVING count(*) < 20 ORDER BY run_id LIMIT 1"
        ).fetchone()
    assert short is not None
    assert run("aic", "--from-records", str(db), "--run", str(short[0]), "--out", str(tmp_path / "r")) == 1
    notes = json.loads((tmp_path / "r" / "summary.json").read_text())["meta"]["notes"]
    assert notes and "too few to fit AR(1..3)" in notes[0]


def test_fig_9s_trend_is_the_temperatures_on_every_seed(everything: Path) -> None:
    """Issue 25: seed 7 read 8.24, 8.52, 8.77 ms at 25, 27.5, 30 C and another seed 8.29, 8.16, 8.39:
    the friction's drift between runs was as large as the effect. Each temperature now meets the same
    friction (common random numbers), and the trend is taken on five seeds."""
    t = json.loads((everything / "summary.json").read_text())["temperature"]
    means = [r["all"]["mean_ns"] for r in t["rows"]]
    assert means[0] < means[1] < means[2]
    assert len(t["slopes_ms_per_c"]) == 5 and t["every_seed_slower_when_warmer"]
    assert t["slope_spread_ms_per_c"] < 0.25 * min(t["slopes_ms_per_c"])
    # The size docs/sim.md cites: the resonance falls 10 Hz per C, ~12 us per C at 40 kHz.
    assert all(0.008 < slope < 0.016 for slope in t["slopes_ms_per_c"]), t["slopes_ms_per_c"]
    assert "slower when warmer on every seed" in (everything / "report.md").read_text()
