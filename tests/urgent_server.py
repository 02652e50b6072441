"""The socket's server with an urgent estop, beside the estop socket the daemon serves itself on the
same handler (server/estop_socket.py), as daemon/methods.py wires them."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from usmswitch.server.estop_socket import EstopSocket
from usmswitch.server.rpc import RpcServer


@contextmanager
def urgent_server(sockdir: Path, estop: Callable[[list[Any]], object], **kwargs: Any) -> Iterator[RpcServer]:
    """Serving `d.sock` and `d.estop.sock` in `sockdir` until the block ends; `kwargs` go to RpcServer."""
    srv = RpcServer(
        {"status": lambda params: {"state": "idle"}},
        unix_path=sockdir / "d.sock",
        urgent={"estop": estop},
        urgent_path=sockdir / "d.estop.sock",
        busy_poll_ns=0,
        **kwargs,
    )
    srv.start()
    assert srv.urgent_listener is not None
    companion = EstopSocket(srv.urgent_listener, {"estop": estop}, srv.limits)
    companion.start()
    try:
        yield srv
    finally:
        companion.stop()
        srv.stop()
