"""What a lab machine uses to work with a usmswitch rig: the socket client (blocking and asyncio),
runs, a callback notifier, reading records files, plots and `usmswitchctl`. Nothing here runs the
daemon; a lab machine needs only this package.

    from usmswitch.client import Client

    with Client() as rig:
        for rec in rig.run(count=500, period="50ms", target="12ms"):
            print(rec["cycle"], rec["error_ns"])
"""

from typing import Any

from usmswitch.protocol.sockets import client_socket_paths
from usmswitch.protocol.wire import (
    Busy,
    CallTimeout,
    ErrorCode,
    Faulted,
    InternalError,
    InvalidParams,
    InvalidRequest,
    ParseError,
    RpcError,
    TargetUnreachable,
    TooLarge,
    Unauthorized,
    Unavailable,
    UnknownMethod,
    WrongState,
)

from .api import Duration, find_socket
from .connection import Client, ConnectionClosed, ReplyTimeout, Subscription, UntrustedSocketError
from .notifier import Listener, Notifier
from .records import RecordsFile, RecordsFileError, RecordsSource
from .run import QueuedRun, QueuedRunNotStarted, Run, RunLost
from .sources import open_records
from .types import (
    CycleRecord,
    Cycling,
    DirectionStats,
    Notification,
    RunInfo,
    Stats,
    Status,
    Targets,
)

__all__ = [
    "AsyncClient",
    "AsyncQueuedRun",
    "AsyncRun",
    "Busy",
    "CallTimeout",
    "Client",
    "ConnectionClosed",
    "CycleRecord",
    "Cycling",
    "DirectionStats",
    "Duration",
    "ErrorCode",
    "Faulted",
    "InternalError",
    "InvalidParams",
    "InvalidRequest",
    "Listener",
    "Notification",
    "Notifier",
    "ParseError",
    "PostgresRecords",
    "QueuedRun",
    "QueuedRunNotStarted",
    "RecordsFile",
    "RecordsFileError",
    "RecordsSource",
    "ReplyTimeout",
    "RpcError",
    "Run",
    "RunInfo",
    "RunLost",
    "Stats",
    "Status",
    "Subscription",
    "TargetUnreachable",
    "Targets",
    "TooLarge",
    "Unauthorized",
    "Unavailable",
    "UnknownMethod",
    "UntrustedSocketError",
    "WrongState",
    "client_socket_paths",
    "find_socket",
    "open_records",
]

# Imported on first use: asyncio and psycopg cost `usmswitchctl` ~0.3 s of start-up it rarely needs.
_LAZY = {
    "AsyncClient": ".aio",
    "AsyncQueuedRun": ".aio",
    "AsyncRun": ".aio",
    "PostgresRecords": ".pgrecords",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
