"""Issue 36: an export over the socket streams every stroke, a chunk a call (`export`), the same
bytes as an export from the file: through a real Unix socket to a real daemon (its server process)
serving the 100,000-stroke session file (tests/conftest.py). Before, the socket gave the last
10,000 records (`history`) and nothing more. (Speed is the bench's: make bench BENCH=records.)"""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from daemonproc import daemon_args, spawn, stop, wait_serving

from usmswitch.client import Client
from usmswitch.protocol.record_csv import csv_header_line
from usmswitch.protocol.wire import ErrorCode, RpcError

CTL = [sys.executable, "-m", "usmswitch.client.ctl"]


@pytest.fixture(scope="module")
def serving(records_100k: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """(socket, the records file it serves): a daemon over a copy of the session file."""
    tmp = tmp_path_factory.mktemp("export-socket")
    state = tmp / "state"
    state.mkdir()
    shutil.copy(records_100k, state / "records.sqlite")
    sock = tmp / "d.sock"
    proc = spawn(daemon_args(tmp, "--no-autostart", "--priority", "0", socket=sock))
    try:
        wait_serving(sock, proc)
        yield sock, state / "records.sqlite"
    finally:
        stop(proc)


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
    if not select:
        assert by_socket.count(b"\n") == 100_001  # the header and every stroke, past history's 10,000


def test_chunks_are_bounded_and_a_client_may_stop_early(serving: tuple[Path, Path]) -> None:
    sock, _db = serving
    with Client(str(sock), timeout=60) as c:
        chunks = c.export_csv(run=3)
        strokes, last, text = next(chunks)
        assert strokes == 10_000 and text.count("\n") == 10_000
        assert last == 30_000 and text.startswith("20001,")
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
