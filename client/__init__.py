"""What a lab machine uses to work with a usmswitch rig: the socket client, reading records files,
plots and `usmswitchctl`. Nothing here runs the daemon; a lab machine needs only this package.

    from usmswitch.client import Client

    with Client("/run/usmswitch/usmswitchd.sock") as rig:
        rig.set_target(12_000_000)
"""

from usmswitch.daemon.sockdir import client_socket_paths

from .connection import (
    Client,
    ConnectionClosed,
    CycleRecord,
    DirectionStats,
    ErrorCode,
    Notification,
    RpcError,
    Stats,
    Status,
    Subscription,
    Targets,
    UntrustedSocketError,
)
from .records import RecordsFile, RecordsFileError

__all__ = [
    "Client",
    "ConnectionClosed",
    "CycleRecord",
    "DirectionStats",
    "ErrorCode",
    "Notification",
    "RecordsFile",
    "RecordsFileError",
    "RpcError",
    "Stats",
    "Status",
    "Subscription",
    "Targets",
    "UntrustedSocketError",
    "client_socket_paths",
]
