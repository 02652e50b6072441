"""The server process on either event loop: uvloop where it is installed, asyncio's own otherwise."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from usmswitch.client import Client
from usmswitch.protocol.wire import RpcError
from usmswitch.server import rpc_process
from usmswitch.server.rpc import RpcServer

LOOPS = ["asyncio"] + (["uvloop"] if rpc_process._loop_factory() is not None else [])


def test_without_uvloop_the_factory_is_asyncios(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "uvloop", None)  # import uvloop -> ImportError
    monkeypatch.delenv("USMSWITCH_RPC_LOOP", raising=False)
    assert rpc_process._loop_factory() is None


@pytest.mark.parametrize("isolation", ["process", "thread"])
@pytest.mark.parametrize("loop", LOOPS)
def test_snapshot_forward_and_errors_on_each_loop(
    sockdir: Path, loop: str, isolation: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("USMSWITCH_RPC_LOOP", loop)
    srv = RpcServer(
        {},
        unix_path=sockdir / "rpc.sock",
        snapshot_methods=["stats"],
        isolation=isolation,
    )
    srv.snapshot("stats", {"count": 7})
    srv.start()
    try:
        with Client(str(srv.unix_path)) as c:
            assert c.call("ping") == "pong"
            assert c.call("stats")["count"] == 7
            with pytest.raises(RpcError):
                c.call("no_such_method")
    finally:
        srv.stop()
