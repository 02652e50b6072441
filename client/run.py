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

    def history(self, n: int = 20, run: int | None = None) -> list[CycleRecord]: ...

    def stats(self, run: int | None = None, *, cycles: tuple[int, int] | None = None) -> Stats: ...

    def stop_cycling(self) -> dict[str, Any]: ...

    def unsubscribe(self, *topics: str) -> list[str]: ...


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


class RunHandle:
    """What `Run` and `aio.AsyncRun` share: the run's start reply, its tracker and its end."""

    def __init__(self, client: Any, started: Cycling, added_topics: list[str], timeout: float | None) -> None:
        self.client = client
        #: start_cycling's reply: run_id, first_cycle, period_ns, count, targets, warnings.
        self.started = started
        self.run_id = started["run_id"]
        self.timeout = timeout
        self._tracker = RunTracker(started)
        self._added_topics = added_topics  # the topics subscribed for the run, dropped at its end

    @property
    def info(self) -> RunInfo | None:
        """The run's record once it has ended (first and last cycle, end reason), else None."""
        return self._tracker.info

    @property
    def ended(self) -> bool:
        return self._tracker.ended


class Run(RunHandle):
    """One run started by `Client.run`; iterate it for its strokes (see the module's doc)."""

    client: Client

    def __iter__(self) -> Iterator[CycleRecord]:
        tracker = self._tracker
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
        assert self._tracker.info is not None
        return self._tracker.info

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
        if self._added_topics and self.client.connected:
            self.client.unsubscribe(*self._added_topics)
            self._added_topics = []
