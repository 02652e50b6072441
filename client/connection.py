"""The blocking client lab scripts use to drive the rig through the daemon's socket.

    from usmswitch.client import Client

    with Client() as rig:                      # finds the socket as usmswitchctl does
        run = rig.run(count=500, period="50ms", target="12ms")
        for rec in run:                        # this run's strokes, then the loop ends
            print(rec["cycle"], rec["error_ns"])
        print(run.stats()["all"]["error_std_ns"])

One socket, msgpack-RPC as in docs/protocol.md; timeouts are float seconds. Server errors raise
`RpcError` with the server's `code`; a lost connection raises `ConnectionClosed`, and idempotent
calls are retried once on a fresh connection. Not thread-safe: one Client per thread (a
`Notifier` opens its own).
"""

from __future__ import annotations

import os
import socket
import struct
import time
from collections import deque
from collections.abc import Iterable, Iterator
from typing import Any
from urllib.parse import parse_qs, urlsplit

import msgpack

from usmswitch.protocol.export_plan import CHUNK, ExportPlan
from usmswitch.protocol.record import check_label
from usmswitch.protocol.sockets import UntrustedSocketError, check_peer, check_socket_owner
from usmswitch.protocol.wire import (
    MAX_MSGID,
    NOTIFICATION,
    REQUEST,
    RESPONSE,
    ErrorCode,
    RpcError,
    estop_socket_path,
)

from .api import Api, Duration, find_socket
from .run import QueuedRun, Run
from .types import Notification

__all__ = [
    "Client",
    "ConnectionClosed",
    "ReplyTimeout",
    "Subscription",
    "UntrustedSocketError",
    "estop_by_every_path",
    "parse_address",
]

#: Seconds a call waits for its reply unless told otherwise.
DEFAULT_TIMEOUT = 10.0
#: Calls that are safe to send twice, so a broken connection may retry them once.
IDEMPOTENT = frozenset(
    {
        "ping",
        "status",
        "get_target",
        "set_target",
        "stats",
        "history",
        "runs",
        "export",
        "set_mode",
        "stop_cycling",
        "estop",
        "set_drive",
    }
)
#: Notifications kept while nobody iterates a subscription; older ones are dropped and counted.
MAX_BUFFERED_NOTIFICATIONS = 100_000


class ConnectionClosed(ConnectionError):
    """The daemon closed the connection (or it broke); `code` is the server's reason when it gave one."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


def parse_address(address: str | os.PathLike[str]) -> tuple[str, Any, str | None]:
    """Split "tcp://host:port?token=...", "unix:/path" or a bare path into (family, address, token)."""
    text = os.fspath(address)
    if text.startswith("tcp://"):
        url = urlsplit(text)
        if not url.hostname or url.port is None:
            raise ValueError(
                f"a TCP address needs a host and a port, like tcp://127.0.0.1:7781; got {text!r}"
            )
        token = parse_qs(url.query).get("token", [None])[-1]
        return "tcp", (url.hostname, url.port), token
    if text.startswith("unix://"):
        text = text[len("unix://") :]
    elif text.startswith("unix:"):
        text = text[len("unix:") :]
    if not text:
        raise ValueError(f"empty socket path in {os.fspath(address)!r}")
    return "unix", text, None


class ReplyTimeout(TimeoutError):
    """A call got no reply within the client's timeout. Says which call, how long it has been
    waiting, and whether the daemon still answers (a ping on a new connection): a slow request is
    not a daemon gone."""

    def __init__(self, method: str, waited_s: float, client: Client, ping_ms: float | None) -> None:
        self.method = method
        self.waited_s = waited_s
        self.ping_ms = ping_ms
        limit = f"{client.timeout:g} s" if client.timeout is not None else "no limit"
        if ping_ms is not None:
            why = (
                f"the daemon is up (a ping on a new connection answered in {ping_ms:.1f} ms) and has been"
                f" on this {method} for {waited_s:.1f} s: a slow request, not a daemon gone; a longer"
                " timeout waits for it"
            )
        else:
            why = f"waited {waited_s:.1f} s, and a ping on a new connection got no answer either"
        super().__init__(f"{method}: no reply from {client.address} within {limit}; {why}")


def check_timeout(name: str, value: float | None) -> float | None:
    """A timeout in seconds (None: wait forever); ValueError for anything else."""
    if value is not None and (isinstance(value, bool) or not isinstance(value, int | float) or value <= 0):
        raise ValueError(f"{name} must be a positive number of seconds or None, got {value!r}")
    return None if value is None else float(value)


def connect_unix(path: str, timeout: float | None) -> socket.socket:
    """A connected Unix socket. Past a full backlog (a connection flood the server sheds at its
    accepts) the connect waits in the kernel's queue of connectors, first come first served, for
    up to `timeout` (SO_SNDTIMEO; then BlockingIOError). A socket with a timeout would fail at
    once with EAGAIN there, and tried again every millisecond it lost each free place to the
    flood's own waiting connects (the abuse bench's estop by the main socket under 600
    connections renewed: p99 9-11 ms)."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        if timeout is not None:
            sec, usec = divmod(max(1, round(timeout * 1e6)), 1_000_000)  # 0 s 0 us: no bound at all
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("@ll", sec, usec))
        sock.connect(path)
        if timeout is not None:  # the bound was the connect's; sends keep the socket's own timeout
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("@ll", 0, 0))
        sock.settimeout(timeout)
    except OSError:
        sock.close()
        raise
    return sock


class Client(Api):
    """A blocking connection to the daemon; one call at a time unless `pipeline` is used.

    `address`: a socket path, "unix:PATH" or "tcp://host:port?token=..."; None finds the local
    daemon's socket as `usmswitchctl` does (`rig` names a rig's instance). `timeout`: seconds a
    call waits for its reply (None: forever). `auth_with_first_call` (TCP): `auth` goes out in one
    write with the first call instead of being answered before the constructor returns, one round
    trip less for a connection made for one call (`usmswitchctl estop`); a wrong token is then
    raised by that first call (Unauthorized), and the call itself is not carried out.
    """

    def __init__(
        self,
        address: str | os.PathLike[str] | None = None,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        token: str | None = None,
        retry: bool = True,
        max_reply_bytes: int = 64 << 20,
        rig: str | None = None,
        auth_with_first_call: bool = False,
    ) -> None:
        self.timeout = check_timeout("timeout", timeout)
        if address is None:
            address = find_socket(rig)
        self._given_address = address
        self.family, self.address, url_token = parse_address(address)
        self.token = (
            token or url_token or (os.environ.get("USMSWITCH_TOKEN") if self.family == "tcp" else None)
        )
        self.retry = retry
        self.max_reply_bytes = max_reply_bytes
        self._probe_on_timeout = True  # a call timed out asks a new connection whether the daemon is up
        #: Notifications lost on this side because nobody read them (see MAX_BUFFERED_NOTIFICATIONS).
        self.local_dropped = 0
        self._sock: socket.socket | None = None
        self._unpacker: msgpack.Unpacker | None = None
        self._msgid = 0
        self._replies: dict[int, list[Any]] = {}
        self._notes: deque[Notification] = deque()
        #: The topics this connection is subscribed to (as the server last said).
        self.topics: set[str] = set()
        self._run_holds: dict[str, int] = {}  # topic -> run objects holding it (hold_topics)
        self._pending_out: list[bytes] = []
        self._auth_with_first_call = auth_with_first_call
        self._auth_msgid: int | None = None  # an auth sent with the first call, its answer not yet read
        self._abandoned: set[int] = set()  # timed-out calls whose late replies are discarded
        self._sent: dict[int, tuple[str, int]] = {}  # msgid -> (method, monotonic ns sent): for timeouts
        self._packer = msgpack.Packer(use_bin_type=True, autoreset=True)
        self.connect()

    # -- connection ------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the connection (and authenticate over TCP); called by the constructor."""
        if self.family == "tcp":
            sock = socket.create_connection(self.address, timeout=self.timeout)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        else:
            # Trust only a socket this user or root owns, or one in a private directory root placed
            # (docs/config.md): in a directory another user can write, the socket may be theirs.
            owner = check_socket_owner(self.address)
            sock = connect_unix(self.address, self.timeout)
            try:
                check_peer(sock, owner)
            except OSError:
                sock.close()
                raise
        self._sock = sock
        self._unpacker = msgpack.Unpacker(raw=False, max_buffer_size=self.max_reply_bytes)
        self._replies.clear()
        self._abandoned.clear()  # replies to a closed connection's calls never come
        self._sent.clear()
        self._pending_out.clear()
        self._auth_msgid = None
        self.topics = set()
        self._run_holds = {}
        if self.family == "tcp":
            if not self.token:
                self.close()
                raise ValueError(
                    "a TCP connection needs a token: Client(..., token=...) or ?token= in the URL"
                )
            if self._auth_with_first_call:
                self._auth_msgid = self._send("auth", [self.token], flush=False)
            else:
                self.call("auth", self.token, retry=False)

    def reconnect(self) -> None:
        """Drop the connection and open a new one. Subscriptions are per connection: subscribe again."""
        self.close()
        self.connect()

    def close(self) -> None:
        """Close the connection (pending notifications stay readable from the buffer)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    @property
    def connected(self) -> bool:
        """True while the socket is open (a server-side close is noticed on the next read)."""
        return self._sock is not None

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- calls -----------------------------------------------------------------------------------
    def call(self, method: str, *params: Any, retry: bool | None = None) -> Any:
        """Send one request and wait for its result; raises RpcError with the server's code."""
        allow = (self.retry if retry is None else retry) and method in IDEMPOTENT
        try:
            return self._call_once(method, list(params))
        except ConnectionError:
            if not allow:
                raise
        self.reconnect()
        return self._call_once(method, list(params))

    def _call_once(self, method: str, params: list[Any]) -> Any:
        msgid = self._send(method, params)
        return result_of(self._wait(msgid))

    def export_csv(
        self,
        run: int | None = None,
        first: int = 1,
        last: int | None = None,
        *,
        label: str | None = None,
        max_strokes: int = CHUNK,
    ) -> Iterator[tuple[int, int, str]]:
        """Every stroke (of a run, of the runs with `label`, from cycle `first` to `last`) as CSV
        lines without the header (`usmswitch.protocol.record_csv.csv_header_line`), a chunk of up to
        `max_strokes` (1..10,000) at a time: (strokes, last cycle, text), in cycle order.

        The chunks are asked a few ahead (`protocol.export_plan`): the server builds the next while
        this one travels and is written. Memory is a few chunks on both ends; stop iterating and no
        more are asked (the replies in flight are dropped as they come)."""
        plan = ExportPlan(first, last, max_strokes)
        tail = [] if label is None else [check_label(label)]
        ids: deque[int] = deque()  # the msgids of plan.in_flight, in the same order
        retried = False
        chunk: dict[str, Any] | None = None

        def lost(exc: ConnectionError) -> None:
            nonlocal retried
            if retried or not self.retry:  # as call() does: once more, on a fresh connection
                raise exc
            retried = True
            ids.clear()
            plan.restart()
            self.reconnect()

        try:
            while True:
                try:  # the next requests in flight before this chunk is handed over
                    for a, b, most in plan.requests():
                        ids.append(self._send("export", [run, a, b, most, *tail], flush=False))
                    self._flush()
                except ConnectionError as exc:
                    lost(exc)
                    continue
                if chunk is not None:
                    yield chunk["strokes"], chunk["last_cycle"], chunk["csv"]
                    chunk = None
                if not ids:
                    return
                try:
                    reply = self._wait(ids[0])
                except ConnectionError as exc:
                    lost(exc)
                    continue
                ids.popleft()
                retried = False
                got = result_of(reply)
                if plan.answered(got["strokes"], got["last_cycle"]) and got["strokes"]:
                    chunk = got
        finally:
            for msgid in ids:
                self._abandon(msgid)

    def pipeline(self, calls: Iterable[tuple[str, list[Any]]]) -> list[Any]:
        """Send every request before reading any reply; results (or RpcError instances) in order."""
        ids = [self._send(method, list(params), flush=False) for method, params in calls]
        self._flush()
        out: list[Any] = []
        for msgid in ids:
            try:
                out.append(result_of(self._wait(msgid)))
            except RpcError as exc:
                out.append(exc)
        return out

    def _send(self, method: str, params: list[Any], flush: bool = True) -> int:
        if self._sock is None:
            raise ConnectionClosed("not connected: call reconnect()")
        self._msgid = (self._msgid + 1) & MAX_MSGID
        frame = self._packer.pack([REQUEST, self._msgid, method, params])
        self._sent[self._msgid] = (method, time.monotonic_ns())
        if flush and not self._pending_out:
            self._sendall(frame)
        else:  # behind what waits to go (a pipeline's frames, an auth sent with the first call)
            self._pending_out.append(frame)
            if flush:
                self._flush()
        return self._msgid

    def _flush(self) -> None:
        frames, self._pending_out = self._pending_out, []
        if frames:
            self._sendall(b"".join(frames))

    def _sendall(self, data: bytes) -> None:
        assert self._sock is not None
        try:
            self._sock.sendall(data)
        except (BrokenPipeError, ConnectionResetError) as exc:
            self.close()
            raise ConnectionClosed(f"connection to {self.address} broke: {exc}") from exc

    def _wait(self, msgid: int) -> list[Any]:
        if self._auth_msgid is not None and msgid != self._auth_msgid:
            # The server took the frames in order: the auth's answer comes first, and a wrong
            # token closed the connection before the call was read.
            auth, self._auth_msgid = self._auth_msgid, None
            try:
                result_of(self._wait(auth))
            except RpcError:
                self.close()
                raise
        try:
            while msgid not in self._replies:
                self._read()
        except TimeoutError:
            self._abandoned.add(msgid)
            method, sent_ns = self._sent.pop(msgid, ("the call", time.monotonic_ns()))
            ping_ms = self._ping_ms() if self._probe_on_timeout else None
            raise ReplyTimeout(method, (time.monotonic_ns() - sent_ns) / 1e9, self, ping_ms) from None
        self._sent.pop(msgid, None)
        return self._replies.pop(msgid)

    def _abandon(self, msgid: int) -> None:
        """Nobody waits for `msgid` any more: its reply is dropped, now or when it comes."""
        self._sent.pop(msgid, None)
        if self._replies.pop(msgid, None) is None and self._sock is not None:
            self._abandoned.add(msgid)

    def _ping_ms(self) -> float | None:
        """A ping's round trip on a new connection, in ms (None: no answer within a second or the
        call's timeout): whether a call that timed out met a slow request or a daemon gone."""
        probe_s = min(self.timeout or 1.0, 1.0)
        t0 = time.monotonic_ns()
        try:
            with Client(self._given_address, timeout=probe_s, token=self.token, retry=False) as c:
                # The probe's own call, timed out, sends no probe of its own: one after another
                # (0.3 s each, 100 deep) said "no answer" 31 s late of a stopped server.
                c._probe_on_timeout = False
                c.ping()
        except (OSError, RpcError, ValueError):
            return None
        return (time.monotonic_ns() - t0) / 1e6

    def _read(self, timeout: float | None = None, override: bool = False) -> None:
        """Read once from the socket and sort what arrives into replies and notifications.

        `override`: wait up to `timeout` (a notification's wait) instead of the call timeout.
        """
        sock, unpacker = self._sock, self._unpacker
        if sock is None or unpacker is None:
            raise ConnectionClosed("not connected: call reconnect()")
        if override:
            sock.settimeout(timeout)
        try:
            data = sock.recv(262_144)
        except TimeoutError:
            if override:
                raise TimeoutError(f"no notification from {self.address} within {timeout:g} s") from None
            raise TimeoutError(f"no reply from {self.address} within {self.timeout:g} s") from None
        except (ConnectionResetError, BrokenPipeError) as exc:
            self.close()
            raise ConnectionClosed(f"connection to {self.address} broke: {exc}") from exc
        finally:
            if override and self._sock is not None:
                self._sock.settimeout(self.timeout)
        if not data:
            self.close()
            raise self._closed_error()
        unpacker.feed(data)
        for msg in unpacker:
            reply, note = sort_message(msg)
            if reply is not None:
                if reply[1] in self._abandoned:
                    self._abandoned.discard(reply[1])
                else:
                    self._replies[reply[1]] = reply
            elif note is not None:
                if len(self._notes) >= MAX_BUFFERED_NOTIFICATIONS:
                    self._notes.popleft()
                    self.local_dropped += 1
                self._notes.append(note)

    def _closed_error(self) -> ConnectionClosed:
        return closed_error(self._notes, self.address)

    # -- notifications ---------------------------------------------------------------------------
    def next_notification(self, timeout: float | None = None) -> Notification:
        """The next notification, waiting up to `timeout` seconds (None: forever); TimeoutError if none."""
        timeout = check_timeout("timeout", timeout)
        while not self._notes:
            self._read(timeout, override=True)
        return self._notes.popleft()

    def subscribe(self, *topics: str, timeout: float | None = None) -> Subscription:
        """Subscribe to topics (default "stroke"); iterating the result yields `Notification`s
        (topic, payload), waiting up to `timeout` seconds for each (None: forever)."""
        wanted = list(topics) or ["stroke"]
        self._subscribed(self.call("subscribe", wanted))
        return Subscription(self, wanted, check_timeout("timeout", timeout))

    def unsubscribe(self, *topics: str) -> list[str]:
        """Stop notifications of `topics` (all when none given); returns the topics still subscribed."""
        result = self.call("unsubscribe", list(topics)) if topics else self.call("unsubscribe")
        return sorted(self._subscribed(result))

    def hold_topics(self, topics: Iterable[str]) -> list[str]:
        """Subscribe `topics` for a run object, counted: several runs on one connection (queued
        ones) share them, and the last to end unsubscribes. Topics subscribed by hand are left be.
        Returns those held, for `release_topics`."""
        holds = self._run_holds
        held = [t for t in topics if t in holds or t not in self.topics]
        new = [t for t in held if t not in holds]
        if new:
            self._subscribed(self.call("subscribe", new))
        for t in held:
            holds[t] = holds.get(t, 0) + 1
        return held

    def release_topics(self, topics: Iterable[str]) -> None:
        """A run object is done with `topics` (`hold_topics`): unsubscribed when no other holds them."""
        holds = self._run_holds
        gone = []
        for t in topics:
            holds[t] -= 1
            if not holds[t]:
                del holds[t]
                gone.append(t)
        if gone and self.connected:
            self.unsubscribe(*gone)

    def _subscribed(self, reply: dict[str, Any]) -> set[str]:
        self.topics = set(reply["topics"])
        return self.topics

    def run(
        self,
        count: int = 0,
        period: Duration = "50ms",
        target: Duration | None = None,
        *,
        allow_late: bool = False,
        take_over: bool = False,
        timeout: float | None = None,
        label: str | None = None,
        notes: str | None = None,
    ) -> Run:
        """Start a run and return it: iterating the `Run` yields its stroke records (none missed:
        the subscription is made before the start) and ends when the run ends. `timeout`: seconds
        to wait for each stroke (None: forever). `label` and `notes` say what the run is for
        (`start_cycling`)."""
        added = self.hold_topics(("stroke", "run"))
        try:
            started = self.start_cycling(
                period,
                count,
                target=target,
                allow_late=allow_late,
                take_over=take_over,
                label=label,
                notes=notes,
            )
        except BaseException:
            self.release_topics(added)
            raise
        return Run(self, started, added, check_timeout("timeout", timeout))

    def submit(
        self,
        count: int = 0,
        period: Duration = "50ms",
        target: Duration | None = None,
        *,
        allow_late: bool = False,
        label: str | None = None,
        notes: str | None = None,
        priority: int = 0,
        take_over: bool = False,
        timeout: float | None = None,
    ) -> QueuedRun:
        """Put a run in the daemon's queue and return it: iterating the `QueuedRun` waits for its
        turn, then yields its strokes and ends with it, as `run`'s does (the subscriptions are made
        before the submit, so no stroke is missed). Two scripts submitting at once both get their
        run, one after the other: none is refused, none ended. `timeout`: seconds to wait for each
        notification (None: forever; its turn may be long in coming)."""
        added = self.hold_topics(("stroke", "run", "queue"))
        try:
            entry = self.submit_entry(
                period,
                count,
                target=target,
                allow_late=allow_late,
                label=label,
                notes=notes,
                priority=priority,
                take_over=take_over,
            )
        except BaseException:
            self.release_topics(added)
            raise
        return QueuedRun(self, entry, added, check_timeout("timeout", timeout))

    # -- methods with a transport of their own ----------------------------------------------------
    def estop(self, by: str = "") -> dict[str, Any]:
        """Stop the drive now and latch FAULT until reset_fault.

        The reply means the drive is off and nothing is scheduled. Over a Unix socket the call goes
        through the estop socket beside it (`<name>.estop.sock`): a connection and slots of its own,
        so no flood on the main socket holds it up; this connection is the fallback (and a fresh
        one after it: a full door keeps a few slots that take only an estop). The fault latched
        names the path and `by` when given: `estop (usmswitchctl, estop socket)`.
        """
        if self.family == "unix":
            try:
                return _estop_on(estop_socket_path(self.address), self.timeout, by)
            except (ConnectionClosed, OSError):
                pass  # busy or gone: the main connection still carries it
        return _estop_call(self, _source(by, self.family))


def _source(by: str, family: str) -> str:
    """An estop's source as the main door's caller says it (the estop socket names itself)."""
    door = "TCP" if family == "tcp" else "main socket"
    return f"{by}, {door}" if by else door


def _estop_call(client: Client, source: str) -> dict[str, Any]:
    """`estop [source]`; a daemon from before estop took a source refuses it: then bare, at once."""
    try:
        return client.call("estop", source)  # type: ignore[no-any-return]
    except RpcError as exc:
        if exc.code != ErrorCode.INVALID_PARAMS:
            raise
        return client.call("estop")  # type: ignore[no-any-return]


def _estop_on(path: str | os.PathLike[str], timeout: float | None, by: str = "") -> dict[str, Any]:
    with Client(path, timeout=timeout, retry=False) as c:
        return _estop_call(c, by) if by else c.call("estop")  # type: ignore[no-any-return]


def estop_by_every_path(
    address: str | os.PathLike[str],
    *,
    timeout: float | None = DEFAULT_TIMEOUT,
    token: str | None = None,
    by: str = "",
) -> dict[str, Any]:
    """An estop however the daemon's doors are held: its estop socket, then its main socket (or
    TCP), each on a fresh connection, twice round; raises the last failure when none answered.

    For `usmswitchctl estop`: it needs no connection made beforehand that a full door could refuse.
    """
    family, path, _ = parse_address(address)
    tries: list[Any] = []
    if family == "unix":
        tries.append(lambda: _estop_on(estop_socket_path(path), timeout, by))

    def main_door() -> dict[str, Any]:
        # Over TCP the auth goes in one write with the estop: no round trip waited for first.
        with Client(address, timeout=timeout, token=token, retry=False, auth_with_first_call=True) as c:
            return _estop_call(c, _source(by, family))

    tries.append(main_door)
    last: Exception | None = None
    for _ in range(2):  # a holder shed for us may take the slot back once; not twice in a row
        for attempt in tries:
            try:
                return attempt()  # type: ignore[no-any-return]
            except (ConnectionClosed, OSError) as exc:
                last = exc
    assert last is not None
    raise last


class Subscription:
    """Iterates a subscription's notifications, each a `Notification` (topic, payload)."""

    def __init__(self, client: Client, topics: list[str], timeout: float | None) -> None:
        self.client = client
        self.topics = topics
        self.timeout = timeout
        #: Notifications the server dropped for this connection because it read too slowly.
        self.dropped = 0

    def notifications(self) -> Iterator[Notification]:
        """Every notification of the subscribed topics, with its topic; counts "dropped" ones."""
        while True:
            note = self.client.next_notification(self.timeout)
            if note.topic == "dropped":
                self.dropped += note.dropped
                continue
            if note.topic in self.topics:
                yield note

    def __iter__(self) -> Iterator[Notification]:
        return self.notifications()

    def close(self) -> None:
        """Unsubscribe (if the connection is still up)."""
        if self.client.connected:
            self.client.unsubscribe(*self.topics)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def sort_message(msg: object) -> tuple[list[Any] | None, Notification | None]:
    """A decoded frame from the server: (a response, None), (None, a notification) or (None, None)."""
    if type(msg) is list and len(msg) == 4 and msg[0] == RESPONSE:
        return msg, None
    if type(msg) is list and len(msg) == 3 and msg[0] == NOTIFICATION:
        params = msg[2]
        payload = params[0] if type(params) is list and len(params) == 1 else params
        return None, Notification(msg[1], payload)
    return None, None


def closed_error(notes: Iterable[Notification], address: object) -> ConnectionClosed:
    """Why the server closed: its "error" notification when it sent one."""
    for note in reversed(list(notes)):
        if note.topic == "error" and type(note.payload) is list and len(note.payload) == 2:
            code, message = note.payload
            return ConnectionClosed(f"server closed the connection: [{code}] {message}", code)
    return ConnectionClosed(f"server closed the connection ({address})")


def result_of(reply: list[Any]) -> Any:
    """A response's result, or its error raised as RpcError."""
    error = reply[2]
    if error is None:
        return reply[3]
    if type(error) is list and len(error) == 2:
        return _raise(int(error[0]), str(error[1]))
    return _raise(int(ErrorCode.INTERNAL), f"malformed error from the server: {error!r}")


def _raise(code: int, message: str) -> Any:
    raise RpcError.of(code, message)
