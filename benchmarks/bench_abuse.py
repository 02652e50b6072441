"""Estop latency and loop lateness under every abusive load of issue 10, beside the idle figures.

One usmswitchd on the real-time sim (closed loop, T = 12 ms, period 15 ms, SCHED_FIFO when allowed)
runs through the whole benchmark. Each load runs in processes of its own while
- the loop's start lateness is read from the daemon's records for the strokes of that window
  (p50, p99, max; target: p99 <= 1.2x idle in the same run), and
- estops are sent on the estop socket at random instants: the time from the request's last byte
  to the reply, which the daemon sends only once the drive is off and nothing is scheduled
  (target: p99 <= 5 ms), each followed by reset and cycling again over a connection opened before
  the load.
RSS of the daemon and of its socket-server process is sampled at the end of each window (memory
bounded under unread pipelined reads).

The loads run with the machine's CPUs kept from halting, as a real-time host's are (`idle=poll`'s
equivalent from user space, benchmarks/cpu_idle.py; BENCH_ABUSE_IDLE=halt for the machine as it
comes): on this VM a halted vCPU's wake-up alone put a trivial echo's p99 at 3.3 ms. The floor is
measured both ways first, and printed.

The daemon serves its Prometheus page all along (`--metrics`): one load hammers it with scrapers.
It serves the browser panel too (`--web`): one load is 10 open panels, each reading the live feed.
One load keeps a queue of 100 runs edited (issue 38): its clients submit, re-prioritise, cancel
and re-submit runs and edit runs' notes while the bench's own run cycles (the queue paused, so none
of them starts: benchmarks/abuse_loads.py, load_queue_edits).
With PostgreSQL 15 installed (tests/pgserver.py), the daemon also ships to a database that is down
until the last load, and its records file starts with a backlog of BENCH_ABUSE_BACKLOG synthetic
strokes: the last load starts the server, and the window runs while the shipper catches up; the
server is stopped after it, before the idle window (its autovacuum of the rows just shipped, which
comes within its minute's nap, ran in that window before: late p99 444 and 1,523 us there in two
runs, 82-110 in the others).

The loads themselves, each the body of a process, are in benchmarks/abuse_loads.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import multiprocessing
import os
import random
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
import msgpack

from benchmarks.abuse_floor import Floor
from benchmarks.abuse_loads import (
    LOADS,
    MS,
    NEEDS,
    connect_unix,
    load_exports,
    load_stats,
    load_unread_history,
)
from benchmarks.bench_loop import PRIORITY, fifo_allowed, percentiles
from benchmarks.cpu_idle import MODES, Polling, describe, steal_ms, vcpu_holds
from benchmarks.table import print_table
from usmswitch.client import Client, ConnectionClosed, RpcError
from usmswitch.protocol.sockets import tcp_token_path, web_token_path
from usmswitch.protocol.wire import estop_socket_path
from usmswitch.runtime.children import wait_exit

ROOT = Path(__file__).resolve().parents[1]
PERIOD_MS = 15
BACKLOG = int(os.environ.get("BENCH_ABUSE_BACKLOG", "200000"))
# 20 s (~1,330 strokes) per load: with 8 s (~530) a window's p99 is its 6th-worst stroke, and two
# idle windows of one run read 12.9 and 23.0 us, more apart than the 1.2x the rows are held to.
WINDOW_S = float(os.environ.get("BENCH_ABUSE_WINDOW_S", "20"))
# 100 a path per load, the kept estop's too: with 20 a p99 was the slowest single one (stop 41 for
# the paths; the kept estop's 20 until stop 58); with 100 it is the 2nd.
ESTOPS = int(os.environ.get("BENCH_ABUSE_ESTOPS", "100"))
PATH_ESTOPS = int(os.environ.get("BENCH_ABUSE_PATH_ESTOPS", "100"))
# The machine's holds are looked for this long on each CPU at the start (benchmarks/cpu_idle.py).
HOLDS_S = float(os.environ.get("BENCH_ABUSE_HOLDS_S", "10"))
# A comma-separated list of words: only the loads whose names contain one of them (and idle).
ONLY = [w for w in os.environ.get("BENCH_ABUSE_ONLY", "").split(",") if w]
# The CPUs kept from halting while the loads run, as a real-time host's are (benchmarks/cpu_idle.py).
IDLE = os.environ.get("BENCH_ABUSE_IDLE", "poll")


# -- the daemon and the measurements ---------------------------------------------------------------
def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def server_pid(daemon_pid: int) -> int | None:
    out = subprocess.run(["pgrep", "-P", str(daemon_pid)], capture_output=True, text=True).stdout.split()
    return int(out[0]) if out else None


class Steady:
    """The bench's control connection: under a load that holds every slot, a full door sheds it when
    it is the longest idle (by design, docs/protocol.md "Doors and budgets"); each call is tried
    again on a fresh connection (a few times, 0.3 s apart) instead of ending the bench."""

    def __init__(self, client: Client) -> None:
        self.client = client

    def __getattr__(self, name: str) -> Any:
        method = getattr(self.client, name)

        def call(*args: Any, **kw: Any) -> Any:
            for attempt in range(10):
                try:
                    return method(*args, **kw)
                except (ConnectionClosed, OSError, RpcError) as exc:
                    if attempt == 9 or (isinstance(exc, RpcError) and exc.code != 1):  # 1: BUSY
                        raise
                    time.sleep(0.3)
                    with contextlib.suppress(OSError, RpcError):
                        self.client.reconnect()
            raise AssertionError("unreachable")

        return call


class Estopper:
    """Estops on a connection to the estop socket kept open, and a control connection for resets."""

    def __init__(self, sock: Path, control: Client) -> None:
        self.path = sock
        self.control = control
        self.msgid = 0
        self._open()

    def _open(self) -> None:
        self.sock = connect_unix(str(estop_socket_path(self.path)))
        self.unpacker = msgpack.Unpacker()
        self.sock.sendall(msgpack.packb([0, 0, "ping", []]))  # within the estop socket's first-frame bound

    def estop(self) -> float:
        """On the connection kept open; when a full estop socket shed it (idle longest), a new one
        is opened and the estop timed on it, from the connect."""
        self.msgid += 1
        frame = msgpack.packb([0, self.msgid, "estop", []])
        t0 = time.perf_counter_ns()
        for attempt in range(2):
            try:
                self.sock.sendall(frame)
                while True:
                    data = self.sock.recv(65_536)
                    if not data:
                        raise ConnectionResetError("shed")
                    self.unpacker.feed(data)
                    for msg in self.unpacker:
                        if msg[0] == 1 and msg[1] == self.msgid:
                            took = time.perf_counter_ns() - t0
                            if msg[2] is not None:
                                raise RuntimeError(f"estop refused: {msg[2]}")
                            return took / 1e6
            except OSError:
                if attempt:
                    raise
                self.sock.close()
                t0 = time.perf_counter_ns()
                self._open()
        raise AssertionError("unreachable")

    def resume(self) -> None:
        """Reset and cycle again; over a fresh connection when a full door shed the control one."""
        for attempt in range(5):
            try:
                if self.control.status()["state"] == "fault":
                    self.control.reset_fault()
                self.control.start_cycling(PERIOD_MS * MS, take_over=True)
                return
            except (ConnectionClosed, RpcError, OSError):
                if attempt == 4:
                    raise
                time.sleep(0.2)
                with contextlib.suppress(OSError, RpcError):
                    self.control.reconnect()


def _raise_observer() -> bool:
    """SCHED_FIFO one below the loop for this (measuring) process, when allowed."""
    if not fifo_allowed():
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PRIORITY - 1))
    except OSError:
        return False
    return True


#: The documented ways an estop reaches the daemon: each on a fresh connection as a client makes
#: it, but the panel's feed, which the page holds open (its POST is the fallback when it is down).
PATHS = ("estop socket", "main socket", "TCP", "panel feed", "panel POST")
#: Beside them, in the same window: the machine's own floor for a fresh Unix exchange
#: (benchmarks/abuse_floor.py). Reported, not held to a target.
FLOOR = "floor: fresh Unix echo"


class PanelFeed:
    """A live feed opened with the token, read all the time as the page reads it, opened when made
    as the page opens it on load; `estop()` sends `{"estop": ID}` on it and times the answer (ms)
    from the send to the answer's arrival. A feed that closed (shed, the server busy) is opened
    again and the estop timed from the open.

    Read only inside `estop()` (as it was until stop 46), the ticks of the window and of the other
    paths' rounds (30 s and more) waited in the socket, and the first estop of each round read them
    all before its answer: a p99 over 5 ms even idle, a cost no page that reads its feed pays.

    In a process of its own, as a browser is. Read on a thread of the measuring process (until
    stop 55), its decoding of the feed held that process's GIL while another path's reply waited
    to be read: under the queue's edits (a notification of the whole queue, ~50 KB, 200 a second)
    the main socket's estop was answered by the server in 1 ms and read by the bench 5-6 ms later
    (a probe's stamps on both sides, stop 55)."""

    def __init__(self, web_url: str, web_token: str) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, theirs = ctx.Pipe()
        self._proc = ctx.Process(target=_feed_process, args=(theirs, web_url, web_token), daemon=True)
        self._proc.start()
        theirs.close()
        self._ask("opened")

    def _ask(self, *command: Any) -> Any:
        self._conn.send(command)
        if not self._conn.poll(60):
            raise RuntimeError(f"the panel feed's process did not answer {command[0]!r} within 60 s")
        ok, value = self._conn.recv()
        if not ok:
            raise RuntimeError(value)
        return value

    def estop(self) -> float:
        return float(self._ask("estop"))

    def set_fifo(self, raised: bool) -> None:
        """The feed's reading thread at the observer's policy (`_raise_observer`): its reads are timed."""
        self._ask("fifo", raised)

    def close(self) -> None:
        with contextlib.suppress(RuntimeError, OSError, EOFError):
            self._ask("close")
        self._proc.join(5)
        if self._proc.is_alive():
            self._proc.kill()


def _feed_process(conn: Any, web_url: str, web_token: str) -> None:
    """The panel feed's process: `_Feed`'s calls as the measuring process asks them, on a pipe."""
    feed = _Feed(web_url, web_token)
    while True:
        command = conn.recv()
        try:
            if command[0] == "estop":
                conn.send((True, feed.estop()))
            elif command[0] == "fifo":
                conn.send((True, feed.set_fifo(command[1])))
            elif command[0] == "close":
                feed.close()
                conn.send((True, None))
                return
            else:
                conn.send((True, None))
        except Exception as exc:  # said in the measuring process as a failed estop
            conn.send((False, f"{type(exc).__name__}: {exc}"))


class _Feed:
    """The panel feed (PanelFeed) in its process: read on a thread of its own."""

    def __init__(self, web_url: str, web_token: str) -> None:
        self.url = f"{web_url}api/live"
        self.headers = {"X-Usmswitch-Token": web_token}
        self.loop = asyncio.new_event_loop()
        self.http: Any = None
        self.ws: Any = None
        self.sent = 0
        self._answers: dict[int, asyncio.Future[tuple[int, dict[str, Any]]]] = {}
        self._thread = threading.Thread(target=self.loop.run_forever, name="panel-feed", daemon=True)
        self._thread.start()
        self._call(self._open())  # as the page opens it on load, before any estop

    def _call(self, coro: Any, timeout_s: float = 15.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def set_fifo(self, raised: bool) -> None:
        """The reading thread at the observer's policy (`_raise_observer`): its reads are timed."""

        async def setting() -> None:
            if raised:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PRIORITY - 1))
            else:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

        self._call(setting())

    async def _open(self) -> None:
        if self.http is None:
            self.http = aiohttp.ClientSession()
        self.ws = await self.http.ws_connect(self.url, headers=self.headers)
        self.loop.create_task(self._read(self.ws))

    async def _read(self, ws: Any) -> None:
        try:
            async for msg in ws:
                if msg.type != aiohttp.WSMsgType.TEXT:
                    break
                answer = json.loads(msg.data).get("estop")
                fut = self._answers.pop(answer["id"], None) if answer is not None else None
                if fut is not None and not fut.done():
                    fut.set_result((time.perf_counter_ns(), answer))
        finally:
            for fut in self._answers.values():
                if not fut.done():
                    fut.set_exception(ConnectionResetError("the feed closed"))
            self._answers.clear()

    async def _estop(self) -> float:
        self.sent += 1
        t0 = time.perf_counter_ns()
        if self.ws is None or self.ws.closed:
            await self._open()
        fut = self.loop.create_future()
        self._answers[self.sent] = fut
        await self.ws.send_str(json.dumps({"estop": self.sent}))
        t_answer, answer = await asyncio.wait_for(fut, 10)
        if "error" in answer:
            raise RuntimeError(f"feed estop refused: {answer['error']}")
        return (t_answer - t0) / 1e6

    def estop(self) -> float:
        try:
            return self._call(self._estop())
        except (OSError, aiohttp.ClientError):
            self.ws = None
            return self._call(self._estop())

    def close(self) -> None:
        async def closing() -> None:
            if self.http is not None:
                await self.http.close()

        self._call(closing())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5)
        self.loop.close()


def estop_by(
    path_name: str, sock: Path, tcp: str, tcp_token: str, web_url: str, web_token: str, feed: PanelFeed
) -> float:
    """One estop by `path_name`, from connecting (the feed: sending) to the reply that says the
    drive is off, in ms."""
    if path_name == "panel feed":
        return feed.estop()
    t0 = time.perf_counter_ns()
    if path_name == "estop socket":
        with Client(str(estop_socket_path(sock)), timeout=10, retry=False) as c:
            c.call("estop")
    elif path_name == "main socket":
        with Client(str(sock), timeout=10, retry=False) as c:
            c.call("estop")
    elif path_name == "TCP":
        # As usmswitchctl estop --tcp makes it: the auth in one write with the estop.
        with Client(f"tcp://{tcp}", token=tcp_token, timeout=10, retry=False, auth_with_first_call=True) as c:
            c.call("estop")
    else:
        import http.client

        host, _, port = web_url.split("/")[2].rpartition(":")
        conn = http.client.HTTPConnection(host, int(port), timeout=10)
        conn.request("POST", "/api/control/estop", b"{}", {"X-Usmswitch-Token": web_token})
        resp = conn.getresponse()
        resp.read()
        conn.close()
        if resp.status != 200:
            raise RuntimeError(f"panel estop refused: {resp.status}")
    return (time.perf_counter_ns() - t0) / 1e6


def path_figures(took: list[float]) -> tuple[float, float, float]:
    """(p50, p99, max) of one path's estops, ms: the p99 the nearest rank (of 100, the 2nd slowest)."""
    took = sorted(took)
    return took[len(took) // 2], took[min(len(took) - 1, round(0.99 * (len(took) - 1)))], took[-1]


def lateness_between(db: Path, first: int, last: int) -> list[int]:
    con = sqlite3.connect(db)
    rows = con.execute(
        "SELECT lateness_ns FROM cycles WHERE cycle > ? AND cycle <= ? AND lateness_ns IS NOT NULL",
        (first, last),
    ).fetchall()
    con.close()
    return [r[0] for r in rows]


def sigterm_exit_ms(runs: int = 5) -> list[float]:
    """SIGTERM to exit of a daemon whose first stroke waits for a start 5 s - t_hat away."""
    out = []
    for _ in range(runs):
        tmp = Path(tempfile.mkdtemp(prefix="usm-term-"))
        cmd = [
            sys.executable, "-m", "usmswitch.daemon.cli", "--sim", "--state-dir", str(tmp / "state"),
            "--socket", str(tmp / "d.sock"), "--log-format", "json", "--target", "5s", "--period", "6s",
        ]  # fmt: skip
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        # Started (its stop signals caught once its scheduling is set) and waiting for the first
        # start: a fixed 2.5 s sent SIGTERM to a daemon still starting on a loaded machine (-15).
        _wait_running(tmp / "d.sock", proc)
        time.sleep(0.5)
        rc, took = term_and_wait(proc)
        out.append(took)
        if rc is None:
            proc.kill()
            raise RuntimeError("usmswitchd still ran 30 s after SIGTERM")
        if rc != 0:
            raise RuntimeError(f"usmswitchd exited {rc} after SIGTERM")
    return out


def _wait_running(sock: Path, proc: subprocess.Popen[bytes]) -> None:
    """Until the daemon's status says how its loop is scheduled (run() has begun), at most 60 s."""
    end = time.monotonic() + 60
    while time.monotonic() < end and proc.poll() is None:
        with contextlib.suppress(OSError, RpcError), Client(str(sock), timeout=5) as c:
            if not c.status()["scheduling"].startswith("not yet"):
                return
        time.sleep(0.05)
    raise RuntimeError("usmswitchd did not start within 60 s")


HEAVY_LOAD = "10 export clients and 8 x 32 unread history 10000"
IDLE_AGAIN = "idle again, after the loads"


def term_and_wait(proc: subprocess.Popen[bytes]) -> tuple[int | None, float]:
    """SIGTERM `proc`; (exit status or None after 30 s, ms from the signal to the exit).

    Not proc.wait(30): its polling sleeps grow to 50 ms and landed in the figure (114 ms measured
    for an exit at 64 ms); the pidfd wakes us the moment the daemon exits. And the observer runs
    above the daemon's priority while it waits, when it may: at normal priority, on a machine
    the load keeps busy, its own wake-up came 30-60 ms late and was counted as the daemon's.
    """
    raised = False
    if fifo_allowed():
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PRIORITY + 1))
            raised = True
    try:
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGTERM)
        rc = wait_exit(proc, 30)
        return rc, (time.perf_counter() - t0) * 1e3
    finally:
        if raised:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def sigterm_under_load(proc: subprocess.Popen[bytes], sock: str, ctx: Any) -> float:
    """SIGTERM to exit (ms) of the cycling bench daemon while the heaviest readers pull its history:
    the server process must not wait for a reader thread packing a long reply."""
    stop = ctx.Event()
    workers = [ctx.Process(target=load_exports, args=(sock, stop)) for _ in range(10)]
    workers.append(ctx.Process(target=load_unread_history, args=(sock, stop), kwargs={"conns": 8}))
    for w in workers:
        w.start()
    try:
        time.sleep(3.0)  # the readers have started and are busy packing
        rc, took = term_and_wait(proc)
    finally:
        stop.set()
        for w in workers:
            w.join(10)
            if w.is_alive():
                w.kill()
    if rc is None:
        raise RuntimeError("usmswitchd still ran 30 s after SIGTERM under load")
    if rc != 0:
        raise RuntimeError(f"usmswitchd exited {rc} after SIGTERM under load")
    return took


def postgres_with_backlog(state: Path) -> tuple[Any, str] | None:
    """A PostgreSQL server, down, and a records file holding BACKLOG strokes of rig "bench" to ship
    once it is up; None (and why, printed) without PostgreSQL 15 here."""
    sys.path.insert(0, str(ROOT / "tests"))
    import pgserver

    why = pgserver.missing()
    if why is not None:
        print(f"no shipper row: {why}")
        return None
    from usmswitch.daemon.records import RecordStore

    server = pgserver.PgServer()
    server.start()
    url = server.database("bench")
    server.stop()
    store = RecordStore(state / "records.sqlite", driver="sim", rig="bench")
    for first in range(1, BACKLOG + 1, 10_000):
        for rec in pgserver.synthetic_records(first, min(10_000, BACKLOG + 1 - first)):
            store.submit(rec)
    store.close()
    return server, url


def shipper_catches_up(control: Client, pg: Any) -> tuple[str, Callable[[], int]]:
    """Start the database and wait until the shipper is connected; returns the row's name-maker."""
    pg.start()
    end = time.monotonic() + 30
    while not (status := control.status()["records"]["postgres"])["connected"]:
        if time.monotonic() > end:
            raise RuntimeError(f"the shipper did not connect: {status['error']}")
        time.sleep(0.05)
    return "shipper catching up a backlog", lambda: control.status()["records"]["postgres"]["shipped"]


def database_after(pg: Any) -> str:
    """What the shipper's database has done with its tables since it came up (autovacuum, analyze)."""
    rows = pg.admin(
        "select relname, n_tup_ins, last_autovacuum, last_autoanalyze from pg_stat_user_tables"
        " order by n_tup_ins desc limit 2",
        dbname="bench",
    )
    return "; ".join(
        f"{name} {ins} rows in, autovacuum {'at ' + str(vac.time()) if vac else 'not yet'},"
        f" autoanalyze {'at ' + str(ana.time()) if ana else 'not yet'}"
        for name, ins, vac, ana in rows
    )


def floor_halting_and_polling(floor: Floor, ctx: Any, rng: random.Random) -> Polling:
    """The machine's floor (a fresh Unix echo) with its CPUs halting, then polling, printed; the
    polling is left on (the caller closes it)."""
    raised = _raise_observer()
    halting = floor.sample(2 * PATH_ESTOPS, rng)
    polling = Polling(ctx)
    time.sleep(0.5)
    polled = floor.sample(2 * PATH_ESTOPS, rng)
    if raised:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    figures = "; ".join(
        "{} p50 / p99 / max {:.2f} / {:.2f} / {:.2f} ms".format(mode, *path_figures(took))
        for mode, took in (("halt", halting), ("poll", polled))
    )
    print(f"the machine's floor (a fresh Unix echo, {2 * PATH_ESTOPS} each), its CPUs {figures}")
    return polling


def main() -> int:
    if IDLE not in MODES:
        raise SystemExit(f"BENCH_ABUSE_IDLE must be one of {', '.join(MODES)}, got {IDLE!r}")
    fifo = fifo_allowed()
    # Before the daemon starts: a spinner above its loop would hold the loop from its CPU.
    holds = vcpu_holds(multiprocessing.get_context("spawn"), HOLDS_S, PRIORITY + 1 if fifo else 0)
    tmp = Path(tempfile.mkdtemp(prefix="usm-abuse-"))
    sock = tmp / "d.sock"
    (tmp / "state").mkdir(mode=0o700)
    wants_pg = not ONLY or any(w in "shipper catching up a backlog" for w in ONLY)
    pg = postgres_with_backlog(tmp / "state") if wants_pg else None
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        tcp = f"127.0.0.1:{free.getsockname()[1]}"
    conf = tmp / "bench.toml"
    conf.write_text(f'[socket]\ntcp = "{tcp}"\n')  # the daemon makes the token (usmswitchd.tcp-token)
    cmd = [
        sys.executable, "-m", "usmswitch.daemon.cli", "--sim", "--state-dir", str(tmp / "state"),
        "--socket", str(sock), "--log-format", "json", "--log-level", "warning", "--target", "12ms",
        "--period", f"{PERIOD_MS}ms", "--priority", str(PRIORITY if fifo else 0),
        "--metrics", "127.0.0.1:0", "--web", "127.0.0.1:0", "--rig", "bench", "--config", str(conf),
    ]  # fmt: skip
    if pg is not None:
        cmd += ["--postgres", pg[1]]
    # Its warnings kept: a stop past its budget says where its time went (daemon/service.py).
    log_path = tmp / "daemon.log"
    with open(log_path, "wb") as log_file:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log_file)
    ctx = multiprocessing.get_context("spawn")
    floor = Floor(ctx, tmp, PRIORITY - 1 if fifo else 0)
    polling: Polling | None = None
    feed: PanelFeed | None = None
    rng = random.Random(1)
    rows = []
    path_rows: list[tuple[str, dict[str, list[float]], float]] = []
    idle_lat: list[int] = []
    try:
        end = time.monotonic() + 30
        while True:
            try:
                with Client(str(sock), timeout=5) as c:
                    c.stats()
                break
            except (OSError, RpcError):
                if proc.poll() is not None or time.monotonic() > end:
                    raise RuntimeError("the daemon did not start") from None
                time.sleep(0.05)
        db = tmp / "state" / "records.sqlite"
        control: Any = Steady(Client(str(sock), timeout=30))
        control.ping()
        estopper = Estopper(sock, control)
        time.sleep(1.0)
        policy = "SCHED_FIFO" if fifo else "SCHED_OTHER"
        print(f"policy {policy}; window {WINDOW_S:g} s; {ESTOPS} estops per load")
        print(describe(IDLE))
        print(holds)
        polling = floor_halting_and_polling(floor, ctx, rng)
        if IDLE == "halt":
            polling.close()
        status = control.status()
        url, web_url = status["metrics_url"], status["web_url"]
        where = {"url": url, "web_url": web_url, "tcp": tcp, "edits": ctx.Value("q", 0)}
        loads = [(n, b, k, {**kw, **{a: where[a] for a in NEEDS.get(b, ())}}) for n, b, k, kw in LOADS]  # type: ignore[call-overload]
        tcp_token = tcp_token_path(sock).read_text().strip()
        web_token = web_token_path(sock).read_text().strip()
        feed = PanelFeed(web_url, web_token)
        if pg is not None:
            loads.append(("shipper catching up a backlog", None, 0, {}))
        loads = [x for x in loads if not ONLY or x[0] == "idle" or any(w in x[0] for w in ONLY)]
        # Idle again at the end: the machine's own drift over the run shows, and the reference
        # p99 (pooled over both idle windows, 2x the strokes) is less at the mercy of a few.
        loads.append((IDLE_AGAIN, load_stats, 0, {}))
        for name, body, procs, kw in loads:
            stop = ctx.Event()
            workers = [ctx.Process(target=body, args=(str(sock), stop), kwargs=kw) for _ in range(procs)]
            for w in workers:
                w.start()
            shipped: Callable[[], int] | None = None
            if body is None and pg is not None:
                name, shipped = shipper_catches_up(control, pg[0])
            time.sleep(1.0)  # the load builds up
            edits = kw.get("edits")  # the queue load's count of answered calls
            first = control.status()["cycle"]
            before = shipped() if shipped else 0
            edits_before = edits.value if edits is not None else 0
            time.sleep(WINDOW_S)
            last = control.status()["cycle"] - 1
            if shipped is not None:
                name = f"{name} ({shipped() - before} shipped)"
            if edits is not None:  # what the window's edits were, and that the queue held its 100
                queued = len(control.status()["queue"]["queued"])
                name = f"{name} ({edits.value - edits_before} edits, {queued} queued)"
            rss = (rss_mb(proc.pid), rss_mb(server_pid(proc.pid) or proc.pid))
            lat = lateness_between(db, first, last)
            # The estops are sent from a process above the loads (SCHED_FIFO below the loop, when
            # allowed): on 2 cores, CPU-bound loads kept this measuring process itself from running
            # for 10-30 ms, and that was counted as the daemon's. The daemon's side is as it is.
            raised = _raise_observer()
            if raised:
                feed.set_fifo(True)
            stolen = steal_ms()
            stops = []
            for _ in range(ESTOPS):
                time.sleep(rng.uniform(0.005, 0.035))  # as the paths' estops below
                stops.append(estopper.estop())
                estopper.resume()
            by_path = {}
            for path_name in PATHS:
                took = []
                for _ in range(PATH_ESTOPS):
                    # Anywhere in the first two strokes after the restart (15 ms a period): the
                    # estop meets the loop at every phase, 5x the estops in the time of 20 s apart.
                    time.sleep(rng.uniform(0.005, 0.035))
                    try:
                        took.append(estop_by(path_name, sock, tcp, tcp_token, web_url, web_token, feed))
                    except (OSError, RpcError, RuntimeError) as exc:
                        print(f"  {name}: estop by {path_name} failed: {exc}")
                        took.append(float("inf"))
                    estopper.resume()
                by_path[path_name] = took
            by_path[FLOOR] = floor.sample(PATH_ESTOPS, rng)
            path_rows.append((name, by_path, steal_ms() - stolen))
            if raised:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
                feed.set_fifo(False)
            stop.set()
            for w in workers:
                w.join(10)
                if w.is_alive():
                    w.kill()
            if shipped is not None and pg is not None:
                # The database is this window's load, not the idle one's after it: some 230,000
                # rows just inserted, its autovacuum would come within its minute's nap.
                print(f"  {name}: then {database_after(pg[0])}; stopped before the idle window")
                pg[0].stop()
            if body is load_stats and not procs:
                idle_lat += lat
            p50, p99, _, mx = percentiles(lat)
            e50, e99, _, emx = percentiles([round(s * 1000) for s in stops])
            rows.append(
                (name, len(lat), p50 / 1e3, p99 / 1e3, mx / 1e3, e50 / 1e3, e99 / 1e3, emx / 1e3, *rss)
            )
            time.sleep(2.5)  # connections the load left die on their timeouts
        term_loaded = sigterm_under_load(proc, str(sock), ctx)
    finally:
        floor.close()
        if polling is not None:
            polling.close()
        if feed is not None:
            feed.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.communicate(timeout=30)
        if pg is not None:
            pg[0].close()
    idle_p99 = percentiles(idle_lat)[1] / 1e3
    print(f"idle reference: late p99 {idle_p99:.1f} us over both idle windows ({len(idle_lat)} strokes)")
    print_table(
        ["load", "strokes", "late p50 us", "late p99 us", "late max us", "x idle p99",
         "estop p50 ms", "estop p99 ms", "estop max ms", "daemon MB", "server MB"],
        [
            (n, k, f"{a:.1f}", f"{b:.1f}", f"{c:.0f}", f"{b / max(idle_p99, 1.0):.2f}",
             f"{d:.2f}", f"{e:.2f}", f"{f:.2f}", f"{g:.0f}", f"{h:.0f}")
            for n, k, a, b, c, d, e, f, g, h in rows
        ],
        title="start lateness from the records, and estop request -> drive-off reply, per load",
    )  # fmt: skip
    # Each path's estop as a client makes it (connect, auth over TCP, the request, the reply once
    # the drive is off; the panel's feed kept open, as the page holds it), under each load, and
    # the machine's floor in the same window.
    print_table(
        ["load", *(f"{p} p50 / p99 / max ms" for p in (*PATHS, FLOOR)), "vCPU steal ms"],
        [
            (
                name,
                *("{:.2f} / {:.2f} / {:.2f}".format(*path_figures(by_path[p])) for p in (*PATHS, FLOOR)),
                f"{stolen:.0f}",
            )
            for name, by_path, stolen in path_rows
        ],
        title=f"estop by each path ({PATH_ESTOPS} per path per load), the machine's floor, and the time"
        " the hypervisor held its vCPUs while they were measured",
    )
    over = [(name, p) for name, by_path, _ in path_rows for p in PATHS if path_figures(by_path[p])[1] > 5.0]
    floors = sorted(path_figures(by_path[FLOOR])[1] for _, by_path, _ in path_rows)
    print(
        f"path-windows over 5 ms: {len(over)} of {len(path_rows) * len(PATHS)}; the floor's own p99"
        f" over the {len(floors)} windows: {floors[0]:.2f} to {floors[-1]:.2f} ms,"
        f" median {floors[len(floors) // 2]:.2f}"
    )
    checks = [(f"estop p99 <= 5 ms: {r[0]}", r[6] <= 5.0) for r in rows]
    checks += [
        (f"estop p99 <= 5 ms by {p}: {name}", path_figures(by_path[p])[1] <= 5.0)
        for name, by_path, _ in path_rows
        for p in PATHS
    ]
    checks += [
        (f"late p99 <= 1.2x idle: {r[0]}", r[3] <= 1.2 * max(idle_p99, 1.0))
        for r in rows
        if r[0] not in ("idle", IDLE_AGAIN)
    ]
    term = sigterm_exit_ms()
    print(f"SIGTERM -> exit with a 5 s target, ms: {' '.join(f'{x:.0f}' for x in term)}")
    print(f"SIGTERM -> exit while cycling under {HEAVY_LOAD}: {term_loaded:.0f} ms")
    for line in log_path.read_text(errors="replace").splitlines():
        if '"exiting"' in line:  # the daemon's own account of that stop, when past its budget
            print(f"  the daemon's account: {json.loads(line)['took']}")
    checks.append(("SIGTERM exits within 100 ms (worst of 5)", max(term) <= 100.0))
    checks.append((f"SIGTERM exits within 100 ms under {HEAVY_LOAD}", term_loaded <= 100.0))
    for label, ok in checks:
        print(f"  {'ok  ' if ok else 'MISS'} {label}")
    return 0 if all(ok for _, ok in checks) else 1
