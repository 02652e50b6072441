"""The socket's wire format, shared by the daemon's server and the client: message kinds, error
codes, limits, the msgpack options and frames (docs/protocol.md).

Pure: msgpack and the standard library only, so a lab machine's client needs nothing of the daemon.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, fields
from enum import IntEnum
from pathlib import Path

import msgpack

#: Bumped when a method, a field or the framing changes incompatibly.
PROTOCOL_VERSION = 1

REQUEST, RESPONSE, NOTIFICATION = 0, 1, 2
#: history's upper bound on n.
MAX_HISTORY = 10_000
MAX_MSGID = 2**32 - 1

#: Methods the server process answers itself, on every connection.
BUILTIN_METHODS = ("ping", "auth", "subscribe", "unsubscribe")
#: Notifications the server itself sends (never published by the daemon).
SERVER_TOPICS = ("dropped", "error")


class ErrorCode(IntEnum):
    """The `code` of an error `[code, message]`; JSON-RPC's numbers for the generic ones."""

    PARSE_ERROR = -32700  # not msgpack, or a frame over the limits: the connection is closed
    INVALID_REQUEST = -32600  # msgpack, but not [0, msgid, method, params]
    UNKNOWN_METHOD = -32601
    INVALID_PARAMS = -32602
    INTERNAL = -32603  # a bug in the daemon; the message says where
    BUSY = 1  # too many outstanding requests, connections or calls in flight: retry later
    UNAUTHORIZED = 2  # TCP without a valid `auth` first
    FAULT = 3  # the rig is in FAULT: reset_fault first
    STATE = 4  # not possible in the current state (e.g. switch while cycling)
    UNAVAILABLE = 5  # not configured or not ready (no drive board, no stats yet, daemon restarting)
    TIMEOUT = 6  # no answer from the daemon within the call timeout, or an idle connection closed
    TOO_LARGE = 7  # a frame or a reply above the limits
    UNREACHABLE = 8  # a closed-loop target below the shortest the rig reaches (the message names it)


class RpcError(Exception):
    """An error the protocol carries as `[code, message]`; handlers raise it to answer with one."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(f"[{int(code)}] {message}")
        self.code = int(code)
        self.message = message

    def to_wire(self) -> list[object]:
        """The `[code, message]` pair of a response's error slot."""
        return [self.code, self.message]

    @staticmethod
    def of(code: int, message: str) -> RpcError:
        """The error for `code` as its own subclass (`except TargetUnreachable:`), else RpcError."""
        return _BY_CODE.get(int(code), RpcError)(code, message)


# One subclass per code, so that scripts catch what they can handle by name.
class ParseError(RpcError):
    """The frame was not msgpack or broke a limit; the server closes the connection."""


class InvalidRequest(RpcError):
    """msgpack, but not a request `[0, msgid, method, params]`."""


class UnknownMethod(RpcError):
    """No such method."""


class InvalidParams(RpcError):
    """A parameter is missing, of the wrong type or out of range; the message names it."""


class InternalError(RpcError):
    """A bug in the daemon; the message says where."""


class Busy(RpcError):
    """Too many requests, connections or calls in flight: retry later."""


class Unauthorized(RpcError):
    """TCP without a valid token."""


class Faulted(RpcError):
    """The rig is in FAULT: `reset_fault` first."""


class WrongState(RpcError):
    """Not possible now (a run is going, the rig is busy); the message says what would be."""


class Unavailable(RpcError):
    """Not configured or not ready (no drive board, the daemon restarting)."""


class CallTimeout(RpcError):
    """No answer within the call's timeout, or an idle connection closed."""


class TooLarge(RpcError):
    """A frame or a reply above the limits."""


class TargetUnreachable(RpcError):
    """A closed-loop target below the shortest the rig reaches; the message names the shortest."""


_BY_CODE: dict[int, type[RpcError]] = {
    ErrorCode.PARSE_ERROR: ParseError,
    ErrorCode.INVALID_REQUEST: InvalidRequest,
    ErrorCode.UNKNOWN_METHOD: UnknownMethod,
    ErrorCode.INVALID_PARAMS: InvalidParams,
    ErrorCode.INTERNAL: InternalError,
    ErrorCode.BUSY: Busy,
    ErrorCode.UNAUTHORIZED: Unauthorized,
    ErrorCode.FAULT: Faulted,
    ErrorCode.STATE: WrongState,
    ErrorCode.UNAVAILABLE: Unavailable,
    ErrorCode.TIMEOUT: CallTimeout,
    ErrorCode.TOO_LARGE: TooLarge,
    ErrorCode.UNREACHABLE: TargetUnreachable,
}


@dataclass(frozen=True, slots=True)
class Limits:
    """Every bound the server enforces; the defaults suit a lab network of a few scripts."""

    max_frame_bytes: int = 65_536  # one incoming frame, and the unparsed buffer per connection
    max_str_len: int = 4_096
    max_bin_len: int = 4_096
    max_array_len: int = 1_024
    max_map_len: int = 64
    max_connections: int = 64  # Unix socket
    max_tcp_connections: int = 8  # TCP, apart: unauthenticated peers cannot take Unix slots
    max_urgent_connections: int = 16  # the estop socket, apart from both
    # The Unix socket's listen backlog: connections made and not yet accepted. Past it a blocking
    # connect waits in the kernel's queue of connectors, first come first served (the clients'
    # do); a non-blocking one fails with EAGAIN. Small, so that a connection behind a flood waits
    # for few accepts (60-100 us each under one): an estop by the main socket under 600
    # connections renewed, p99 9-11 ms at 100, 3.8-4.4 at 32, 3.0-3.1 at 16.
    unix_backlog: int = 16
    urgent_reserve: int = 4  # per door past its budget: connections that may only send auth and estop
    urgent_hold_ns: int = 1_000_000_000  # how long such a reserved connection is kept
    shed_idle_ns: int = 1_000_000_000  # a full door sheds its longest-idle holder once idle this long
    max_outstanding: int = 32  # per connection: calls waiting for the daemon
    max_forwarded: int = 256  # all connections: calls waiting for the daemon
    max_reads: int = 2  # history reads served from the records file at once (the rest wait)
    max_bad_frames: int = 8  # invalid requests on one connection before it is closed
    idle_timeout_ns: int = 600_000_000_000  # no request, no subscription, nothing outstanding
    auth_timeout_ns: int = 5_000_000_000  # TCP: time to send `auth`
    first_frame_timeout_ns: int = 2_000_000_000  # a new connection that sends no whole frame
    frame_timeout_ns: int = 2_000_000_000  # a frame begun and not finished
    urgent_timeout_ns: int = 250_000_000  # the estop socket: time to send the request
    call_timeout_ns: int = 30_000_000_000  # a forwarded call the daemon does not answer
    subscriber_buffer_bytes: int = 262_144  # unsent bytes above which notifications are dropped
    max_write_buffer_bytes: int = 16_777_216  # unsent bytes above which a connection is aborted
    publish_backlog: int = 4_096  # daemon side: notifications queued for the server process

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"Limits.{f.name} must be a positive integer, got {value!r}")
        if self.max_write_buffer_bytes < self.subscriber_buffer_bytes:
            raise ValueError(
                f"Limits.max_write_buffer_bytes ({self.max_write_buffer_bytes}) must be >= "
                f"subscriber_buffer_bytes ({self.subscriber_buffer_bytes})"
            )


def estop_socket_path(path: str | os.PathLike[str]) -> Path:
    """The estop socket beside the main one: `usmswitchd.sock` -> `usmswitchd.estop.sock`."""
    p = Path(path)
    return p.with_name(f"{p.stem}.estop{p.suffix}")


def unpacker(limits: Limits) -> msgpack.Unpacker:
    """A streaming decoder that refuses anything above `limits` and every ext type."""
    return msgpack.Unpacker(
        raw=False,
        use_list=True,
        strict_map_key=True,
        max_buffer_size=limits.max_frame_bytes,
        max_str_len=limits.max_str_len,
        max_bin_len=limits.max_bin_len,
        max_array_len=limits.max_array_len,
        max_map_len=limits.max_map_len,
        max_ext_len=0,
    )


_local = threading.local()


def packb(obj: object) -> bytes:
    """msgpack-encode with this thread's Packer (a Packer is not thread-safe; making one costs ~1 us)."""
    try:
        packer = _local.packer
    except AttributeError:
        packer = _local.packer = msgpack.Packer(use_bin_type=True, autoreset=True)
    return packer.pack(obj)


_NIL = b"\xc0"
_RESPONSE_HEAD = b"\x94\x01"  # fixarray(4), RESPONSE


def ok_frame(msgid: int, result_bytes: bytes) -> bytes:
    """A success response spliced around an already packed result: no re-encoding per request."""
    return ok_head(msgid) + result_bytes


def ok_head(msgid: int) -> bytes:
    """A success response's bytes before its packed result (the result then follows as it is)."""
    return _RESPONSE_HEAD + packb(msgid) + _NIL


def error_frame(msgid: int, code: int, message: str) -> bytes:
    return packb([RESPONSE, msgid, [int(code), message], None])


def note_frame(topic: str, payload: object) -> bytes:
    return packb([NOTIFICATION, topic, [payload]])
