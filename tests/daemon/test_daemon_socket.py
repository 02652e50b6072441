"""The socket against a real usmswitchd subprocess on the sim: every method, from other processes."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import random
import signal
import socket
import sqlite3
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import daemonproc
import msgpack
import pytest

from usmswitch.client import Client, ConnectionClosed, ErrorCode, RpcError
from usmswitch.protocol.record import Flag

MS = 1_000_000
TOKEN = "lab-token-0123456789abcdef"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Daemon:
    def __init__(self, tmp: Path, *extra: str, config: str = "") -> None:
        self.tmp = tmp
        self.sock = tmp / "d.sock"
        self.port = free_port()
        cfg = tmp / "d.toml"
        cfg.write_text(f'[socket]\ntcp = "127.0.0.1:{self.port}"\ntcp_token = "{TOKEN}"\n{config}')
        self.proc = daemonproc.spawn(daemonproc.daemon_args(tmp, "--config", str(cfg), *extra))
        daemonproc.wait_serving(self.sock, self.proc)

    def client(self, **kw) -> Client:
        return Client(str(self.sock), timeout=10, **kw)

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        self.proc.communicate(timeout=20)
        return self.proc.returncode


@pytest.fixture(scope="module")
def idle(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """A daemon that starts idle (as on hardware): strokes only when asked."""
    d = Daemon(tmp_path_factory.mktemp("idle"), "--no-autostart")
    yield d
    assert d.stop() == 0


def test_status_targets_and_socket_mode(idle: Daemon) -> None:
    mode = stat.S_IMODE(os.stat(idle.sock).st_mode)
    assert mode == 0o660
    with idle.client() as c:
        assert c.ping() == "pong"
        st = c.status()
        assert st["state"] == "idle" and st["driver"] == "sim" and st["protocol_version"] >= 1
        assert st["uptime_ns"] > 0 and st["version"]
        t = c.set_target(13 * MS, "off")
        assert t["target_on_ns"] == 12 * MS and t["target_off_ns"] == 13 * MS
        assert c.get_target()["target_off_ns"] == 13 * MS
        c.set_target(12 * MS)


def test_switch_records_and_history(idle: Daemon) -> None:
    with idle.client() as c:
        first = c.switch("next")
        second = c.switch("next")
        assert first["direction"] != second["direction"]
        assert second["cycle"] == first["cycle"] + 1
        for rec in (first, second):
            assert rec["t_arrive_ns"] is not None and rec["error_ns"] == rec["total_ns"] - rec["target_ns"]
        hist = c.history(2)
        assert [h["cycle"] for h in hist] == [first["cycle"], second["cycle"]]
        assert hist[-1] == second
        with pytest.raises(RpcError) as err:
            c.call("history", 0)
        assert err.value.code == ErrorCode.INVALID_PARAMS


def test_mode_change_applies_from_the_next_stroke_and_is_recorded(idle: Daemon) -> None:
    with idle.client() as c:
        r = c.set_mode("open", 2 * MS)
        assert r["mode"] == "open" and r["open_delay_ns"] == 2 * MS
        rec = c.switch()
        assert rec["mode"] == "open" and rec["delay_ns"] == 2 * MS and rec["cycle"] >= r["from_cycle"]
        c.set_mode("closed")
        assert c.switch()["mode"] == "closed"
    con = sqlite3.connect(idle.tmp / "state" / "records.sqlite")
    kinds = [k for (k,) in con.execute("SELECT kind FROM events ORDER BY rowid")]
    con.close()
    assert "mode" in kinds and "target" in kinds


def test_a_runs_start_and_end_are_in_the_file_when_their_replies_come(idle: Daemon) -> None:
    """CI at 62730fa: `history(50, run)` just after that run's `start_cycling` answered "no run 9
    (runs are 1..8)": the reply left before the run's row was committed, and history is read from
    the file by a reader process. Here the record writer is held 150 ms by a lock on the file before
    each reply (a start, a reset after an estop, a stop); `runs` read just after says what it said."""
    db = idle.tmp / "state" / "records.sqlite"

    @contextlib.contextmanager
    def writer_held() -> Iterator[None]:
        con = sqlite3.connect(db, isolation_level=None, check_same_thread=False)
        con.execute("BEGIN IMMEDIATE")  # the writer's next commit waits (its busy timeout: 200 ms)
        release = threading.Timer(0.15, con.rollback)
        release.start()
        try:
            yield
        finally:
            release.join()
            con.close()

    with idle.client() as c:
        c.history(1)  # the reads' lane started: its process spawn is no part of the race
        with writer_held():
            started = c.start_cycling(20 * MS, 0)
            assert c.history(5, started["run_id"]) is not None
            (run,) = c.runs(1)
            assert run["run_id"] == started["run_id"] and run["end_reason"] is None
        with writer_held():
            c.estop()
            c.reset_fault()
            (run,) = c.runs(1)
            assert run["run_id"] == started["run_id"] and run["end_reason"].startswith("fault: estop")
        started = c.start_cycling(20 * MS, 0)
        with writer_held():
            stopped = c.stop_cycling()
            (run,) = c.runs(1)
            assert run["run_id"] == started["run_id"] and run["end_reason"] == "stopped"
            assert run["last_cycle"] == stopped["run"]["last_cycle"]


def test_cycling_stats_and_subscription(idle: Daemon) -> None:
    with idle.client() as c:
        cyc = c.start_cycling(20 * MS, 30)
        assert cyc["count"] == 30
        with pytest.raises(RpcError) as err:
            c.switch()
        assert err.value.code == ErrorCode.STATE
        got = []
        with c.subscribe("stroke", timeout=5) as sub:
            for rec in (note.payload for note in sub):
                got.append(rec)
                if len(got) == 10:
                    break
        cycles = [r["cycle"] for r in got]
        assert cycles == list(range(cycles[0], cycles[0] + 10))
        stop = c.stop_cycling()
        assert stop["was_cycling"] is True
        assert stop["run"]["run_id"] == cyc["run_id"] and stop["run"]["end_reason"] == "stopped"
        stats = c.stats()  # the run just stopped: exactly its strokes
        run = stats["run"]
        assert run["run_id"] == cyc["run_id"] and run["first_cycle"] == cyc["first_cycle"]
        assert stats["first_cycle"] == run["first_cycle"] and stats["last_cycle"] == run["last_cycle"]
        assert stats["all"]["strokes"] == run["last_cycle"] - run["first_cycle"] + 1 >= 10
        assert stats["on"]["order"] == 1 and len(stats["on"]["coefficients"]) == 1
        assert stats["all"]["abs_error_p99_ns"] >= stats["all"]["abs_error_p50_ns"] >= 0
        assert stats["all"]["max_abs_error_pct"] > 0


def test_estop_latches_fault_and_reset_clears(idle: Daemon) -> None:
    with idle.client() as c:
        with pytest.raises(RpcError) as err:
            c.reset_fault()
        assert err.value.code == ErrorCode.STATE
        e = c.estop()
        assert e["state"] == "fault"
        with pytest.raises(RpcError) as err:
            c.switch()
        assert err.value.code == ErrorCode.FAULT
        assert c.status()["state"] == "fault"
        assert c.reset_fault()["fault"] == e["fault"]
        assert c.switch()["flags"] & Flag.FAULT == 0


def test_set_drive_changes_the_rig(idle: Daemon) -> None:
    with idle.client() as c:
        d = c.set_drive(frequency_hz=39_500.0)
        assert d["frequency_hz"] == 39_500.0
        rec = c.switch()
        assert rec["frequency_hz"] == 39_500.0
        c.set_drive(frequency_hz=40_000.0)
        with pytest.raises(RpcError) as err:
            c.set_drive(enabled=False)
        assert err.value.code == ErrorCode.UNAVAILABLE


def test_pipelined_requests(idle: Daemon) -> None:
    with idle.client() as c:
        results = c.pipeline([("ping", []), ("get_target", []), ("stats", []), ("nope", []), ("ping", [])])
        assert results[0] == "pong" and results[4] == "pong"
        assert results[1]["target_on_ns"] == 12 * MS
        assert isinstance(results[3], RpcError) and results[3].code == ErrorCode.UNKNOWN_METHOD


def _hammer(path: str, n: int, q: multiprocessing.Queue) -> None:
    with Client(path, timeout=10) as c:
        ok = sum(1 for _ in range(n) if "all" in c.stats())
    q.put(ok)


def test_concurrent_clients_from_other_processes(idle: Daemon) -> None:
    ctx = multiprocessing.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=_hammer, args=(str(idle.sock), 200, q)) for _ in range(4)]
    for p in procs:
        p.start()
    with idle.client() as c:
        rec = c.switch()  # a stroke while four other processes hammer stats
        assert rec["t_arrive_ns"] is not None
    results = [q.get(timeout=60) for _ in procs]
    for p in procs:
        p.join(30)
    assert results == [200] * 4


def test_tcp_needs_the_token(idle: Daemon) -> None:
    addr = f"tcp://127.0.0.1:{idle.port}"
    with Client(addr, token=TOKEN, timeout=5) as c:
        assert c.status()["driver"] == "sim"
    with (
        pytest.raises((RpcError, ConnectionClosed)) as err,
        Client(addr, token="wrong-token-0123456789", timeout=5, retry=False) as c,
    ):
        c.status()
    if isinstance(err.value, RpcError):
        assert err.value.code == ErrorCode.UNAUTHORIZED
    raw = socket.create_connection(("127.0.0.1", idle.port), timeout=5)
    raw.sendall(msgpack.packb([0, 1, "stats", []]))
    reply = msgpack.Unpacker(raw=False)
    reply.feed(raw.recv(65536))
    msg = next(reply)
    assert msg[2][0] == ErrorCode.UNAUTHORIZED
    raw.close()


def test_fuzzed_frames_leave_the_daemon_serving_and_stroking(tmp_path: Path) -> None:
    d = Daemon(tmp_path, "--period", "20ms")
    try:
        with d.client() as c:
            before = c.stats()["all"]["count"]
        rng = random.Random(7)
        valid = [
            msgpack.packb([0, 1, "stats", []]),
            msgpack.packb([0, 2, "get_target", []]),  # (a mutated set_target may be a valid one)
            msgpack.packb([0, 3, "history", [5]]),
            msgpack.packb([2, "stats", []]),
        ]
        sent = 0
        while sent < 3000:
            s = socket.socket(socket.AF_UNIX)
            s.settimeout(2)
            try:
                s.connect(str(d.sock))
                for _ in range(50):
                    kind = rng.random()
                    if kind < 0.3:
                        frame = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 64)))
                    elif kind < 0.7:
                        b = bytearray(rng.choice(valid))
                        for _ in range(rng.randint(1, 4)):
                            b[rng.randrange(len(b))] = rng.getrandbits(8)
                        frame = bytes(b)
                    elif kind < 0.85:
                        frame = rng.choice(valid)[: rng.randint(1, 8)]  # truncated
                    else:
                        frame = msgpack.packb([0, rng.getrandbits(40), rng.choice([1, None, "x" * 300]), {}])
                    s.sendall(frame)
                    sent += 1
            except OSError:
                pass  # the server closed this connection on bad input: expected
            finally:
                s.close()
        time.sleep(0.3)
        with d.client() as c:
            st = c.stats()
            assert c.ping() == "pong"
            time.sleep(0.3)
            after = c.stats()["all"]["count"]
            assert st["state"] == "cycling"
            assert after > before and after > st["all"]["count"] - 1
            assert c.get_target()["target_on_ns"] == 12 * MS
    finally:
        assert d.stop() == 0
