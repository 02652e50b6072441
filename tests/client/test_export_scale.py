"""Issue 36: exports of a 100,000-stroke file (tests/conftest.py) are the record path's CSV byte
for byte, whole and per run; usmswitchctl's progress bar goes to a terminal's stderr only, never
into a pipe, the CSV or --json output. (Speed is the bench's: make bench BENCH=records.)"""

from __future__ import annotations

import functools
import io
import json
import os
import pty
import subprocess
import sys
from pathlib import Path

import pytest

from usmswitch.client.ctl import output
from usmswitch.client.ctl.main import main as ctl_main
from usmswitch.client.records import RecordsFile
from usmswitch.protocol.record_csv import write_csv

CTL = [sys.executable, "-m", "usmswitch.client.ctl"]


@functools.cache
def _record_path_csv(path: Path, run: int | None = None) -> str:
    """The CSV the record path writes (records read one by one): made once per file and run."""
    out = io.StringIO()
    with RecordsFile(path) as f:
        write_csv(f.records(run=run), out)
    return out.getvalue()


def test_an_export_of_100k_strokes_is_the_record_paths_csv(records_100k: Path, tmp_path: Path) -> None:
    out = tmp_path / "all.csv"
    ctl = [*CTL, "export", "--from", str(records_100k)]
    done = subprocess.run([*ctl, "--csv", str(out)], capture_output=True)
    assert done.returncode == 0, done.stderr
    assert done.stderr == b""  # not a terminal: no progress bar
    text = out.read_text()
    assert text == _record_path_csv(records_100k)
    assert text.count("\n") == 100_001
    # One run, to standard output (a pipe).
    done = subprocess.run([*ctl, "--run", "4", "--csv", "-"], capture_output=True)
    assert done.returncode == 0 and done.stderr == b""
    assert done.stdout.decode() == _record_path_csv(records_100k, run=4)


@pytest.mark.parametrize("as_json", [False, True])
def test_the_progress_bar_is_drawn_on_a_terminal_only(
    records_100k: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    as_json: bool,
) -> None:
    monkeypatch.setattr(output.ExportProgress, "AFTER_NS", 0)  # drawn at once, not after a second
    master, slave = pty.openpty()
    tty = os.fdopen(slave, "w")
    monkeypatch.setattr(sys, "stderr", tty)
    out = tmp_path / "all.csv"
    argv = ["export", "--from", str(records_100k), "--csv", str(out), *(["--json"] if as_json else [])]
    try:
        assert ctl_main(argv) == 0
        tty.flush()
        os.set_blocking(master, False)
        drawn = b""
        try:
            while chunk := os.read(master, 65536):
                drawn += chunk
        except (BlockingIOError, OSError):
            pass
    finally:
        tty.close()
        os.close(master)
    printed = capsys.readouterr().out
    if as_json:
        assert drawn == b"" and json.loads(printed) == {"records": 100_000, "file": str(out)}
    else:
        assert b"export" in drawn and b"strokes" in drawn, drawn[:500]
        assert printed == f"100000 records written to {out}\n"
    assert out.read_text() == _record_path_csv(records_100k)


def test_the_files_chunks_built_ahead_are_in_order_and_an_early_stop_stops_them(records_100k: Path) -> None:
    """`RecordsFile.csv_chunks` builds the chunks ahead on two threads (issue 36): they come in
    cycle order with nothing twice or missing, for a range with an explicit last cycle and for
    small chunks; a reader that stops after one chunk leaves no thread or connection behind, and
    the file reads on."""
    import threading

    with RecordsFile(records_100k) as f:
        lines = _record_path_csv(records_100k).splitlines(keepends=True)[1:]
        got = "".join(text for _n, _last, text in f.csv_chunks(1, 25_003, chunk=777))
        assert got == "".join(lines[:25_003])
        chunks = f.csv_chunks(chunk=1000)
        n, last, text = next(chunks)
        assert (n, last) == (1000, 1000) and text == "".join(lines[:1000])
        chunks.close()
        assert not [t for t in threading.enumerate() if t.name.startswith("export")]
        assert len(f) == 100_000
