"""A run as a lab script sees it: its strokes, as they come, then its end.

`Client.run(...)` subscribes to "stroke" and "run" before it starts the run, so no stroke is
missed; iterating the `Run` yields exactly that run's stroke records, in cycle order, and stops
when the daemon says the run ended (its count reached, stopped, a fault, a shutdown). Strokes the
server had to drop for a slow reader are fetched back from the records (`history`), so the
iteration still holds every stroke or says which it could not get.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, Protocol

from usmswitch.protocol.wire import MAX_HISTORY

from .types import CycleRecord, Cycling, Notification, RunInfo, Stats


class Client(Protocol):
    """What a Run uses of `connection.Client` (named here: the client imports this module)."""

    @property
    def connected(self) -> bool: ...

    def next_notification(self, timeout: float | None = None) -> Notification: ...

    def status(self) -> Any: ...

    def runs(self, n: int = 20, label: str | None = None) -> list[RunInfo]: ...

    def history(self, n: int = 20, run: int | None = None) -> list[CycleRecord]: ...

    def stats(self, run: int | None = None, *, cycles: tuple[int, int] | None = None) -> Stats: ...

    def stop_cycling(self) -> dict[str, Any]: ...

    def unsubscribe(self, *topics: str) -> list[str]: ...

    def queue_cancel(self, entry: int, *, operator: bool = False) -> dict[str, Any]: ...

    def release_topics(self, topics: list[str]) -> None: ...


class RunLost(RuntimeError):
    """Strokes of the run could be neither received nor read back (the reader fell too far behind)."""


class RunTracker:
    """What a run's notifications mean, apart from any transport (the blocking and the asyncio
    client both use it): which strokes to yield, which are missing, when the run is over."""

    def __init__(self, started: Cycling) -> None:
        self.run_id = started["run_id"]
        self.next_cycle = started["first_cycle"]  # the run's strokes are consecutive cycles
        self.info: RunInfo | None = None  # set when the run has ended
        self.received = 0

    @property
    def ended(self) -> bool:
        return self.info is not None

    def accept(self, note: Notification) -> tuple[CycleRecord | None, int]:
        """One notification: (a stroke of this run, or None; how many strokes are missing before
        it, or before the run's end, to be read back first)."""
        payload = note.payload
        if note.topic == "stroke" and type(payload) is dict and payload.get("run_id") == self.run_id:
            if payload["cycle"] < self.next_cycle:
                return None, 0  # read back already
            return payload, payload["cycle"] - self.next_cycle  # type: ignore[return-value]
        if (
            note.topic == "run"
            and type(payload) is dict
            and payload.get("run_id") == self.run_id
            and payload.get("end_reason") is not None
        ):
            self.info = payload  # type: ignore[assignment]
            return None, max(0, payload["last_cycle"] - self.next_cycle + 1)
        return None, 0

    def took(self, rec: CycleRecord) -> None:
        self.next_cycle = rec["cycle"] + 1
        self.received += 1

    @staticmethod
    def history_wanted(missing: int) -> int:
        """How many of the run's last records to read back for `missing` dropped strokes."""
        return min(MAX_HISTORY, missing + 1000)

    def deliver(self, rec: CycleRecord | None, missing: int, history: list[CycleRecord]) -> list[CycleRecord]:
        """What `accept` said, as the strokes to yield in order: the `missing` ones read back from
        `history` (a read of `history_wanted(missing)` records), then `rec`."""
        out = self.fill(history, self.next_cycle + missing) if missing else []
        if rec is not None:
            out.append(rec)
        for r in out:
            self.took(r)
        return out

    def fill(self, history: list[CycleRecord], up_to: int) -> list[CycleRecord]:
        """The missing strokes (cycles next_cycle..up_to-1) from a `history` read of the run."""
        want = [r for r in history if self.next_cycle <= r["cycle"] < up_to]
        if len(want) != up_to - self.next_cycle:
            raise RunLost(
                f"run {self.run_id}: strokes {self.next_cycle}..{up_to - 1} were dropped and the last "
                f"{MAX_HISTORY} records no longer hold them all; read the run with "
                f"`usmswitchctl export --run {self.run_id}`"
            )
        return want


class QueuedRunNotStarted(RuntimeError):
    """A queued run left the queue without running: cancelled, or refused when its turn came."""


class QueueWatch:
    """What the notifications mean for a queued run until it starts (`Client.submit`): its run's id
    and first cycle, from the run's opening (its settings name the entry) or the queue's word."""

    def __init__(self, entry: dict[str, Any]) -> None:
        #: The entry as last heard of: its state, its place, its run once started.
        self.entry = entry
        self.entry_id: int = entry["entry"]

    def accept(self, note: Notification) -> Cycling | None:
        """The run's start (run_id, first_cycle) when `note` tells it; QueuedRunNotStarted when the
        entry was cancelled or refused."""
        payload = note.payload
        if type(payload) is not dict:
            return None
        if note.topic == "run" and (payload.get("settings") or {}).get("queue_entry") == self.entry_id:
            return {"run_id": payload["run_id"], "first_cycle": payload["first_cycle"]}  # type: ignore[typeddict-item]
        entry = payload.get("entry")
        if note.topic != "queue" or type(entry) is not dict or entry.get("entry") != self.entry_id:
            return None
        self.entry = entry
        if entry["state"] == "started":
            return {"run_id": entry["run_id"], "first_cycle": entry["first_cycle"]}  # type: ignore[typeddict-item]
        self._not_started()
        return None

    def _not_started(self) -> None:
        if self.entry["state"] in ("cancelled", "refused"):
            raise QueuedRunNotStarted(
                f"queued run {self.entry_id} was {self.entry['state']}: {self.entry['reason']}"
            )

    def locate(self, queue: dict[str, Any], runs: list[RunInfo]) -> tuple[Cycling | None, RunInfo | None]:
        """Where the entry is now, from `status()["queue"]` and `runs()` (its notifications may have
        been read by another run object on the same connection): (its run's start, None while it
        waits; that run's record once it has ended). QueuedRunNotStarted when it left the queue
        without running."""
        self._not_started()
        for entry in (queue.get("current"), *queue.get("queued", ())):
            if entry and entry["entry"] == self.entry_id:
                self.entry = entry
                if entry["state"] != "started":
                    return None, None
                return {"run_id": entry["run_id"], "first_cycle": entry["first_cycle"]}, None  # type: ignore[typeddict-item]
        for run in runs:
            if (run.get("settings") or {}).get("queue_entry") == self.entry_id:
                started = {"run_id": run["run_id"], "first_cycle": run["first_cycle"]}
                return started, (run if run["end_reason"] is not None else None)  # type: ignore[return-value]
        raise QueuedRunNotStarted(
            f"queued run {self.entry_id} left the queue without running (cancelled or refused)"
        )


class RunHandle:
    """What `Run` and `aio.AsyncRun` share: the run's start reply, its tracker and its end (a queued
    run's start is known once its turn comes: `started` None until then)."""

    def __init__(
        self, client: Any, started: Cycling | None, added_topics: list[str], timeout: float | None
    ) -> None:
        self.client = client
        #: start_cycling's reply: run_id, first_cycle, period_ns, count, targets, warnings (a queued
        #: run's: run_id and first_cycle, once it started).
        self.started = started
        self.run_id: int | None = None
        self.timeout = timeout
        self._tracker: RunTracker | None = None
        self._added_topics = added_topics  # the topics subscribed for the run, dropped at its end
        if started is not None:
            self._begin(started)

    def _begin(self, started: Cycling) -> None:
        self.started = started
        self.run_id = started["run_id"]
        self._tracker = RunTracker(started)

    @property
    def info(self) -> RunInfo | None:
        """The run's record once it has ended (first and last cycle, end reason), else None."""
        return None if self._tracker is None else self._tracker.info

    @property
    def ended(self) -> bool:
        return self._tracker is not None and self._tracker.ended


class Run(RunHandle):
    """One run started by `Client.run`; iterate it for its strokes (see the module's doc)."""

    client: Client

    def __iter__(self) -> Iterator[CycleRecord]:
        tracker = self._tracker
        assert tracker is not None
        client = self.client
        while not tracker.ended:
            rec, missing = tracker.accept(client.next_notification(self.timeout))
            history = client.history(tracker.history_wanted(missing), self.run_id) if missing else []
            yield from tracker.deliver(rec, missing, history)
        self._unsubscribe()

    def wait(self) -> RunInfo:
        """Wait for the run to end (reading and dropping its strokes); returns its record."""
        for _ in self:
            pass
        info = self.info
        assert info is not None
        return info

    def stats(self) -> Stats:
        """This run's statistics, in the shape of `Client.stats()`."""
        return self.client.stats(self.run_id)

    def stop(self) -> dict[str, Any]:
        """Stop the run after the stroke in progress (iterating then ends)."""
        return self.client.stop_cycling()

    def __enter__(self) -> Run:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        # Leaving the block by an error (Ctrl-C included) stops the rig: no run outlives its script.
        if exc_type is not None and not self.ended and self.client.connected:
            self.stop()

    def _unsubscribe(self) -> None:
        if self._added_topics:
            self.client.release_topics(self._added_topics)
            self._added_topics = []


class QueuedRun(Run):
    """A run submitted to the queue (`Client.submit`): iterating it waits for its turn, then yields
    its strokes as `Run` does; `entry` is its queue entry as last heard of (state, place)."""

    def __init__(
        self, client: Any, entry: dict[str, Any], added_topics: list[str], timeout: float | None
    ) -> None:
        super().__init__(client, None, added_topics, timeout)
        self._watch = QueueWatch(entry)

    @property
    def entry(self) -> dict[str, Any]:
        return self._watch.entry

    def __iter__(self) -> Iterator[CycleRecord]:
        client = self.client
        if self._tracker is None:
            started, ended = self._watch.locate(client.status()["queue"], client.runs(1000))
            if started is not None:
                self._begin(started)
            if ended is not None:  # over already: its end as its notification would have said it
                yield from self._take(Notification("run", ended))
        while self._tracker is None:
            started = self._watch.accept(client.next_notification(self.timeout))
            if started is not None:
                self._begin(started)
        yield from super().__iter__()

    def _take(self, note: Notification) -> list[CycleRecord]:
        tracker = self._tracker
        assert tracker is not None
        rec, missing = tracker.accept(note)
        history = self.client.history(tracker.history_wanted(missing), self.run_id) if missing else []
        return tracker.deliver(rec, missing, history)

    def cancel(self, *, operator: bool = False) -> dict[str, Any]:
        """Take it out of the queue before its turn (its submitter, or an operator)."""
        self._watch.entry = self.client.queue_cancel(self._watch.entry_id, operator=operator)
        return self._watch.entry

    def __exit__(self, exc_type: object, *exc: object) -> None:
        # Left by an error before its turn: it leaves the queue (a run going is stopped, as Run's).
        if exc_type is not None and self._tracker is None and self.client.connected:
            self.cancel()
            return
        super().__exit__(exc_type, *exc)
