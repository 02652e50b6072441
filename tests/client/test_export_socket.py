"""Issue 36: an export over the socket streams every stroke, a chunk a call (`export`), the same
bytes as an export from the file: through a real Unix socket to a real daemon (its server process)
serving the 100,000-stroke session file (tests/conftest.py), runs 2 and 4 labelled. Before, the
socket gave the last 10,000 records (`history`) and nothing more. The chunks are asked a few ahead
(protocol/export_plan.py), by the client and by the panel's CSV: across chunk boundaries, a gap
between a label's runs, an explicit last cycle, a client that stops early. (Speed is the bench's:
make bench BENCH=records.)"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from daemonproc import child_pid, daemon_args, spawn, stop, wait_serving

from usmswitch.client import Client
from usmswitch.client.records import RecordsFile
from usmswitch.protocol.record_csv import csv_header_line
from usmswitch.protocol.wire import ErrorCode, RpcError

CTL = [sys.executable, "-m", "usmswitch.client.ctl"]
#: Runs 2 and 4 (cycles 10001-20000 and 30001-40000) carry it; run 3 lies between them.
LABEL = "gap-pair"


@pytest.fixture(scope="module")
def daemon(
    records_100k: Path, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[Path, Path, str, subprocess.Popen[bytes]]]:
    """(socket, the records file it serves, the panel's URL, the daemon): a daemon over a copy of
    the session file, runs 2 and 4 labelled LABEL."""
    tmp = tmp_path_factory.mktemp("export-socket")
    state = tmp / "state"
    state.mkdir()
    shutil.copy(records_100k, state / "records.sqlite")
    with sqlite3.connect(state / "records.sqlite") as db:
        db.execute("UPDATE runs SET label = ? WHERE run_id IN (2, 4)", (LABEL,))
    sock = tmp / "d.sock"
    proc = spawn(daemon_args(tmp, "--no-autostart", "--priority", "0", "--web", "127.0.0.1:0", socket=sock))
    try:
        wait_serving(sock, proc)
        with Client(str(sock)) as c:
            url = c.status()["web_url"]
        yield sock, state / "records.sqlite", url, proc
    finally:
        stop(proc)


@pytest.fixture(scope="module")
def serving(daemon: tuple[Path, Path, str, Any]) -> tuple[Path, Path]:
    """(socket, the records file it serves)."""
    return daemon[0], daemon[1]


class AskSpy(Client):
    """A Client that notes each `export` request it sends, (first_cycle, last_cycle, max_strokes),
    in `log` beside what the test notes there itself."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.log: list[tuple[Any, ...]] = []
        super().__init__(*args, **kwargs)

    def _send(self, method: str, params: list[Any], flush: bool = True) -> int:
        if method == "export":
            self.log.append(("ask", *params[1:4]))
        return super()._send(method, params, flush)


def _file_csv(db: Path, first: int = 1, last: int | None = None, **which: Any) -> str:
    with RecordsFile(db) as f:
        return "".join(text for _, _, text in f.csv_chunks(first, last, **which))


def _ctl(*argv: str) -> bytes:
    done = subprocess.run([*CTL, *argv], capture_output=True)
    assert done.returncode == 0, done.stderr
    assert done.stderr == b""  # not a terminal: no progress bar
    return done.stdout


@pytest.mark.parametrize(
    "select",
    [[], ["--run", "4"], ["--first", "9990", "--last", "30011"], ["--run", "2", "--first", "15000"]],
    ids=["every stroke", "a run", "a range across chunks", "a run from a cycle"],
)
def test_an_export_over_the_socket_is_the_files_byte_for_byte(
    serving: tuple[Path, Path], select: list[str]
) -> None:
    sock, db = serving
    by_socket = _ctl("--socket", str(sock), "export", *select, "--csv", "-")
    by_file = _ctl("export", "--from", str(db), *select, "--csv", "-")
    assert by_socket == by_file
    if not select:  # the header and every stroke, past history's 10,000, below the labels' lines
        lines = by_socket.splitlines()
        assert [line[:8] for line in lines[:2]] == [b"# run 2:", b"# run 4:"] and len(lines) == 100_003


def test_chunks_are_bounded_and_a_client_may_stop_early(serving: tuple[Path, Path]) -> None:
    sock, _db = serving
    with Client(str(sock), timeout=60) as c:
        chunks = c.export_csv(run=3)
        strokes, last, text = next(chunks)
        assert strokes == 5000 and text.count("\n") == 5000  # export_plan.CHUNK
        assert last == 25_000 and text.startswith("20001,")
        chunks.close()  # asks for no more
        one = c.export_chunk(None, 99_999, None, 5)
        assert one["strokes"] == 2 and one["last_cycle"] == 100_000
        assert c.export_chunk(None, 100_001)["strokes"] == 0
        with pytest.raises(RpcError) as caught:
            c.export_chunk(999)
        assert caught.value.code == ErrorCode.INVALID_PARAMS and "no run 999" in str(caught.value)
        with pytest.raises(RpcError) as caught:
            c.export_chunk(None, 1, None, 10_001)
        assert caught.value.code == ErrorCode.INVALID_PARAMS
        assert csv_header_line().startswith("cycle,direction,")


def test_a_small_read_is_answered_beside_four_exports(serving: tuple[Path, Path]) -> None:
    sock, _db = serving
    stop_ = threading.Event()
    done = [0] * 4
    errors: list[BaseException] = []

    def export(i: int) -> None:
        try:
            with Client(str(sock), timeout=120) as b:
                while not stop_.is_set():
                    for _ in b.export_csv():
                        if stop_.is_set():
                            break
                    done[i] += 1
        except BaseException as exc:  # said below
            errors.append(exc)

    threads = [threading.Thread(target=export, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    try:
        with Client(str(sock), timeout=60) as s:
            for _ in range(10):
                assert [r["run_id"] for r in s.runs(1)] == [10]
                assert len(s.history(5)) == 5
    finally:
        stop_.set()
        for t in threads:
            t.join(120)
    assert not errors, errors


def test_the_next_chunks_are_asked_before_this_one_is_handed_over(serving: tuple[Path, Path]) -> None:
    """The server builds the next chunks while one travels and is written: the request for each
    chunk's successors are out before the chunk reaches the caller, three ranges ahead, each range
    max_strokes cycles (complete by construction). Before, each request waited for the last."""
    sock, db = serving
    with AskSpy(str(sock), timeout=60) as c:
        got = []
        for strokes, last, text in c.export_csv(run=4, max_strokes=3000):
            c.log.append(("got", strokes, last))
            got.append(text)
        assert "".join(got) == _file_csv(db, run=4)
    # Where the run starts is asked first (one stroke: its CSV is read again in the first range);
    # then ranges of 3000 cycles, three in flight, each chunk's successors asked before it is
    # handed over; the short one (the run's end) stops the asking ahead, and once the ranges in
    # flight after it are answered (empty), one stroke from there says there is no more.
    assert c.log == [
        ("ask", 1, None, 1),
        ("ask", 30_001, 33_000, 3000),
        ("ask", 33_001, 36_000, 3000),
        ("ask", 36_001, 39_000, 3000),
        ("ask", 39_001, 42_000, 3000),
        ("got", 3000, 33_000),
        ("ask", 42_001, 45_000, 3000),
        ("got", 3000, 36_000),
        ("ask", 45_001, 48_000, 3000),
        ("got", 3000, 39_000),
        ("got", 1000, 40_000),
        ("ask", 48_001, None, 1),
    ]


@pytest.mark.parametrize("max_strokes", [3000, 10_000])
def test_a_label_export_over_a_gap_is_its_runs_strokes(serving: tuple[Path, Path], max_strokes: int) -> None:
    """Runs 2 and 4 with run 3 between them: a range comes back short at run 2's end (3000: in the
    middle of a range, the next one empty; 10,000: on a range's edge, the next range empty, the one
    after it run 4's), and the export goes on at run 4's first stroke, none of run 3's in it."""
    sock, db = serving
    with AskSpy(str(sock), timeout=60) as c:
        chunks = list(c.export_csv(label=LABEL, max_strokes=max_strokes))
        asked = list(c.log)
        by_run = [text for run in (2, 4) for _, _, text in c.export_csv(run=run)]
    text = "".join(t for _, _, t in chunks)
    assert text == _file_csv(db, label=LABEL) == "".join(by_run)
    assert text.count("\n") == 20_000 and "\n20001," not in text and text.startswith("10001,")
    assert all(0 < n <= max_strokes for n, _, _ in chunks) and sum(n for n, _, _ in chunks) == 20_000
    assert [last for _, last, _ in chunks] == sorted({last for _, last, _ in chunks})
    # Past a short range, one stroke asked from where the ranges left off says where they go on.
    probes = [e[1] for e in asked if e[0] == "ask" and e[3] == 1]
    assert probes[0] == 1 and len(probes) >= 2 and all(p > 20_000 for p in probes[1:])


@pytest.mark.parametrize(
    ("first", "last", "max_strokes"),
    [
        (9990, 30_011, 3000),
        (9990, 30_011, 10_000),
        (35_000, 35_000, 3000),
        (12_345, 18_000, 5655),
        (99_990, 200_000, 3),
    ],
    ids=["across runs", "across runs, 10000", "one stroke", "on a range's edge", "past the end"],
)
def test_an_export_with_a_last_cycle_ends_there(
    serving: tuple[Path, Path], first: int, last: int, max_strokes: int
) -> None:
    sock, db = serving
    with AskSpy(str(sock), timeout=60) as c:
        chunks = list(c.export_csv(None, first, last, max_strokes=max_strokes))
    assert "".join(t for _, _, t in chunks) == _file_csv(db, first, last)
    assert chunks[-1][1] == min(last, 100_000)
    # No request reaches past the last cycle asked for.
    assert all(e[2] is None or e[2] <= last for e in c.log)


def test_a_client_that_stops_early_asks_no_more_and_its_connection_serves_on(
    serving: tuple[Path, Path],
) -> None:
    """Stopped with three chunks in flight: no request goes out after the stop, the replies in flight are
    dropped as they come, and the next calls on the same connection get their own answers."""
    sock, db = serving
    with AskSpy(str(sock), timeout=60) as c:
        chunks = c.export_csv(max_strokes=2000)
        assert next(chunks)[:2] == (2000, 2000)
        in_flight = [e for e in c.log if e[0] == "ask"][-3:]
        assert in_flight == [("ask", 2001, 4000, 2000), ("ask", 4001, 6000, 2000), ("ask", 6001, 8000, 2000)]
        asked = len(c.log)
        chunks.close()
        assert [r["run_id"] for r in c.runs(1)] == [10]
        one = c.export_chunk(None, 99_999, None, 5)
        assert one["strokes"] == 2 and one["last_cycle"] == 100_000
        again = list(c.export_csv(run=3, max_strokes=4000))
        assert "".join(t for _, _, t in again) == _file_csv(db, run=3)
        assert [n for n, _, _ in again] == [4000, 4000, 2000]
        assert len([e for e in c.log[asked:] if e[0] == "ask" and e[3] == 2000]) == 0
        # The three dropped replies come, and are kept by nobody.
        end = time.monotonic() + 60
        while c._abandoned and time.monotonic() < end:
            with contextlib.suppress(TimeoutError):
                c._read(0.2, override=True)
        assert not c._abandoned and not c._replies


def test_the_panels_csv_is_the_files_byte_for_byte(daemon: tuple[Path, Path, str, Any]) -> None:
    """The panel's CSV of a run asks its chunks ahead as the client does: the same bytes as
    usmswitchctl's export of that run from the file (its label's line, the header, every stroke)."""
    _sock, db, url, _proc = daemon
    with urllib.request.urlopen(f"{url}api/runs/4.csv", timeout=60) as resp:
        body = resp.read()
    assert body == _ctl("export", "--from", str(db), "--run", "4", "--csv", "-")
    assert body.startswith(b"# run 4:") and body.count(b"\n") == 10_002


def test_an_export_whose_connection_breaks_goes_on_where_it_was(daemon: tuple[Path, Path, str, Any]) -> None:
    """The server process killed with chunks in flight: the export asks again on a fresh connection
    (once, as an idempotent call is retried) from the first cycle it has not handed over, the same
    bytes as the file's, none twice."""
    sock, db, _url, proc = daemon
    with Client(str(sock), timeout=60) as c:
        chunks = c.export_csv(run=5, max_strokes=2000)
        got = [next(chunks)]
        os.kill(child_pid(proc, "usmswitch.server.rpc_process"), signal.SIGKILL)
        wait_serving(sock, proc)  # the daemon starts another
        got += list(chunks)
    assert "".join(t for _, _, t in got) == _file_csv(db, run=5)
    assert [last for _, last, _ in got] == list(range(42_000, 50_001, 2000))
