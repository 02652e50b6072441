"""The daemon's side of the msgpack-RPC socket: binds, spawns the server process, runs the handlers.

Architecture (docs/protocol.md, "Architecture"): the sockets are served by a separate server process
(`python -m usmswitch.server.rpc_process`), never by a thread of the control loop's process, because any
CPU-bound Python in the loop's process holds the GIL for up to the switch interval (5 ms) and lands
directly in the loop's start lateness. The daemon binds the listening sockets itself (so bind and
permission errors surface in `RpcServer.start`) and hands their descriptors to the child with a
socketpair "channel". Over the channel the daemon sends pre-packed snapshots (`stats`, ...) that the
child answers from without waking the daemon, pre-packed notifications it fans out to subscribers, and
the results of forwarded calls; the child sends only validated, bounded calls back. In the daemon,
`publish` and `snapshot` are O(1) appends; one writer thread packs and sends, one bridge thread reads
calls and runs the handlers, one at a time.
"""

from __future__ import annotations

import contextlib
import errno
import grp
import logging
import os
import queue
import socket
import stat
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import msgpack

from usmswitch.protocol.wire import (
    BUILTIN_METHODS,
    SERVER_TOPICS,
    ErrorCode,
    Limits,
    RpcError,
    note_frame,
    packb,
)
from usmswitch.runtime.children import end_child
from usmswitch.runtime.realtime import name_thread, renice_child, server_fifo
from usmswitch.server.after_reply import run_afters, split
from usmswitch.server.busy_poll import DEFAULT_WINDOW_NS
from usmswitch.server.estop_socket import THREAD_NAME as ESTOP_THREAD
from usmswitch.server.hub import TCP_BACKLOG, URGENT_BACKLOG
from usmswitch.web.budgets import HTTP_BACKLOG

from .rpc_process import serve

log = logging.getLogger("usmswitch.rpc")

#: How long stop() lets the server process close its clients before it is killed. An idle one
#: exits in ~5 ms; one starved of CPU by busy clients may take 100 ms and more.
#: The longest path a Unix socket binds to on Linux (sun_path: 108 bytes with its NUL).
MAX_UNIX_PATH = 107
STOP_GRACE_S = 0.01


# -- the daemon side -------------------------------------------------------------------------------


#: The daemon's threads an estop passes through (the urgent channel's, the estop socket's): they run
#: SCHED_FIFO above the daemon's other helpers, so a record writer's or bridge's burst at the same
#: priority never holds an estop back (FIFO threads of one priority wait for each other).
URGENT_THREADS = ("rpc-urgent", ESTOP_THREAD)


class SocketBusyError(RuntimeError):
    """The socket's path is served by another server (a second daemon): the message says how to
    give this one its own."""


@dataclass(slots=True)
class _Link:
    """One running server process (or thread) and the daemon's end of its channel."""

    gen: int
    sock: socket.socket
    urgent: socket.socket  # estop and the like: served by a thread of their own, behind nothing
    feed: msgpack.Unpacker
    proc: subprocess.Popen[bytes] | None
    thread: threading.Thread | None
    started_ns: int


class RpcServer:
    """The daemon's socket front: serves clients from a separate process, calls `handlers` here.

    `handlers[method](params)` runs in one bridge thread, one call at a time, with params already
    validated against docs/protocol.md (defaults filled). It returns a msgpack-able result, raises
    `RpcError`, or returns a `concurrent.futures.Future` the loop resolves later (e.g. `switch`:
    the record of the stroke). Keep handlers short: they share the GIL with the control loop.

    `urgent[method](params)` (estop) runs in a thread of its own, reached over a channel of its own:
    no other call, however many or slow, is ahead of it, and no call limit refuses it. It must
    return its result directly. `urgent_path` binds a socket that takes only these and ping, with
    its own connection limit, so a flood on the main socket cannot lock an estop out.
    `records_path` lets the server process answer `history` from the records file itself, through
    `records_reader` ("package.module:function", path -> a read-only store; OSError naming why it
    cannot be opened), which the server process imports by name: the daemon's store.
    `feeds` are snapshots the server process keeps for itself, never answered as methods (the
    metrics page's figures); `metrics` (host, port) binds the TCP socket it serves that page on.
    `web` (host, port) binds the browser panel's (web/panel.py), whose controls need `web_token`
    (kept by the daemon in `web_token_file`, which the panel names when it refuses a control).
    """

    def __init__(
        self,
        handlers: Mapping[str, Callable[[list[Any]], object]],
        *,
        unix_path: str | os.PathLike[str],
        urgent: Mapping[str, Callable[[list[Any]], object]] | None = None,
        urgent_path: str | os.PathLike[str] | None = None,
        records_path: str | os.PathLike[str] | None = None,
        records_reader: str | None = None,
        mode: int = 0o660,
        group: str | int | None = None,
        tcp: tuple[str, int] | None = None,
        tcp_token: str | None = None,
        limits: Limits | None = None,
        topics: Iterable[str] = ("stroke", "state"),
        snapshot_methods: Iterable[str] = (),
        snapshot_finishers: Mapping[str, str] | None = None,
        feeds: Iterable[str] = (),
        metrics: tuple[str, int] | None = None,
        web: tuple[str, int] | None = None,
        web_token: str | None = None,
        web_token_file: str | os.PathLike[str] | None = None,
        web_allowed_hosts: Iterable[str] = (),
        isolation: str = "process",
        nice: int = 5,
        busy_poll_ns: int = DEFAULT_WINDOW_NS,
        max_restarts: int = 5,
        log_format: str = "auto",
        log_level: str = "info",
    ) -> None:
        urgent = dict(urgent or {})
        for name, handler in [*handlers.items(), *urgent.items()]:
            if type(name) is not str or not callable(handler):
                raise ValueError(f"handlers must map method names to callables, got {name!r}: {handler!r}")
            if name in BUILTIN_METHODS:
                raise ValueError(f"handler {name!r} clashes with a method the server answers itself")
        if set(urgent) & set(handlers):
            raise ValueError(f"methods {sorted(set(urgent) & set(handlers))} are both urgent and not")
        if urgent_path is not None and not urgent:
            raise ValueError("urgent_path needs urgent handlers to serve")
        if isinstance(mode, bool) or not isinstance(mode, int) or not 0 <= mode <= 0o777:
            raise ValueError(f"mode must be permission bits in [0, 0o777], got {mode!r}")
        if tcp is not None:
            if not (
                isinstance(tcp, tuple) and len(tcp) == 2 and isinstance(tcp[0], str) and type(tcp[1]) is int
            ):
                raise ValueError(f"tcp must be (host, port), got {tcp!r}")
            if not 0 <= tcp[1] <= 65_535:
                raise ValueError(f"tcp port must be in [0, 65535], got {tcp[1]!r}")
            if not isinstance(tcp_token, str) or len(tcp_token) < 16:
                raise ValueError("tcp_token must be a string of at least 16 characters when tcp is set")
        if isolation not in ("process", "thread"):
            raise ValueError(f"isolation must be 'process' or 'thread', got {isolation!r}")
        if isinstance(nice, bool) or not isinstance(nice, int) or not 0 <= nice <= 19:
            raise ValueError(f"nice must be an integer in [0, 19], got {nice!r}")
        if isinstance(busy_poll_ns, bool) or not isinstance(busy_poll_ns, int) or busy_poll_ns < 0:
            raise ValueError(f"busy_poll_ns must be an integer >= 0 (0: off), got {busy_poll_ns!r}")
        self.topics = tuple(topics)
        for topic in self.topics:
            if type(topic) is not str or topic in SERVER_TOPICS:
                raise ValueError(f"topic {topic!r} is not a name the daemon may publish")
        self.handlers = dict(handlers)
        self.urgent = urgent
        self.snapshot_methods = frozenset(snapshot_methods)
        self.feeds = frozenset(feeds)
        if self.feeds & (self.snapshot_methods | set(self.handlers) | set(urgent)):
            raise ValueError(f"feeds {sorted(self.feeds)} must not be method names")
        if metrics is not None and not self.feeds:
            raise ValueError("metrics needs the feeds its page is made from")
        self.metrics = metrics
        if web is not None and (not isinstance(web_token, str) or len(web_token) < 16):
            raise ValueError("web_token must be a string of at least 16 characters when web is set")
        self.web = web
        self.web_token = web_token
        self.web_token_file = None if web_token_file is None else str(web_token_file)
        self.web_allowed_hosts = [str(h) for h in web_allowed_hosts]
        #: Where the panel listens once started (the port resolved when 0 was asked).
        self.web_address: tuple[str, int] | None = None
        #: Where the metrics page listens once started (the port resolved when 0 was asked).
        self.metrics_address: tuple[str, int] | None = None
        #: method -> "module:function" the server process applies to that snapshot before serving it.
        self.snapshot_finishers = dict(snapshot_finishers or {})
        if set(self.snapshot_finishers) - self.snapshot_methods:
            raise ValueError("snapshot_finishers must name snapshot methods")
        self.unix_path = Path(unix_path)
        self.urgent_path = None if urgent_path is None else Path(urgent_path)
        self.records_path = None if records_path is None else Path(records_path)
        if records_path is not None and (not isinstance(records_reader, str) or ":" not in records_reader):
            raise ValueError(
                f"records_path needs records_reader 'package.module:function', got {records_reader!r}"
            )
        self.records_reader = records_reader
        self.mode = mode
        self.gid = _resolve_group(group)
        self.tcp = tcp
        self.tcp_token = tcp_token
        self.limits = limits or Limits()
        self.isolation = isolation
        self.nice = nice
        #: The server process's event loop at SCHED_FIFO this priority (0: SCHED_OTHER); see
        #: raise_priority.
        self.fifo_priority = 0
        #: SCHED_FIFO for an urgent channel's thread started after a restart (0: as its starter).
        self.urgent_priority = 0
        self.busy_poll_ns = busy_poll_ns
        self.log_settings = (log_format, log_level)
        self.max_restarts = max_restarts
        #: Where TCP listens once started (the port resolved when 0 was asked).
        self.tcp_address: tuple[str, int] | None = None
        #: Called by the bridge and writer threads before each piece of work: the daemon makes it
        #: wait while the loop is about to start a stroke (they share the GIL). Urgent calls never wait.
        self.gate: Callable[[], object] = lambda: None
        #: Counters for status and logs.
        self.published = 0
        self.lost = 0  # notifications dropped because the backlog to the server process was full
        self.restarts = 0
        self._listeners: list[tuple[socket.socket, str]] = []
        #: The bound estop socket (None without urgent_path): the daemon serves it itself.
        self.urgent_listener: socket.socket | None = None
        #: Stopped, in order, before the sockets close (the estop socket's server).
        self.companions: list[Any] = []
        self._unix_inos: dict[Path, int] = {}
        self._out: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self._snaps: dict[str, object] = {}
        self._snap_pending: set[str] = set()
        self._link: _Link | None = None
        self._gen = 0
        self._stopping = False
        self._started = False
        # One longer than the limit, so that "more than max_restarts in a minute" can be seen.
        self._restart_times: deque[int] = deque(maxlen=max_restarts + 1)
        self._threads: list[threading.Thread] = []

    # -- public API, called by the daemon --------------------------------------------------------
    def start(self) -> None:
        """Bind the sockets (errors name the path or address), start the server process, serve."""
        if self._started:
            raise RuntimeError("RpcServer already started")
        self._started = True
        try:
            self._listeners.append((self._bind_unix(self.unix_path, self.limits.unix_backlog), "unix"))
            if self.urgent_path is not None:
                # Bound here (mode, group, stale-socket checks as the main one); served in this
                # process by server/estop_socket.py, which the daemon starts on it.
                self.urgent_listener = self._bind_unix(self.urgent_path, URGENT_BACKLOG)
            if self.tcp is not None:
                tsock = socket.create_server(self.tcp, backlog=TCP_BACKLOG)
                self.tcp_address = tsock.getsockname()[:2]
                self._listeners.append((tsock, "tcp"))
            if self.metrics is not None:
                msock = _bind_tcp(self.metrics, "metrics page")
                self.metrics_address = msock.getsockname()[:2]
                self._listeners.append((msock, "metrics"))
            if self.web is not None:
                wsock = _bind_tcp(self.web, "browser panel")
                self.web_address = wsock.getsockname()[:2]
                self._listeners.append((wsock, "web"))
            self._link = self._spawn()
        except BaseException:
            self._close_listeners()
            raise
        for target, name in ((self._writer, "rpc-writer"), (self._bridge, "rpc-bridge")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def publish(self, topic: str, payload: object) -> bool:
        """Notify subscribers of `topic`; O(1), never blocks; False when dropped (backlog full).

        The server takes `payload` as is: do not mutate it afterwards.
        """
        if topic not in self.topics:
            raise ValueError(f"unknown topic {topic!r}; declared: {', '.join(self.topics)}")
        if self._out.qsize() >= self.limits.publish_backlog or self._stopping:
            self.lost += 1
            return False
        self._out.put(("note", topic, payload))
        self.published += 1
        return True

    def snapshot(self, method: str, result: object) -> None:
        """Set what `method []` returns, answered by the server process without calling the daemon.

        O(1), never blocks; snapshots set faster than they are sent coalesce to the latest. Those
        set before `start()` are served from the first request; later ones a moment after the call.
        """
        if method not in self.snapshot_methods and method not in self.feeds:
            raise ValueError(
                f"{method!r} is not in snapshot_methods or feeds"
                f" ({', '.join(sorted(self.snapshot_methods | self.feeds))})"
            )
        self._snaps[method] = result
        if method not in self._snap_pending:
            self._snap_pending.add(method)
            self._out.put(("snap", method))

    @property
    def alive(self) -> bool:
        """True while a server process (or thread) is serving."""
        link = self._link
        if link is None:
            return False
        if link.proc is not None:
            return link.proc.poll() is None
        return link.thread is not None and link.thread.is_alive()

    @property
    def server_pid(self) -> int | None:
        """The server process's pid (None in thread isolation or before start)."""
        link = self._link
        return link.proc.pid if link is not None and link.proc is not None else None

    def lower_priority(self, nice: int) -> bool:
        """Run the server process `nice` above the daemon from now on, and after a restart: every
        thread of the running one (Linux's nice is per thread). Lowering one's own processes'
        priority is always permitted; False (and a warning) if it was refused all the same."""
        if isinstance(nice, bool) or not isinstance(nice, int) or not self.nice <= nice <= 19:
            raise ValueError(f"nice must be an integer in [{self.nice}, 19], got {nice!r}")
        self.nice = nice
        pid = self.server_pid
        cost = "the socket's clients compete with the loop for CPU at the loop's nice"
        return pid is None or renice_child(pid, nice, "server", cost)

    def raise_priority(self, priority: int) -> bool:
        """Run the server process's event loop at SCHED_FIFO `priority` from now on, and after a
        restart (0: SCHED_OTHER). Its worker threads run at SCHED_FIFO 1 under it
        (rpc_process.WORKER_PRIORITY). False (and a warning) when refused: it serves at SCHED_OTHER."""
        if isinstance(priority, bool) or not isinstance(priority, int) or not 0 <= priority <= 99:
            raise ValueError(f"priority must be an integer in [0, 99], got {priority!r}")
        self.fifo_priority = priority
        pid = self.server_pid
        if pid is None:
            return True
        # pid is the process's main thread: the event loop's (threads it starts later inherit it).
        return server_fifo(pid, priority)

    def stop(self) -> None:
        """Stop serving: close every connection, end the server process, remove the socket file."""
        if not self._started or self._stopping:
            return
        self._stopping = True
        for companion in self.companions:
            companion.stop()
        self._out.put(("stop",))
        link = self._link
        if link is not None:
            self._end_link(link)
        for thread in self._threads:
            thread.join(timeout=5)
        if link is not None:
            link.sock.close()
            link.urgent.close()
        self._close_listeners()

    def __enter__(self) -> RpcServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- sockets ---------------------------------------------------------------------------------
    def _bind_unix(self, path: Path, backlog: int) -> socket.socket:
        if path.is_symlink() or path.exists():
            if not stat.S_ISSOCK(os.lstat(path).st_mode):
                raise RuntimeError(f"{path} exists and is not a socket; refusing to replace it")
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            probe.settimeout(1.0)
            try:
                probe.connect(str(path))
            except (ConnectionRefusedError, FileNotFoundError):
                path.unlink(missing_ok=True)  # stale: left by a daemon that died
            else:
                raise SocketBusyError(
                    f"another server is listening on {path}: a second daemon needs a socket of its"
                    " own, --socket PATH (make run SOCKET=PATH)"
                )
            finally:
                probe.close()
        size = len(os.fsencode(path))
        if size > MAX_UNIX_PATH:
            # bind() says only "AF_UNIX path too long", an OSError without errno or strerror.
            raise OSError(
                errno.ENAMETOOLONG,
                f"cannot bind the RPC socket {path}: its path is {size} bytes, a Unix socket's at most"
                f" {MAX_UNIX_PATH}; choose a shorter --socket (or runtime directory)",
            )
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(str(path))
        except OSError as exc:
            sock.close()
            why = exc.strerror or str(exc)
            raise OSError(exc.errno, f"cannot bind the RPC socket {path}: {why}") from exc
        try:
            # Bound with the process umask; restricted before listen(), so no client connects earlier.
            os.chmod(path, self.mode)
            if self.gid is not None:
                os.chown(path, -1, self.gid)
            sock.listen(backlog)
        except OSError as exc:
            sock.close()
            path.unlink(missing_ok=True)
            raise OSError(exc.errno, f"cannot set up the RPC socket {path}: {exc.strerror}") from exc
        self._unix_inos[path] = os.stat(path).st_ino
        return sock

    def _close_listeners(self) -> None:
        for sock, _ in self._listeners:
            sock.close()
        self._listeners.clear()
        if self.urgent_listener is not None:
            self.urgent_listener.close()
            self.urgent_listener = None
        for path, ino in self._unix_inos.items():
            with contextlib.suppress(OSError):
                if os.stat(path).st_ino == ino:  # still ours: not replaced by a newer daemon
                    path.unlink()
        self._unix_inos.clear()

    # -- the server process ------------------------------------------------------------------------
    def _config(self) -> dict[str, Any]:
        return {
            "limits": asdict(self.limits),
            "token": self.tcp_token if self.tcp is not None else None,
            "handlers": sorted(self.handlers),
            "urgent": sorted(self.urgent),
            "records_path": None if self.records_path is None else str(self.records_path),
            "records_reader": self.records_reader,
            "snapshot_methods": sorted(self.snapshot_methods),
            "feeds": sorted(self.feeds),
            "finishers": self.snapshot_finishers,
            "topics": list(self.topics),
            "web_token": self.web_token if self.web is not None else None,
            "web_token_file": self.web_token_file,
            "web_allowed_hosts": self.web_allowed_hosts,
            # The panel's estop goes there first (server/estop_link.py).
            "estop_socket": None if self.urgent_path is None else str(self.urgent_path),
            "lost": self.lost,
            # In a thread of the daemon's process, polling would hold the GIL against the loop.
            "busy_poll_ns": self.busy_poll_ns if self.isolation == "process" else 0,
            # Snapshots set so far are served from the first request (and after a restart).
            "snaps": {method: packb(value) for method, value in list(self._snaps.items())},
        }

    def _spawn(self) -> _Link:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        u_ours, u_theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        self._gen += 1
        proc = thread = None
        try:
            if self.isolation == "process":
                cmd = [
                    sys.executable,
                    "-m",
                    "usmswitch.server.rpc_process",
                    "--channel",
                    str(theirs.fileno()),
                ]
                cmd += ["--urgent-channel", str(u_theirs.fileno())]
                for sock, kind in self._listeners:
                    cmd += ["--listen", f"{sock.fileno()}:{kind}"]
                cmd += ["--nice", str(self.nice), "--priority", str(self.fifo_priority)]
                cmd += ["--log-format", self.log_settings[0], "--log-level", self.log_settings[1]]
                fds = [theirs.fileno(), u_theirs.fileno()] + [sock.fileno() for sock, _ in self._listeners]
                proc = subprocess.Popen(cmd, pass_fds=fds, stdin=subprocess.DEVNULL)
                theirs.close()
                u_theirs.close()
            else:
                listeners = [(os.dup(sock.fileno()), kind) for sock, kind in self._listeners]
                thread = threading.Thread(
                    target=serve,
                    args=(theirs.detach(), u_theirs.detach(), listeners),
                    name="rpc-server",
                    daemon=True,
                )
                thread.start()
            cfg = packb(self._config())
            ours.sendall(len(cfg).to_bytes(4, "big") + cfg)
            link = _Link(
                self._gen,
                ours,
                u_ours,
                msgpack.Unpacker(raw=False, max_buffer_size=1 << 24),
                proc,
                thread,
                time.monotonic_ns(),
            )
            self._await_ready(link)
        except BaseException:
            ours.close()
            u_ours.close()
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
            raise
        # Snapshots set while the process started may have missed the config: send them again.
        for method in list(self._snaps):
            if method not in self._snap_pending:
                self._snap_pending.add(method)
                self._out.put(("snap", method))
        urgent = threading.Thread(target=self._serve_urgent, args=(link,), name="rpc-urgent", daemon=True)
        urgent.start()
        return link

    def _await_ready(self, link: _Link) -> None:
        link.sock.settimeout(30.0)
        try:
            while True:
                data = link.sock.recv(65_536)
                if not data:
                    code = link.proc.wait() if link.proc is not None else None
                    raise RuntimeError(f"the RPC server process exited during start-up (exit status {code})")
                link.feed.feed(data)
                for msg in link.feed:
                    if msg[0] == "ready":
                        return
        except TimeoutError as exc:
            raise RuntimeError("the RPC server process did not start within 30 s") from exc
        finally:
            link.sock.settimeout(None)

    def _end_link(self, link: _Link) -> None:
        if link.proc is not None:
            # The process holds nothing to save: a grace for it to close its clients cleanly,
            # then SIGKILL, so a server starved by busy clients never delays the daemon's exit.
            end_child(link.proc, STOP_GRACE_S)
        elif link.thread is not None:
            link.thread.join(timeout=5)
        with contextlib.suppress(OSError):
            link.sock.shutdown(socket.SHUT_RDWR)

    def _respawn(self, old: _Link) -> _Link | None:
        """Replace a server process that died; give up after too many deaths in a minute."""
        if old.proc is not None:
            old.proc.wait()
        old.sock.close()
        old.urgent.close()
        now = time.monotonic_ns()
        self._restart_times.append(now)
        recent = [t for t in self._restart_times if now - t < 60_000_000_000]
        if len(recent) > self.max_restarts:
            log.error("rpc: server process died %d times in a minute; no longer serving", len(recent))
            return None
        log.warning(
            "rpc: server process died (exit %s); restarting", old.proc.returncode if old.proc else "-"
        )
        self.restarts += 1
        try:
            return self._spawn()
        except (OSError, RuntimeError):
            log.exception("rpc: cannot restart the server process")
            return None

    # -- daemon-side threads -----------------------------------------------------------------------
    def _writer(self) -> None:
        """The only writer of the channel: packs here, so publish() costs the loop one append."""
        out = self._out
        while True:
            item = out.get()
            self.gate()
            kind = item[0]
            link = self._link
            try:
                if kind == "note":
                    data = packb(["note", item[1], note_frame(item[1], item[2]), self.lost])
                elif kind == "snap":
                    self._snap_pending.discard(item[1])
                    data = packb(["snap", item[1], packb(self._snaps[item[1]])])
                elif kind == "resp":
                    _, gen, fid, error, result = item
                    if link is None or gen != link.gen:
                        continue  # the process that asked is gone
                    try:
                        data = packb(["resp", fid, error, packb(result)])
                    except (TypeError, ValueError, OverflowError) as exc:
                        data = packb(
                            ["resp", fid, [int(ErrorCode.INTERNAL), f"result not msgpack-able: {exc}"], None]
                        )
                elif kind == "stop":
                    if link is not None:
                        with contextlib.suppress(OSError):
                            link.sock.sendall(packb(["stop"]))
                    return
                else:
                    continue
            except (TypeError, ValueError, OverflowError) as exc:
                log.error("rpc: cannot pack %s %r: %s", kind, item[1], exc)
                continue
            if link is None:
                continue
            try:
                link.sock.sendall(data)
            except OSError:
                if kind == "note":
                    self.lost += 1

    def _bridge(self) -> None:
        """Read calls from the server process and run the handlers; respawn it if it dies."""
        while not self._stopping:
            link = self._link
            if link is None:
                return
            try:
                data = link.sock.recv(262_144)
            except OSError:
                data = b""
            if not data:
                if self._stopping:
                    return
                self._link = self._respawn(link)
                continue
            link.feed.feed(data)
            for msg in link.feed:
                if msg[0] == "call":
                    self.gate()
                    self._call(link.gen, msg[1], msg[2], msg[3])

    def _serve_urgent(self, link: _Link) -> None:
        """One link's urgent calls, each answered from this thread as soon as it is done."""
        name_thread("rpc-urgent")
        if self.urgent_priority:
            # Started by a helper thread (a restart): lifted above it, as at the daemon's start.
            with contextlib.suppress(OSError):  # refused: it runs at its starter's priority
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.urgent_priority))
        feed = msgpack.Unpacker(raw=False, max_buffer_size=1 << 20)
        packer = msgpack.Packer(use_bin_type=True, autoreset=True)
        while True:
            try:
                data = link.urgent.recv(65_536)
            except OSError:
                return
            if not data:
                return
            feed.feed(data)
            for msg in feed:
                if msg[0] != "call":
                    continue
                _, fid, method, params = msg
                answer, error = _run_handler(self.urgent[method], method, params, urgent=True)
                result, afters = split(answer)
                try:
                    link.urgent.sendall(packer.pack(["resp", fid, error, packer.pack(result)]))
                except OSError:
                    return
                finally:
                    run_afters(afters)

    def _call(self, gen: int, fid: int, method: str, params: list[Any]) -> None:
        result, error = _run_handler(self.handlers[method], method, params)
        if isinstance(result, Future):
            result.add_done_callback(lambda fut: self._finish(gen, fid, method, fut))
            return
        self._out.put(("resp", gen, fid, error, result))

    def _finish(self, gen: int, fid: int, method: str, fut: Future[Any]) -> None:
        error = result = None
        if fut.cancelled():
            error = [int(ErrorCode.UNAVAILABLE), f"{method}: cancelled"]
        elif (exc := fut.exception()) is not None:
            error = _wire_error(method, exc)
        else:
            result = fut.result()
        self._out.put(("resp", gen, fid, error, result))


def _run_handler(
    handler: Callable[[list[Any]], Any], method: str, params: list[Any], urgent: bool = False
) -> tuple[Any, list[Any] | None]:
    """(result, None), or (None, the wire's error) when the handler raised; anything but an RpcError
    is a bug, logged with its traceback. An urgent reply names only the exception's type."""
    try:
        return handler(params), None
    except Exception as exc:
        if not isinstance(exc, RpcError):
            log.exception("rpc: %shandler %s failed", "urgent " if urgent else "", method)
        return None, _wire_error(method, exc, detail=not urgent)


def _wire_error(method: str, exc: BaseException, detail: bool = True) -> list[Any]:
    """A handler's exception as the wire's [code, message]: an RpcError as it is, anything else an
    internal error naming its type (and its text when `detail`)."""
    if isinstance(exc, RpcError):
        return exc.to_wire()
    text = f"{method}: internal error: {type(exc).__name__}"
    return [int(ErrorCode.INTERNAL), f"{text}: {exc}" if detail else text]


def _bind_tcp(address: tuple[str, int], what: str) -> socket.socket:
    """A listening TCP socket on (host, port), IPv6 for a host with a colon; errors name `what`."""
    family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
    try:
        return socket.create_server(address, family=family, backlog=HTTP_BACKLOG)
    except OSError as exc:
        host, port = address
        where = f"[{host}]:{port}" if family == socket.AF_INET6 else f"{host}:{port}"
        raise OSError(exc.errno, f"cannot listen for the {what} on {where}: {exc.strerror}") from exc


def _resolve_group(group: str | int | None) -> int | None:
    if group is None:
        return None
    if isinstance(group, bool):
        raise ValueError(f"group must be a name or a gid, got {group!r}")
    if isinstance(group, int):
        if group < 0:
            raise ValueError(f"group gid must be >= 0, got {group!r}")
        return group
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise ValueError(f"group {group!r} does not exist") from None
