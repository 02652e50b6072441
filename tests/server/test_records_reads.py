"""Issue 35, item 7: records reads are queued fairly (a small read never behind big ones) and dropped
when their client is gone. A real daemon (subprocess) on the simulated rig in virtual time, so that
its records file holds >10,000 strokes in a few seconds."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import msgpack
import pytest
from rawsock import Raw

from usmswitch.client import Client


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, int]]:
    tmp = tmp_path_factory.mktemp("reads")
    sock = tmp / "d.sock"
    args = daemonproc.daemon_args(
        tmp, "--sim-clock", "virtual", "--autostart", "--period", "15ms", socket=sock
    )
    proc = daemonproc.spawn(args)
    try:
        daemonproc.wait_serving(sock, proc)
        with Client(str(sock), timeout=30) as c:
            for _ in range(1200):  # bounded: 12,000 strokes take ~6 s here
                if c.stats()["all"]["count"] >= 12_000:
                    break
                time.sleep(0.1)
            c.stop_cycling()
            assert c.stats()["all"]["count"] >= 10_000
        yield sock, daemonproc.child_pid(proc, "usmswitch.server.rpc_process")
    finally:
        daemonproc.stop(proc)


def test_a_small_history_is_not_queued_behind_big_reads(rig: tuple[Path, int]) -> None:
    """4 panel CSV downloads of a 16k-stroke run made a Unix `history [5]` take 8-30 s."""
    sock, _ = rig
    floods = []
    done = [0]  # flood replies read whole so far (a reader thread per flood connection)
    lock = threading.Lock()

    def read_all(raw: Raw, n: int) -> None:
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=1 << 30)
        got = 0
        while got < n:
            data = raw.sock.recv(1 << 20)
            if not data:
                return
            unpacker.feed(data)
            for _ in unpacker:
                got += 1
                with lock:
                    done[0] += 1

    readers = []
    for _ in range(2):
        raw = Raw(str(sock))
        raw.sock.settimeout(300)
        raw.send(*([0, i, "history", [10_000]] for i in range(1, 5)))
        floods.append(raw)
        readers.append(threading.Thread(target=read_all, args=(raw, 4), daemon=True))
        readers[-1].start()
    time.sleep(0.05)  # the flood's reads are queued first
    with Client(str(sock), timeout=120) as c:
        assert len(c.history(5)) == 5
    with lock:
        before = done[0]
    # 8 reads of 10,000 records at 2 at once: answered in the small lane before all but the first.
    assert before <= 1, f"the small read waited for {before} big ones"
    for raw, reader in zip(floods, readers, strict=True):
        reader.join(300)
        raw.close()


def _readers(server_pid: int) -> list[int]:
    """The server's records reader processes (server/records_reads.py)."""
    found = subprocess.run(
        ["pgrep", "-P", str(server_pid), "-f", "usmswitch.server.records_reads"],
        capture_output=True,
        text=True,
    )
    return [int(pid) for pid in found.stdout.split()]


def _cpu_s(server_pid: int) -> float:
    """CPU seconds of the server process and its records readers, where the reads are done."""
    total = 0.0
    for pid in (server_pid, *_readers(server_pid)):
        with contextlib.suppress(FileNotFoundError):
            fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def test_reads_of_a_client_that_left_are_dropped(rig: tuple[Path, int]) -> None:
    """A `history [10000]` flood left the server reading for 100-300 s after its clients had gone."""
    sock, server_pid = rig
    for _ in range(4):
        raw = Raw(str(sock))
        raw.send(*([0, i, "history", [10_000]] for i in range(1, 33)))
        raw.close()
    # 128 reads of ~1 s of CPU each were queued: kept on, they use a core's worth for minutes.
    # Dropped, the server is quiet once the reads that had begun end (well under a second each,
    # seconds on a loaded machine).
    end = time.monotonic() + 30
    while True:
        before = _cpu_s(server_pid)
        time.sleep(2.0)
        used = _cpu_s(server_pid) - before
        if used < 0.5:
            break
        assert time.monotonic() < end, f"the server used {used:.2f} s of CPU in 2 s, 30 s after they left"
    with Client(str(sock), timeout=60) as c:
        assert len(c.history(5)) == 5


def test_a_reader_process_that_dies_is_replaced(rig: tuple[Path, int]) -> None:
    """The reads run in processes of their own (no GIL shared with the event loop that answers an
    estop): killed, each is started again at its lane's next read, which is answered."""
    sock, server_pid = rig
    with Client(str(sock), timeout=60) as c:
        assert len(c.history(2000)) == 2000  # the large lane's reader is up
        readers = _readers(server_pid)
        assert readers, "no records reader process: the reads share the event loop's GIL"
        for pid in readers:
            os.kill(pid, signal.SIGKILL)
        # A process started and 10,000 records read: 1.9 s with the history above on a quiet
        # machine, past Raw's 5 s beside `make run` and two CPU hogs (loaded run 53): the client's 60.
        raw = Raw(str(sock), timeout=60)
        raw.send([0, 1, "history", [10_000]])
        (reply,) = raw.read(1)  # a new reader is started for it
        raw.close()
        assert reply[2] is None and len(reply[3]) == 10_000, reply[2]
        assert len(c.history(5)) == 5
        assert c.ping() == "pong"
