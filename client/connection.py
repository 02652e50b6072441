"""The Python client lab scripts use to drive the rig through the daemon's socket.

    from usmswitch.client import Client

    with Client("/run/usmswitch/usmswitch.sock") as rig:
        rig.set_target(12_000_000)
        rig.start_cycling(period_ns=50_000_000, count=500)
        for rec in rig.subscribe():
            print(rec["cycle"], rec["error_ns"])

Synchronous, one socket, msgpack-RPC as in docs/protocol.md. Server errors raise `RpcError` with the
server's `code`; a lost connection raises `ConnectionClosed`, and idempotent calls are retried once on
a fresh connection.
"""

from __future__ import annotations

import os
import socket
from collections import deque
from collections.abc import Iterable, Iterator
from typing import Any, NamedTuple, TypedDict
from urllib.parse import parse_qs, urlsplit

import msgpack

from usmswitch.daemon.sockdir import UntrustedSocketError, check_peer, check_socket_owner
from usmswitch.daemon.wire import (
    MAX_MSGID,
    NOTIFICATION,
    REQUEST,
    RESPONSE,
    ErrorCode,
    RpcError,
    estop_socket_path,
)

__all__ = [
    "Client",
    "ConnectionClosed",
    "CycleRecord",
    "DirectionStats",
    "ErrorCode",
    "Notification",
    "RpcError",
    "Stats",
    "Status",
    "Subscription",
    "Targets",
    "UntrustedSocketError",
]

DEFAULT_TIMEOUT_NS = 10_000_000_000
#: Calls that are safe to send twice, so a broken connection may retry them once.
IDEMPOTENT = frozenset(
    {
        "ping",
        "status",
        "get_target",
        "set_target",
        "stats",
        "history",
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


class Targets(TypedDict):
    target_on_ns: int
    target_off_ns: int
    from_cycle: int  # the first stroke armed with these targets


class Status(TypedDict):
    state: str  # "idle", "cycling", "fault", "stopped"
    mode: str  # "closed" or "open"
    fault: str  # why FAULT is latched; "" when not
    driver: str
    driver_ok: bool  # the device answers (link up)
    protocol_version: int
    version: str
    uptime_ns: int
    cycle: int  # the number the next stroke will get
    target_on_ns: int
    target_off_ns: int
    driver_counters: dict[str, int]  # what the driver dropped or repaired (bounces, link errors, ...)
    records: dict[str, Any]  # the record writer: path, backlog, dropped, rejected, writer_error, ...


class DirectionStats(TypedDict, total=False):
    count: int  # completed strokes
    strokes: int  # completed + stalled
    operating_mean_ns: float
    operating_std_ns: float
    operating_max_abs_ns: int
    total_mean_ns: float
    total_std_ns: float
    total_max_abs_ns: int
    error_mean_ns: float
    error_std_ns: float
    error_max_abs_ns: int
    max_abs_error_pct: float
    abs_error_p50_ns: int | None
    abs_error_p95_ns: int | None
    abs_error_p99_ns: int | None
    lateness_p50_ns: int | None
    lateness_p99_ns: int | None
    lateness_p99_9_ns: int | None
    lateness_max_ns: int | None
    late: int
    stalls: int
    bounces: int
    faults: int
    order: int  # "on" and "off" only
    coefficients: list[float]
    ready: bool


class Stats(TypedDict):
    state: str
    mode: str
    fault: str
    cycle: int
    target_on_ns: int
    target_off_ns: int
    spurious_edges: int
    overruns: int
    driver_bounces: int
    all: DirectionStats
    on: DirectionStats
    off: DirectionStats


class CycleRecord(TypedDict):
    cycle: int
    direction: int  # 0 = on (A -> B), 1 = off (B -> A)
    mode: str
    target_ns: int
    order: int
    coefficients: list[float]
    t_hat_ns: int
    delay_ns: int
    t_cmd_ns: int
    t_start_ns: int | None
    t_depart_ns: int | None
    t_arrive_ns: int | None
    operating_ns: int | None
    total_ns: int | None
    error_ns: int | None
    dead_ns: int | None
    lateness_ns: int | None
    temperature_c: float | None
    frequency_hz: float | None
    flags: int  # usmswitch.daemon.record.Flag bits
    wall_ns: int
    driver: str | None  # the driver that made the stroke ("sim", "serial", "usb")
    rig: str | None  # the rig's identity ([daemon] rig, the host name by default)


class Notification(NamedTuple):
    """One notification: its topic ("stroke", "state", ...) and its single payload."""

    topic: str
    payload: Any


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


class Client:
    """A synchronous connection to the daemon; one call at a time unless `pipeline` is used."""

    def __init__(
        self,
        address: str | os.PathLike[str],
        *,
        timeout_ns: int | None = DEFAULT_TIMEOUT_NS,
        token: str | None = None,
        retry: bool = True,
        max_reply_bytes: int = 64 << 20,
    ) -> None:
        if timeout_ns is not None and (type(timeout_ns) is not int or timeout_ns <= 0):
            raise ValueError(
                f"timeout_ns must be a positive integer of nanoseconds or None, got {timeout_ns!r}"
            )
        self.family, self.address, url_token = parse_address(address)
        self.token = (
            token or url_token or (os.environ.get("USMSWITCH_TOKEN") if self.family == "tcp" else None)
        )
        self.timeout_ns = timeout_ns
        self.retry = retry
        self.max_reply_bytes = max_reply_bytes
        #: Notifications lost on this side because nobody read them (see MAX_BUFFERED_NOTIFICATIONS).
        self.local_dropped = 0
        self._sock: socket.socket | None = None
        self._unpacker: msgpack.Unpacker | None = None
        self._msgid = 0
        self._replies: dict[int, list[Any]] = {}
        self._notes: deque[Notification] = deque()
        self._pending_out: list[bytes] = []
        self._abandoned: set[int] = set()  # timed-out calls whose late replies are discarded
        self._packer = msgpack.Packer(use_bin_type=True, autoreset=True)
        self.connect()

    # -- connection ------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the connection (and authenticate over TCP); called by the constructor."""
        if self.family == "tcp":
            sock = socket.create_connection(self.address, timeout=self._timeout_s())
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        else:
            # Trust only a socket this user or root owns, or one in a private directory root placed
            # (docs/config.md): in a directory another user can write, the socket may be theirs.
            owner = check_socket_owner(self.address)
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            sock.settimeout(self._timeout_s())
            try:
                sock.connect(self.address)
                check_peer(sock, owner)
            except OSError:
                sock.close()
                raise
        self._sock = sock
        self._unpacker = msgpack.Unpacker(raw=False, max_buffer_size=self.max_reply_bytes)
        self._replies.clear()
        if self.family == "tcp":
            if not self.token:
                self.close()
                raise ValueError(
                    "a TCP connection needs a token: Client(..., token=...) or ?token= in the URL"
                )
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

    def _timeout_s(self) -> float | None:
        return None if self.timeout_ns is None else self.timeout_ns / 1e9

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
        return _result(self._wait(msgid))

    def pipeline(self, calls: Iterable[tuple[str, list[Any]]]) -> list[Any]:
        """Send every request before reading any reply; results (or RpcError instances) in order."""
        ids = [self._send(method, list(params), flush=False) for method, params in calls]
        self._flush()
        out: list[Any] = []
        for msgid in ids:
            try:
                out.append(_result(self._wait(msgid)))
            except RpcError as exc:
                out.append(exc)
        return out

    def _send(self, method: str, params: list[Any], flush: bool = True) -> int:
        if self._sock is None:
            raise ConnectionClosed("not connected: call reconnect()")
        self._msgid = (self._msgid + 1) & MAX_MSGID
        frame = self._packer.pack([REQUEST, self._msgid, method, params])
        if flush:
            self._sendall(frame)
        else:
            self._pending_out.append(frame)
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
        try:
            while msgid not in self._replies:
                self._read()
        except TimeoutError:
            self._abandoned.add(msgid)
            raise
        return self._replies.pop(msgid)

    def _read(self, timeout_ns: int | None = None, override: bool = False) -> None:
        """Read once from the socket and sort what arrives into replies and notifications."""
        sock, unpacker = self._sock, self._unpacker
        if sock is None or unpacker is None:
            raise ConnectionClosed("not connected: call reconnect()")
        if override:
            sock.settimeout(None if timeout_ns is None else timeout_ns / 1e9)
        try:
            data = sock.recv(262_144)
        except TimeoutError:
            raise TimeoutError(f"no reply from {self.address} within the timeout") from None
        except (ConnectionResetError, BrokenPipeError) as exc:
            self.close()
            raise ConnectionClosed(f"connection to {self.address} broke: {exc}") from exc
        finally:
            if override and self._sock is not None:
                self._sock.settimeout(self._timeout_s())
        if not data:
            self.close()
            raise self._closed_error()
        unpacker.feed(data)
        for msg in unpacker:
            if type(msg) is list and len(msg) == 4 and msg[0] == RESPONSE:
                if msg[1] in self._abandoned:
                    self._abandoned.discard(msg[1])
                else:
                    self._replies[msg[1]] = msg
            elif type(msg) is list and len(msg) == 3 and msg[0] == NOTIFICATION:
                params = msg[2]
                payload = params[0] if type(params) is list and len(params) == 1 else params
                if len(self._notes) >= MAX_BUFFERED_NOTIFICATIONS:
                    self._notes.popleft()
                    self.local_dropped += 1
                self._notes.append(Notification(msg[1], payload))

    def _closed_error(self) -> ConnectionClosed:
        # The server's "error" notification, when it sent one, says why it closed.
        for note in reversed(self._notes):
            if note.topic == "error" and type(note.payload) is list and len(note.payload) == 2:
                code, message = note.payload
                return ConnectionClosed(f"server closed the connection: [{code}] {message}", code)
        return ConnectionClosed(f"server closed the connection ({self.address})")

    # -- notifications ---------------------------------------------------------------------------
    def next_notification(self, timeout_ns: int | None = None) -> Notification:
        """The next notification, waiting up to `timeout_ns` (None: forever); TimeoutError if none."""
        while not self._notes:
            self._read(timeout_ns, override=True)
        return self._notes.popleft()

    def subscribe(self, *topics: str, timeout_ns: int | None = None) -> Subscription:
        """Subscribe to topics (default "stroke") and return an iterator over their notifications."""
        wanted = list(topics) or ["stroke"]
        self.call("subscribe", wanted)
        return Subscription(self, wanted, timeout_ns)

    def unsubscribe(self, *topics: str) -> list[str]:
        """Stop notifications of `topics` (all when none given); returns the topics still subscribed."""
        result = self.call("unsubscribe", list(topics)) if topics else self.call("unsubscribe")
        return list(result["topics"])

    # -- typed methods (docs/protocol.md) --------------------------------------------------------
    def ping(self) -> str:
        """Check that the daemon's server answers ("pong")."""
        return self.call("ping")

    def status(self) -> Status:
        """State, mode, fault, driver, versions, uptime and targets."""
        return self.call("status")

    def get_target(self) -> Targets:
        """The target total time T of each direction, in ns."""
        return self.call("get_target")

    def set_target(self, target_ns: int, direction: str = "both") -> Targets:
        """Set T (ns) for "on", "off" or "both"; takes effect from the next armed stroke."""
        return self.call("set_target", target_ns, direction)

    def stats(self) -> Stats:
        """Running statistics per direction and combined, as of the last finished stroke."""
        return self.call("stats")

    def history(self, n: int = 20) -> list[CycleRecord]:
        """The last `n` stroke records, oldest first."""
        return self.call("history", n)

    def switch(self, direction: str = "next") -> CycleRecord:
        """Make one stroke ("on", "off" or "next") and return its record once it has finished."""
        return self.call("switch", direction)

    def start_cycling(self, period_ns: int, count: int = 0) -> dict[str, int]:
        """Alternate on/off strokes every `period_ns`; `count` strokes, 0 for until stopped."""
        return self.call("start_cycling", period_ns, count)

    def stop_cycling(self) -> dict[str, Any]:
        """Stop cycling after the stroke in progress."""
        return self.call("stop_cycling")

    def set_mode(self, mode: str, open_delay_ns: int | None = None) -> dict[str, Any]:
        """Open loop ("open": fixed delay) or closed loop ("closed": AR-predicted delay)."""
        if open_delay_ns is None:
            return self.call("set_mode", mode)
        return self.call("set_mode", mode, open_delay_ns)

    def reset_fault(self) -> dict[str, Any]:
        """Clear a latched FAULT so strokes may run again."""
        return self.call("reset_fault")

    def estop(self) -> dict[str, Any]:
        """Stop the drive now and latch FAULT until reset_fault.

        The reply means the drive is off and nothing is scheduled. Over a Unix socket the call goes
        through the estop socket beside it (`<name>.estop.sock`): a connection and slots of its own,
        so no flood on the main socket holds it up; this connection is the fallback.
        """
        if self.family == "unix":
            urgent = estop_socket_path(self.address)
            if urgent.exists():
                try:
                    with Client(urgent, timeout_ns=self.timeout_ns, retry=False) as c:
                        return c.call("estop")
                except (ConnectionClosed, OSError):
                    pass  # busy or gone: the main connection still carries it
        return self.call("estop")

    def set_drive(
        self,
        *,
        frequency_hz: float | None = None,
        voltage_vpp: float | None = None,
        enabled: bool | None = None,
    ) -> dict[str, Any]:
        """Set the drive board's excitation (only the given keys); returns the drive's state."""
        settings: dict[str, Any] = {}
        if frequency_hz is not None:
            settings["frequency_hz"] = frequency_hz
        if voltage_vpp is not None:
            settings["voltage_vpp"] = voltage_vpp
        if enabled is not None:
            settings["enabled"] = enabled
        return self.call("set_drive", settings)


class Subscription:
    """Iterates a subscription's notifications: payloads for one topic, `Notification`s for several."""

    def __init__(self, client: Client, topics: list[str], timeout_ns: int | None) -> None:
        self.client = client
        self.topics = topics
        self.timeout_ns = timeout_ns
        #: Notifications the server dropped for this connection because it read too slowly.
        self.dropped = 0

    def notifications(self) -> Iterator[Notification]:
        """Every notification of the subscribed topics, with its topic; counts "dropped" ones."""
        while True:
            note = self.client.next_notification(self.timeout_ns)
            if note.topic == "dropped":
                self.dropped += int(note.payload.get("count", 0)) if type(note.payload) is dict else 0
                continue
            if note.topic in self.topics:
                yield note

    def __iter__(self) -> Iterator[Any]:
        if len(self.topics) == 1:
            return (note.payload for note in self.notifications())
        return self.notifications()

    def close(self) -> None:
        """Unsubscribe (if the connection is still up)."""
        if self.client.connected:
            self.client.unsubscribe(*self.topics)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _result(reply: list[Any]) -> Any:
    error = reply[2]
    if error is None:
        return reply[3]
    if type(error) is list and len(error) == 2:
        return _raise(int(error[0]), str(error[1]))
    return _raise(int(ErrorCode.INTERNAL), f"malformed error from the server: {error!r}")


def _raise(code: int, message: str) -> Any:
    raise RpcError(code, message)
