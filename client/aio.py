"""The asyncio client: the same methods as `Client`, awaited, for lab code that lives in an event loop.

    import asyncio
    from usmswitch.client import AsyncClient

    async def main():
        async with AsyncClient() as rig:
            run = await rig.run(count=100, period="50ms", target="12ms")
            async for rec in run:
                print(rec["cycle"], rec["error_ns"])
            print((await run.stats())["all"]["error_std_ns"])

    asyncio.run(main())

Every method of `Client` (status, stats, set_target, history, runs ...) is here and returns an
awaitable of the same result. Calls may be in flight at once (from several tasks); a reader task
sorts replies and notifications. Timeouts are float seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
from collections import deque
from collections.abc import AsyncIterator, Iterable
from typing import Any

import msgpack

from usmswitch.protocol.sockets import check_peer, check_socket_owner
from usmswitch.protocol.wire import MAX_MSGID, REQUEST, estop_socket_path

from .api import Api, Duration, find_socket
from .connection import (
    DEFAULT_TIMEOUT,
    MAX_BUFFERED_NOTIFICATIONS,
    ConnectionClosed,
    check_timeout,
    closed_error,
    connect_unix,
    parse_address,
    result_of,
    sort_message,
)
from .run import QueueWatch, RunHandle
from .types import CycleRecord, Notification, RunInfo, Stats


async def _connect_unix_async(path: str, timeout: float | None) -> socket.socket:
    """A connected Unix socket, as the blocking Client's (connection.connect_unix) without
    blocking the loop: at once while the backlog has room; past it (a connection flood) a
    non-blocking connect is refused, never queued, so the connect waits its turn in the
    kernel's queue on a worker thread, for up to `timeout`."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.setblocking(False)
    try:
        sock.connect(path)
    except BlockingIOError:
        sock.close()
        return await asyncio.get_running_loop().run_in_executor(None, connect_unix, path, timeout)
    except OSError:
        sock.close()
        raise
    return sock


class AsyncClient(Api):
    """An asyncio connection to the daemon (see the module's doc); `async with` connects and closes."""

    def __init__(
        self,
        address: str | os.PathLike[str] | None = None,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        token: str | None = None,
        rig: str | None = None,
        max_reply_bytes: int = 64 << 20,
    ) -> None:
        self.timeout = check_timeout("timeout", timeout)
        if address is None:
            address = find_socket(rig)
        self.family, self.address, url_token = parse_address(address)
        env_token = os.environ.get("USMSWITCH_TOKEN") if self.family == "tcp" else None
        self.token = token or url_token or env_token
        self.max_reply_bytes = max_reply_bytes
        self.topics: set[str] = set()
        self._run_holds: dict[str, int] = {}  # topic -> run objects holding it (hold_topics)
        #: Notifications lost on this side because nobody read them.
        self.local_dropped = 0
        self._writer: asyncio.StreamWriter | None = None
        self._reader_task: asyncio.Task[None] | None = None
        self._packer = msgpack.Packer(use_bin_type=True, autoreset=True)
        self._msgid = 0
        self._waiting: dict[int, asyncio.Future[list[Any]]] = {}
        self._notes: deque[Notification] = deque()
        self._note_ready = asyncio.Event()
        self._closed: ConnectionClosed | None = None

    async def connect(self) -> AsyncClient:
        """Open the connection (and authenticate over TCP)."""
        if self.family == "tcp":
            if not self.token:
                raise ValueError("a TCP connection needs a token: AsyncClient(..., token=...) or ?token=")
            host, port = self.address
            reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), self.timeout)
        else:
            owner = check_socket_owner(self.address)
            sock = await _connect_unix_async(self.address, self.timeout)
            reader, writer = await asyncio.wait_for(asyncio.open_unix_connection(sock=sock), self.timeout)
            try:
                check_peer(writer.get_extra_info("socket"), owner)
            except OSError:
                writer.close()
                raise
        self._writer = writer
        self._closed = None
        self._reader_task = asyncio.get_running_loop().create_task(self._read_loop(reader))
        if self.family == "tcp":
            await self.call("auth", self.token)
        return self

    async def close(self) -> None:
        """Close the connection; calls still waiting fail with ConnectionClosed."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._reader_task is not None:
            self._reader_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader_task
            self._reader_task = None
        self._fail_all(ConnectionClosed(f"connection to {self.address} closed"))

    async def __aenter__(self) -> AsyncClient:
        return await self.connect()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        return self._writer is not None and self._closed is None

    # -- calls -----------------------------------------------------------------------------------
    async def call(self, method: str, *params: Any) -> Any:  # type: ignore[override]
        """Send one request and wait for its result; raises RpcError with the server's code."""
        if self._writer is None or self._closed is not None:
            raise self._closed or ConnectionClosed("not connected: await connect()")
        self._msgid = (self._msgid + 1) & MAX_MSGID
        msgid = self._msgid
        fut: asyncio.Future[list[Any]] = asyncio.get_running_loop().create_future()
        self._waiting[msgid] = fut
        try:
            self._writer.write(self._packer.pack([REQUEST, msgid, method, list(params)]))
            await self._writer.drain()
            reply = await asyncio.wait_for(fut, self.timeout)
        except TimeoutError:
            raise TimeoutError(f"no reply from {self.address} within {self.timeout:g} s") from None
        except (ConnectionResetError, BrokenPipeError) as exc:
            raise ConnectionClosed(f"connection to {self.address} broke: {exc}") from exc
        finally:
            self._waiting.pop(msgid, None)
        return result_of(reply)

    async def estop(self) -> dict[str, Any]:
        """Stop the drive now and latch FAULT (through the estop socket when there is one)."""
        if self.family == "unix":
            urgent = estop_socket_path(self.address)
            if urgent.exists():
                try:
                    async with AsyncClient(urgent, timeout=self.timeout) as c:
                        return await c.call("estop")
                except (ConnectionClosed, OSError):
                    pass  # busy or gone: the main connection still carries it
        return await self.call("estop")

    # -- notifications ---------------------------------------------------------------------------
    async def next_notification(self, timeout: float | None = None) -> Notification:
        """The next notification, waiting up to `timeout` seconds (None: forever)."""
        timeout = check_timeout("timeout", timeout)
        while not self._notes:
            if self._closed is not None:
                raise self._closed
            self._note_ready.clear()
            try:
                await asyncio.wait_for(self._note_ready.wait(), timeout)
            except TimeoutError:
                raise TimeoutError(f"no notification from {self.address} within {timeout:g} s") from None
        return self._notes.popleft()

    async def subscribe(self, *topics: str, timeout: float | None = None) -> AsyncSubscription:
        """Subscribe to topics (default "stroke"); `async for` over the result yields Notifications."""
        wanted = list(topics) or ["stroke"]
        self.topics = set((await self.call("subscribe", wanted))["topics"])
        return AsyncSubscription(self, wanted, check_timeout("timeout", timeout))

    async def hold_topics(self, topics: Iterable[str]) -> list[str]:
        """Subscribe `topics` for a run object, counted (as `Client.hold_topics`)."""
        holds = self._run_holds
        held = [t for t in topics if t in holds or t not in self.topics]
        new = [t for t in held if t not in holds]
        if new:
            self.topics = set((await self.call("subscribe", new))["topics"])
        for t in held:
            holds[t] = holds.get(t, 0) + 1
        return held

    async def release_topics(self, topics: Iterable[str]) -> None:
        """A run object is done with `topics`: unsubscribed when no other holds them."""
        holds = self._run_holds
        gone = []
        for t in topics:
            holds[t] -= 1
            if not holds[t]:
                del holds[t]
                gone.append(t)
        if gone and self.connected:
            await self.unsubscribe(*gone)

    async def unsubscribe(self, *topics: str) -> list[str]:
        """Stop notifications of `topics` (all when none given); returns the topics still subscribed."""
        reply = await (self.call("unsubscribe", list(topics)) if topics else self.call("unsubscribe"))
        self.topics = set(reply["topics"])
        return sorted(self.topics)

    async def run(  # type: ignore[override]
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
    ) -> AsyncRun:
        """Start a run; `async for` over the result yields its strokes and ends with the run."""
        added = await self.hold_topics(("stroke", "run"))
        try:
            started = await self.start_cycling(
                period,
                count,
                target=target,
                allow_late=allow_late,
                take_over=take_over,
                label=label,
                notes=notes,
            )
        except BaseException:
            await self.release_topics(added)
            raise
        return AsyncRun(self, started, added, check_timeout("timeout", timeout))

    async def submit(  # type: ignore[override]
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
    ) -> AsyncQueuedRun:
        """Queue a run; `async for` over the result waits for its turn, then yields its strokes."""
        added = await self.hold_topics(("stroke", "run", "queue"))
        try:
            entry = await self.submit_entry(
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
            await self.release_topics(added)
            raise
        return AsyncQueuedRun(self, entry, added, check_timeout("timeout", timeout))

    # -- the reader task ---------------------------------------------------------------------------
    async def _read_loop(self, reader: asyncio.StreamReader) -> None:
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=self.max_reply_bytes)
        try:
            while True:
                data = await reader.read(262_144)
                if not data:
                    break
                unpacker.feed(data)
                for msg in unpacker:
                    reply, note = sort_message(msg)
                    if reply is not None:
                        fut = self._waiting.get(reply[1])
                        if fut is not None and not fut.done():
                            fut.set_result(reply)
                    elif note is not None:
                        if len(self._notes) >= MAX_BUFFERED_NOTIFICATIONS:
                            self._notes.popleft()
                            self.local_dropped += 1
                        self._notes.append(note)
                        self._note_ready.set()
            self._fail_all(closed_error(self._notes, self.address))
        except (ConnectionError, OSError) as exc:
            self._fail_all(ConnectionClosed(f"connection to {self.address} broke: {exc}"))
        except msgpack.UnpackException as exc:
            self._fail_all(ConnectionClosed(f"unreadable reply from {self.address}: {exc}"))

    def _fail_all(self, exc: ConnectionClosed) -> None:
        if self._closed is None:
            self._closed = exc
        for fut in self._waiting.values():
            if not fut.done():
                fut.set_exception(exc)
        self._note_ready.set()  # a waiting next_notification sees the close


class AsyncSubscription:
    """`async for` over a subscription's notifications, each a `Notification`."""

    def __init__(self, client: AsyncClient, topics: list[str], timeout: float | None) -> None:
        self.client = client
        self.topics = topics
        self.timeout = timeout
        self.dropped = 0

    def __aiter__(self) -> AsyncIterator[Notification]:
        return self._notifications()

    async def _notifications(self) -> AsyncIterator[Notification]:
        while True:
            note = await self.client.next_notification(self.timeout)
            if note.topic == "dropped":
                self.dropped += note.dropped
            elif note.topic in self.topics:
                yield note

    async def close(self) -> None:
        if self.client.connected:
            await self.client.unsubscribe(*self.topics)


class AsyncRun(RunHandle):
    """One run started by `AsyncClient.run`: `async for` yields its strokes, then ends."""

    client: AsyncClient

    def __aiter__(self) -> AsyncIterator[CycleRecord]:
        return self._strokes()

    async def _strokes(self) -> AsyncIterator[CycleRecord]:
        tracker = self._tracker
        assert tracker is not None
        while not tracker.ended:
            rec, missing = tracker.accept(await self.client.next_notification(self.timeout))
            history = (
                await self.client.history(tracker.history_wanted(missing), self.run_id) if missing else []
            )
            for r in tracker.deliver(rec, missing, history):
                yield r
        if self._added_topics:
            await self.client.release_topics(self._added_topics)
            self._added_topics = []

    async def wait(self) -> RunInfo:
        """Wait for the run to end; returns its record."""
        async for _ in self:
            pass
        info = self.info
        assert info is not None
        return info

    async def stats(self) -> Stats:
        """This run's statistics, in the shape of `stats()`."""
        return await self.client.stats(self.run_id)

    async def stop(self) -> dict[str, Any]:
        """Stop the run after the stroke in progress."""
        return await self.client.stop_cycling()


class AsyncQueuedRun(AsyncRun):
    """A run submitted to the queue (`AsyncClient.submit`): `async for` waits for its turn, then
    yields its strokes; `entry` is its queue entry as last heard of."""

    def __init__(
        self, client: Any, entry: dict[str, Any], added_topics: list[str], timeout: float | None
    ) -> None:
        super().__init__(client, None, added_topics, timeout)
        self._watch = QueueWatch(entry)

    @property
    def entry(self) -> dict[str, Any]:
        return self._watch.entry

    async def _strokes(self) -> AsyncIterator[CycleRecord]:
        client = self.client
        if self._tracker is None:
            queue = (await client.status())["queue"]
            started, ended = self._watch.locate(queue, await client.runs(1000))
            if started is not None:
                self._begin(started)
            if ended is not None:  # over already: its end as its notification would have said it
                tracker = self._tracker
                assert tracker is not None
                rec, missing = tracker.accept(Notification("run", ended))
                history = (
                    await client.history(tracker.history_wanted(missing), self.run_id) if missing else []
                )
                for r in tracker.deliver(rec, missing, history):
                    yield r
        while self._tracker is None:
            started = self._watch.accept(await client.next_notification(self.timeout))
            if started is not None:
                self._begin(started)
        async for rec in super()._strokes():
            yield rec

    async def cancel(self, *, operator: bool = False) -> dict[str, Any]:
        """Take it out of the queue before its turn (its submitter, or an operator)."""
        self._watch.entry = await self.client.queue_cancel(self._watch.entry_id, operator=operator)
        return self._watch.entry
