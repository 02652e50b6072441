"""The panel's share of the queue's notifications (server/rpc_process.py's PanelConn): the first at
once, then the latest at most once per QUEUE_EVERY_S, never one decoded per edit; the other topics
as they come."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

from usmswitch.protocol.wire import Limits, note_frame
from usmswitch.server.rpc_process import QUEUE_EVERY_S, PanelConn


def test_the_queue_is_handed_to_the_panel_at_most_once_a_tick_the_latest() -> None:
    heard: list[tuple[str, Any]] = []

    async def main() -> None:
        hub = SimpleNamespace(loop=asyncio.get_running_loop(), limits=Limits())
        conn = PanelConn(hub)  # type: ignore[arg-type]
        conn.listen(lambda topic, payload: heard.append((topic, payload)))
        for k in range(50):  # an editing script's burst: 50 edits, each the whole queue
            conn.notify(note_frame("queue", {"queued": [k]}))
            if k == 10:
                conn.notify(note_frame("state", {"state": "cycling"}))
        assert heard == [("queue", {"queued": [0]}), ("state", {"state": "cycling"})]
        # asyncio runs due timers in their order: the hand-on (due after QUEUE_EVERY_S) comes
        # before this sleep's end, however late the loop runs
        await asyncio.sleep(QUEUE_EVERY_S * 1.5)
        assert heard[2:] == [("queue", {"queued": [49]})]
        await asyncio.sleep(QUEUE_EVERY_S * 1.5)  # a quiet tick: nothing more to hand on
        assert len(heard) == 3
        conn.notify(note_frame("queue", {"queued": []}))  # after the quiet: at once
        assert heard[3:] == [("queue", {"queued": []})]

    asyncio.run(main())
