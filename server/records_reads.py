"""The socket's records reads (`history`, `runs`, a past run's `stats`, `export`), answered by
processes of their own (`python -m usmswitch.server.records_reads`), spawned by the server process.

Why processes: in threads of the server process, a reader's Python (a record to a dict, packing)
held the GIL against the event loop, and an estop by the main socket, TCP or the panel waited for
it at each of its steps (p99 12-30 ms under the abuse bench's read loads, `make bench
BENCH=abuse`). A reader process shares nothing with the event loop but its socket; it runs at
SCHED_OTHER, below everything real-time.

`RecordsReaders` is the server process's side: two lanes (small reads: a few hundred records and the
runs list, never queued behind an export; the rest, `Limits.max_reads` at once), each a queue and
its worker processes, started at their lane's first read. A read whose client has gone before its
turn is dropped unread; every read is one bounded piece of work (at most 10,000 records, an export a
chunk a call), so none runs long after its client left. A worker that dies fails its read with
INTERNAL and is started again at the next.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import logging
import os
import pkgutil
import select
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import msgpack

from usmswitch.protocol.wire import ErrorCode, RpcError, packb

log = logging.getLogger("usmswitch.rpc")

HISTORY_CHUNK = 200
#: A reply's head, from a reader process: its job's number, 0 or the RpcError's code (its body is
#: then the error's message, UTF-8), the body's length; the body follows as it is. The server hands
#: a reply's body on in the pieces it arrived in, never unpacked or joined: a history [10000]
#: (3.5 MB) taken from a msgpack stream and spliced into the client's frame cost the event loop
#: 6-13 ms in one step (the unpacker's copies and the splice's), and an accept, a TCP estop's among
#: them, waited behind it (the loop ran 5-10 ms at a stretch under 10 export clients, perf sched).
REPLY_HEAD = struct.Struct(">QqQ")
SMALL_READ = 1000  # history reads up to this many records take the small reads' lane
#: Methods answered from the records file, by a reader process.
READS = frozenset({"history", "runs", "stats", "export"})


# -- the reader process ----------------------------------------------------------------------------


def _known_run(store: Any, method: str, run_id: int) -> Any:
    run = store.run(run_id)
    if run is None:
        last = store.last_run_id()
        have = f"runs are 1..{last}" if last else "no run has been recorded yet"
        raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: no run {run_id} ({have})")
    return run


def history_reply(store: Any, n: int, run_id: int | None = None) -> bytes:
    """The last `n` records (of one run) packed as a msgpack array."""
    if run_id is not None:
        _known_run(store, "history", run_id)
    records = store.history(n, run_id=run_id)
    packer = msgpack.Packer(use_bin_type=True, autoreset=True)
    parts = [packer.pack_array_header(len(records))]
    parts += [packer.pack(r.to_dict()) for r in records]
    return b"".join(parts)


def runs_reply(store: Any, n: int, label: str | None = None) -> bytes:
    """The last `n` runs (with that label), oldest first, packed."""
    return packb([r.to_dict() for r in store.runs(n, label=label or None)])


def stats_reply(
    store: Any, run_id: int | None, first_cycle: int | None, last_cycle: int | None, label: str | None = None
) -> bytes:
    """Statistics of a past run, a range of cycles or a label's runs (pooled and per run), from the
    records file, packed."""
    from usmswitch.protocol.stats import stats_of_records

    if label:
        if run_id is not None or first_cycle is not None or last_cycle is not None:
            raise RpcError(ErrorCode.INVALID_PARAMS, "stats: a label's runs, or a run or cycles, not both")
        return packb(store.label_stats(label))
    run = None if run_id is None else _known_run(store, "stats", run_id)
    if first_cycle is not None and last_cycle is not None and last_cycle < first_cycle:
        raise RpcError(
            ErrorCode.INVALID_PARAMS, f"stats: last_cycle {last_cycle} is before first_cycle {first_cycle}"
        )
    if run is not None and first_cycle is None and last_cycle is None:
        # A run's statistics as kept while its strokes were written: the same cost at 10^7 strokes
        # as at 10 (issue 36). A run without them yet (a file being migrated) is scanned.
        kept = store.run_stats(run.run_id)
        if kept is not None:
            return packb(kept)
    return packb(stats_of_records(store.iter_records(first_cycle or 1, last_cycle, run_id=run_id), run))


def export_reply(
    store: Any,
    run_id: int | None,
    first_cycle: int,
    last_cycle: int | None,
    max_strokes: int,
    label: str | None = None,
) -> bytes:
    """One chunk of an export: the CSV lines (no header) of up to `max_strokes` strokes from
    `first_cycle` on (to `last_cycle`, of one run, of a label's runs), each chunk's text built by
    SQLite in one statement (issue 36: within 2x `sqlite3 -csv`); the client asks for the next chunk from
    `last_cycle` + 1. A chunk a call: the export's memory is one chunk, a client that has gone asks
    for no more, and the lane's other reads take their turns between chunks."""
    if run_id is not None:
        run = _known_run(store, "export", run_id)
        # A run's strokes lie within its cycles: read from there, not through the runs before it.
        first_cycle = max(first_cycle, run.first_cycle or 1)
    chunks = store.csv_chunks(first_cycle, last_cycle, run_id=run_id, chunk=max_strokes, label=label or None)
    for strokes, last, text in chunks:
        return packb({"strokes": strokes, "last_cycle": last, "csv": text})
    return packb({"strokes": 0, "last_cycle": None, "csv": ""})


_REPLIES: dict[str, Callable[..., bytes]] = {
    "history": history_reply,
    "runs": runs_reply,
    "stats": stats_reply,
    "export": export_reply,
}


def answer(store: Any, method: str, params: list[Any]) -> list[Any]:
    """[error or None, packed result]: one read, as the reader process sends it back."""
    try:
        return [None, _REPLIES[method](store, *params)]
    except RpcError as exc:
        return [[exc.code, exc.message], b""]
    except (OSError, ValueError) as exc:  # a file gone or unreadable, a cell not what it should be
        return [[ErrorCode.UNAVAILABLE, f"{method}: {exc}"], b""]
    except Exception as exc:  # a bug: the client is told, the reader reads on
        return [[ErrorCode.INTERNAL, f"{method}: {type(exc).__name__}: {exc}"], b""]


def worker(sock: socket.socket, records_path: str, open_records: Callable[[str], Any]) -> None:
    """Answer [job, method, params] requests on `sock` until it closes (the server has gone)."""
    unpacker = msgpack.Unpacker(raw=False)
    store = None
    while data := sock.recv(1 << 16):
        unpacker.feed(data)
        for job, method, params in unpacker:
            if store is None:
                try:
                    store = open_records(records_path)
                except OSError as exc:
                    _send_reply(sock, job, [ErrorCode.UNAVAILABLE, f"{method}: {exc}"], b"")
                    continue
            error, body = answer(store, method, params)
            store.release()  # idle, no file open: the daemon's last close removes -wal and -shm
            _send_reply(sock, job, error, body)


def _send_reply(sock: socket.socket, job: int, error: list[Any] | None, body: bytes) -> None:
    """One reply, framed by REPLY_HEAD."""
    if error is not None:
        body = str(error[1]).encode()
    sock.sendall(REPLY_HEAD.pack(job, 0 if error is None else int(error[0]), len(body)))
    sock.sendall(body)


def _die_with_the_server(fd: int) -> None:
    """End this process the moment the server's end of the socket closes, mid-read too: a scan of
    10^5 strokes went on for 10 s after its server had gone (holding the daemon's stderr open)."""
    watch = select.poll()
    watch.register(fd, select.POLLRDHUP)
    watch.poll()  # only a hang-up or an error wakes it
    os._exit(0)


def main(argv: list[str] | None = None) -> int:
    """Entry of a reader process (not a command for people)."""
    from usmswitch.runtime.realtime import drop_realtime

    drop_realtime()  # spawned by a thread on SCHED_OTHER already; a refusal changes nothing here
    parser = argparse.ArgumentParser(prog="usmswitch.server.records_reads")
    parser.add_argument("--fd", type=int, required=True, help="the socket to the server process")
    parser.add_argument("--records", required=True, help="the records file")
    parser.add_argument("--reader", required=True, help="package.module:function opening it read-only")
    args = parser.parse_args(argv)
    sock = socket.socket(fileno=args.fd)
    sock.setblocking(True)
    threading.Thread(target=_die_with_the_server, args=(sock.fileno(),), daemon=True).start()
    with contextlib.suppress(BrokenPipeError, ConnectionResetError, KeyboardInterrupt):
        worker(sock, args.records, pkgutil.resolve_name(args.reader))
    return 0


# -- the server process's side ---------------------------------------------------------------------


class _Job:
    __slots__ = ("future", "gone", "method", "params", "tries")

    def __init__(
        self, method: str, params: list[Any], future: asyncio.Future[list[bytes]], gone: Callable[[], bool]
    ) -> None:
        self.method = method
        self.params = params
        self.future = future
        self.gone = gone
        self.tries = 0


def _spawn(records_path: str, reader: str) -> tuple[socket.socket, subprocess.Popen[bytes]]:
    """A reader process on a socketpair, forked from a thread on SCHED_OTHER: a child of the
    real-time event loop would run its start-up (~0.3 s of imports) above ordinary work."""
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    out: list[Any] = []

    def run() -> None:
        from usmswitch.runtime.realtime import drop_realtime

        drop_realtime()
        try:
            cmd = [sys.executable, "-m", "usmswitch.server.records_reads", "--fd", str(theirs.fileno())]
            cmd += ["--records", records_path, "--reader", reader]
            out.append(subprocess.Popen(cmd, pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL))
        except OSError as exc:
            out.append(exc)

    thread = threading.Thread(target=run, name="rpc-read-spawn")
    thread.start()
    thread.join()
    theirs.close()
    if isinstance(out[0], OSError):
        ours.close()
        raise out[0]
    return ours, out[0]


class _Worker(asyncio.Protocol):
    """One reader process, as the event loop sees it: one read at a time."""

    def __init__(self, lane: _Lane, proc: subprocess.Popen[bytes]) -> None:
        self.lane = lane
        self.proc = proc
        self.transport: asyncio.Transport | None = None
        self.job: _Job | None = None
        self.jobs = 0
        self.head = b""  # a reply's head (REPLY_HEAD), as far as it has come
        self.code = 0
        self.need = 0  # the body's bytes still to come
        self.body: list[bytes] | None = None  # its pieces so far, once its head is whole

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def send(self, job: _Job) -> None:
        assert self.transport is not None
        self.job = job
        job.tries += 1
        self.jobs += 1
        self.transport.write(packb([self.jobs, job.method, job.params]))

    def data_received(self, data: bytes) -> None:
        while data:
            if self.body is None:
                short = REPLY_HEAD.size - len(self.head)
                self.head += data[:short]
                data = data[short:]
                if len(self.head) < REPLY_HEAD.size:
                    return
                _job, self.code, self.need = REPLY_HEAD.unpack(self.head)
                self.head, self.body = b"", []
            if len(data) > self.need:
                piece, data = data[: self.need], data[self.need :]
            else:
                piece, data = data, b""
            if piece:
                self.body.append(piece)
                self.need -= len(piece)
            if not self.need:
                self._answered(self.body)

    def _answered(self, body: list[bytes]) -> None:
        self.body = None
        job, self.job = self.job, None
        if job is not None and not job.future.done():
            if not self.code:
                job.future.set_result(body)
            else:
                job.future.set_exception(RpcError(self.code, b"".join(body).decode()))
        self.lane.next(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.lane.lost(self)


class _Lane:
    """A queue of reads and up to `size` reader processes taking them in turn."""

    def __init__(self, readers: RecordsReaders, name: str, size: int) -> None:
        self.readers = readers
        self.name = name
        self.size = size
        self.queue: collections.deque[_Job] = collections.deque()
        self.idle: list[_Worker] = []
        self.workers: set[_Worker] = set()
        self.starting = 0

    def submit(self, job: _Job) -> None:
        self.queue.append(job)
        self._dispatch()
        self._grow()

    def _grow(self) -> None:
        """A reader process more while reads wait and the lane has room (started at first need)."""
        if self.queue and len(self.workers) + self.starting < self.size:
            self.starting += 1
            self.readers.loop.create_task(self._start())

    async def _start(self) -> None:
        loop = self.readers.loop
        try:
            sock, proc = await loop.run_in_executor(None, _spawn, self.readers.path, self.readers.reader)
            sock.setblocking(False)
            _, w = await loop.connect_accepted_socket(lambda: _Worker(self, proc), sock=sock)
        except OSError as exc:
            log.error("rpc: a records reader process could not be started: %s", exc)
            while self.queue and not self.workers:  # nobody else to read them
                self._fail(self.queue.popleft(), f"the records reader could not be started: {exc}")
            return
        finally:
            self.starting -= 1
        self.workers.add(w)
        if self.readers.closed:
            w.transport.close()  # type: ignore[union-attr]
            return
        self.next(w)

    def next(self, w: _Worker) -> None:
        """`w` is free: give it the next read whose client is still there."""
        self.idle.append(w)
        self._dispatch()

    def _dispatch(self) -> None:
        while self.idle and self.queue:
            job = self.queue.popleft()
            if job.future.done() or job.gone():
                job.future.cancel()  # its client left while it waited: no read for nobody
                continue
            self.idle.pop().send(job)

    def lost(self, w: _Worker) -> None:
        self.workers.discard(w)
        if w in self.idle:
            self.idle.remove(w)
        code = w.proc.poll()
        if w.job is not None and w.job.tries < 2:
            self.queue.appendleft(w.job)  # a read is idempotent: once more, on another reader
        elif w.job is not None:
            self._fail(w.job, f"the records reader process ended (exit {code}), twice on this read")
        if not self.readers.closed:
            log.error("rpc: a %s records reader process ended (exit %s); another starts", self.name, code)
            self._grow()

    def _fail(self, job: _Job, why: str) -> None:
        if not job.future.done():
            job.future.set_exception(RpcError(ErrorCode.INTERNAL, f"{job.method}: {why}"))

    def close(self) -> None:
        for w in self.workers:
            if w.transport is not None:
                w.transport.close()
        for job in self.queue:
            job.future.cancel()
        self.queue.clear()


class RecordsReaders:
    """The server process's records reads: `read()` returns a future of the packed reply."""

    def __init__(self, loop: asyncio.AbstractEventLoop, path: str, reader: str, max_reads: int) -> None:
        self.loop = loop
        self.path = path
        self.reader = reader
        self.closed = False
        # A lane of its own for small reads (a few hundred records, the runs list): never queued
        # behind CSV exports or history [10000] floods (a history [5] took 8-30 s behind 4 exports).
        self.small = _Lane(self, "small", 1)
        self.big = _Lane(self, "large", max_reads)

    def read(
        self, method: str, params: list[Any], gone: Callable[[], bool] = lambda: False
    ) -> asyncio.Future[list[bytes]]:
        """Queue one read on its lane (called on the event loop's thread); its future's result is
        the packed reply in the pieces it arrived in (REPLY_HEAD)."""
        small = method == "runs" or (method == "history" and params[0] <= SMALL_READ)
        future: asyncio.Future[list[bytes]] = self.loop.create_future()
        (self.small if small else self.big).submit(_Job(method, params, future, gone))
        return future

    def close(self, wait_s: float = 1.0) -> None:
        """End the readers and wait for them (up to `wait_s` in all), so that the daemon's last
        close of the records file is the last: a reader still holding it open kept its -wal and
        -shm. Terminated (a read-only reader has nothing to save), since a transport's close takes
        effect only at the event loop's next step, which the shutdown does not wait for."""
        self.closed = True
        procs = [w.proc for lane in (self.small, self.big) for w in lane.workers]
        self.small.close()
        self.big.close()
        for proc in procs:
            with contextlib.suppress(OSError):
                proc.terminate()
        deadline = time.monotonic() + wait_s
        for proc in procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(max(0.0, deadline - time.monotonic()))


if __name__ == "__main__":
    sys.exit(main())
