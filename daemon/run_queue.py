"""The queue of runs (issue 38): a shared rig's runs wait their turn instead of being refused.

A run submitted (`submit`) waits in the queue, highest `priority` first, then in the order submitted.
The queue starts its head when nothing else runs: at once when the rig is idle (or runs only the
daemon's own start-up run, which gives way), else when the run going ends `done`, `stopped` or
taken over, or, after a FAULT, once a person resets it (`reset_fault`): a fault never starts the next
run by itself. A submission with `take_over` starts at once, ending the run going, as `start_cycling`'s
`take_over` does; without it no run is ever ended to make room. A waiting entry's priority may be
changed (`queue_priority`: its submitter's or an operator's), which moves it in the queue.

Every entry is kept in the records file (`run_queue`), so a restart finds what waited: the queue is
then paused until an operator resumes it. An entry becomes its run exactly once: the run's settings
name its `queue_entry`, written with the run's row, and an entry whose run is in the file is started,
whatever the kill -9 left of its own row (`load`).

None of this is on the loop's timing path: decisions are made on the bridge and record writer
threads, and a start is a request served in the loop's slack, as a client's `start_cycling` is.
"""

from __future__ import annotations

import json
import queue
import sqlite3
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import structlog

from usmswitch.protocol.record import RunRecord
from usmswitch.protocol.wire import ErrorCode, RpcError

from .run_notes import owner_person

log = structlog.get_logger("usmswitch.queue")

QUEUED, STARTED, CANCELLED, REFUSED = "queued", "started", "cancelled", "refused"
#: The run params an entry keeps, in start_run's order after them: what `submit` takes.
PARAMS = ("period_ns", "count", "target_ns", "allow_late", "take_over", "label", "notes")


@dataclass
class Entry:
    """One submitted run."""

    entry: int
    owner: str
    priority: int
    params: dict[str, Any]
    submitted_wall_ns: int
    state: str = QUEUED
    run_id: int | None = None
    first_cycle: int | None = None
    reason: str | None = None
    changed_wall_ns: int | None = None

    def order(self) -> tuple[bool, int, int]:
        """Queue order: take-overs first, then the highest priority, then the first submitted."""
        return (not self.params.get("take_over"), -self.priority, self.entry)

    def to_dict(self) -> dict[str, Any]:
        return {
            "entry": self.entry,
            "owner": self.owner,
            "priority": self.priority,
            **self.params,
            "submitted_wall_ns": self.submitted_wall_ns,
            "state": self.state,
            "run_id": self.run_id,
            "first_cycle": self.first_cycle,
            "reason": self.reason,
        }


# -- the records file (each run by the record writer, `RecordStore.write`) ---------------------------
def _insert(entry: Entry) -> Callable[[sqlite3.Connection], int]:
    def insert(conn: sqlite3.Connection) -> int:
        cur = conn.execute(
            "INSERT INTO run_queue (submitted_wall_ns, owner, priority, params, state)"
            " VALUES (?, ?, ?, ?, ?)",
            (entry.submitted_wall_ns, entry.owner, entry.priority, json.dumps(entry.params), QUEUED),
        )
        return int(cur.lastrowid or 0)

    return insert


def _update(entry: Entry) -> Callable[[sqlite3.Connection], None]:
    values = (entry.state, entry.run_id, entry.first_cycle, entry.reason, entry.changed_wall_ns, entry.entry)

    def update(conn: sqlite3.Connection) -> None:
        conn.execute(
            "UPDATE run_queue SET state = ?, run_id = ?, first_cycle = ?, reason = ?, changed_wall_ns = ?"
            " WHERE entry = ?",
            values,
        )

    return update


def _reorder(entry_id: int, priority: int) -> Callable[[sqlite3.Connection], None]:
    def reorder(conn: sqlite3.Connection) -> None:
        conn.execute("UPDATE run_queue SET priority = ? WHERE entry = ?", (priority, entry_id))

    return reorder


def _load(conn: sqlite3.Connection) -> list[Entry]:
    """The entries still queued; one whose run is in the file (killed between the run's row and the
    entry's) is marked started here, never run twice."""
    ran = {
        int(r[0]): (int(r[1]), int(r[2]))
        for r in conn.execute(
            "SELECT json_extract(settings, '$.queue_entry'), run_id, first_cycle FROM runs"
            " WHERE json_extract(settings, '$.queue_entry') IS NOT NULL"
        )
    }
    out = []
    rows = conn.execute(
        "SELECT entry, owner, priority, params, submitted_wall_ns FROM run_queue WHERE state = ?"
        " ORDER BY entry",
        (QUEUED,),
    ).fetchall()
    for entry_id, owner, priority, params, wall in rows:
        if entry_id in ran:
            run_id, first = ran[entry_id]
            conn.execute(
                "UPDATE run_queue SET state = ?, run_id = ?, first_cycle = ?, changed_wall_ns = ?"
                " WHERE entry = ?",
                (STARTED, run_id, first, time.time_ns(), entry_id),
            )
            continue
        out.append(Entry(entry_id, owner, priority, json.loads(params), wall))
    return out


class _Deciding(Exception):
    """The entry's start is being decided: a change to it waits for that (`_when_decided`)."""


class RunQueue:
    """The queue: what waits, whether it is paused, the entry whose run is going."""

    def __init__(
        self,
        write: Callable[[Callable[[sqlite3.Connection], Any]], Future[Any]],
        start: Callable[[Entry], Future[Any]],
        publish: Callable[[dict[str, Any]], None],
        gate: Callable[[], object] = lambda: None,
    ) -> None:
        """`write`: RecordStore.write; `start(entry)`: its run opened in the loop's slack, the future's
        result the Cycling reply, None to wait (FAULT, another's run going), or its refusal;
        `publish`: a `queue` notification; `gate`: the loop's `wait_turn`, before the queue's own
        thread does its Python work."""
        self._write = write
        self._start = start
        self._publish = publish
        self._gate = gate
        # What follows a start happens on a thread of the queue's own, not in the loop's slack
        # where the start's future is completed.
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._queued: dict[int, Entry] = {}
        self._starting: int | None = None
        self._again = False  # asked to start the next while a start was deciding: ask again after
        # Changes to the entry whose start is being decided (a cancel, a new priority), made once
        # that is decided: each submit looks at the head even while another's run goes, so a
        # submitter's cancel right after its submit would otherwise meet that look.
        self._after_look: list[Callable[[], None]] = []
        #: The entry whose run is going (None: none, or a run that is not the queue's).
        self.current: Entry | None = None
        self.paused = False

    def start(self) -> None:
        """Start the queue's thread."""
        self._thread = threading.Thread(target=self._work, name="usmswitch-queue", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the queue's thread (the daemon is stopping)."""
        if self._thread is not None:
            self._jobs.put(None)
            self._thread.join(5)
            self._thread = None

    def _work(self) -> None:
        while (job := self._jobs.get()) is not None:
            self._gate()
            try:
                job()
            except Exception:  # a bug must not stop the queue for good
                log.exception("queue job failed")

    def load(self, timeout_s: float = 30.0) -> None:
        """At start: what the file's queue holds waits, paused until an operator resumes it."""
        entries = self._write(_load).result(timeout_s)
        with self._lock:
            self._queued = {e.entry: e for e in entries}
            self.paused = bool(entries)
        if entries:
            log.info("queue kept from before: paused until resumed", queued=[e.entry for e in entries])

    # -- requests (the bridge thread) ---------------------------------------------------------------
    def submit(self, params: dict[str, Any], owner: str, priority: int) -> Future[dict[str, Any]]:
        """Keep a new entry in the file, then put it in the queue; answered with it (and its place)."""
        entry = Entry(0, owner, priority, params, time.time_ns())
        done: Future[dict[str, Any]] = Future()

        def kept(fut: Future[int]) -> None:
            exc = fut.exception()
            if exc is not None:
                done.set_exception(exc)
                return
            entry.entry = fut.result()
            with self._lock:
                self._queued[entry.entry] = entry
                view = self._view(entry)
            log.info(
                "run queued", entry=entry.entry, owner=owner, priority=priority, position=view["position"]
            )
            self._changed("submitted", entry)
            done.set_result(view)
            self.next()

        self._write(_insert(entry)).add_done_callback(kept)
        return done

    def cancel(self, entry_id: int, owner: str, operator: bool) -> Future[dict[str, Any]]:
        """A queued entry taken out: its submitter's (the same `user@host`), or any with `operator`.
        Answered at once, or, while its start is being decided, once that is (it may have started)."""

        def take_out() -> dict[str, Any]:
            with self._lock:
                entry = self._waiting(entry_id, "queue_cancel", owner, operator, "cancels it", "cancel N")
                del self._queued[entry_id]
            self._leave(entry, CANCELLED, f"cancelled by {owner or 'a client'}")
            return entry.to_dict()

        return self._when_decided(entry_id, take_out)

    def set_priority(
        self, entry_id: int, priority: int, owner: str, operator: bool
    ) -> Future[dict[str, Any]]:
        """A queued entry's priority changed, and with it its place: its submitter's (the same
        `user@host`), or any with `operator`. Answered with the entry and its new place once the
        change is in the file (and, while its start is being decided, once that is)."""
        done: Future[dict[str, Any]] = Future()

        def move() -> None:
            with self._lock:
                entry = self._waiting(
                    entry_id, "queue_priority", owner, operator, "reorders it", "priority N P"
                )
                entry.priority = priority
                view = self._view(entry)
            log.info("queued run reordered", entry=entry_id, priority=priority, position=view["position"])
            self._changed("reordered", entry)

            def kept(fut: Future[None]) -> None:
                exc = fut.exception()
                if exc is not None:
                    done.set_exception(exc)
                else:
                    done.set_result(view)

            self._write(_reorder(entry_id, priority)).add_done_callback(kept)

        def refused(fut: Future[None]) -> None:  # `move`'s own outcome is `done`'s, once written
            exc = fut.exception()
            if exc is not None:
                done.set_exception(exc)

        self._when_decided(entry_id, move).add_done_callback(refused)
        return done

    def _waiting(self, entry_id: int, method: str, owner: str, operator: bool, rule: str, ctl: str) -> Entry:
        """The queued entry `entry_id` for `method` by `owner` (the lock held), or why not: not
        queued (started: its run named), another's without `operator`, or its start being decided."""
        entry = self._queued.get(entry_id)
        if entry is None:
            going = self.current
            if going is not None and going.entry == entry_id:
                raise RpcError(
                    ErrorCode.STATE,
                    f"{method}: entry {entry_id} has started as run {going.run_id}: stop_cycling ends it",
                )
            raise RpcError(ErrorCode.INVALID_PARAMS, f"{method}: entry {entry_id} is not queued")
        if not operator and owner_person(entry.owner) != owner_person(owner):
            raise RpcError(
                ErrorCode.STATE,
                f"{method}: entry {entry_id} is {owner_person(entry.owner)}'s: its submitter {rule},"
                f" or an operator (operator=True, `usmswitchctl queue {ctl} --operator`)",
            )
        if self._starting == entry_id:
            raise _Deciding
        return entry

    def _when_decided(self, entry_id: int, change: Callable[[], Any]) -> Future[Any]:
        """`change()` now, or once the start being decided for `entry_id` is decided."""
        done: Future[Any] = Future()

        def attempt() -> None:
            try:
                done.set_result(change())
            except _Deciding:
                with self._lock:
                    if self._starting == entry_id:
                        self._after_look.append(attempt)
                        return
                attempt()  # decided between the two looks: at once
            except Exception as exc:
                done.set_exception(exc)

        attempt()
        return done

    def set_paused(self, paused: bool, operator: bool) -> dict[str, Any]:
        """Pause (no next run starts; the one going goes on) or resume; an operator's to do."""
        if not operator:
            verb = "pause" if paused else "resume"
            raise RpcError(
                ErrorCode.STATE,
                f"queue_{verb}: the queue is everyone's: an operator {verb}s it (operator=True,"
                f" `usmswitchctl queue {verb} --operator`)",
            )
        with self._lock:
            changed = self.paused != paused
            self.paused = paused
        if changed:
            log.info("queue paused" if paused else "queue resumed")
            self._changed("paused" if paused else "resumed", None)
        self.next()
        return self.snapshot()

    def snapshot(self) -> dict[str, Any]:
        """For `status`: paused or not, the entry whose run is going, what waits in order."""
        with self._lock:
            waiting = sorted(self._queued.values(), key=Entry.order)
            return {
                "paused": self.paused,
                "current": None if self.current is None else self.current.to_dict(),
                "queued": [{**e.to_dict(), "position": i} for i, e in enumerate(waiting, 1)],
            }

    # -- what moves it ------------------------------------------------------------------------------
    def on_run(self, run: RunRecord) -> None:
        """A run's row committed (the record writer's thread): an end may let the next start."""
        if run.end_reason is None:
            return
        with self._lock:
            if self.current is not None and self.current.run_id == run.run_id:
                self.current = None
        if run.end_reason.startswith("fault") or run.end_reason == "shutdown":
            return  # a fault waits for a person's reset; a shutdown for the restart's resume
        self.next()

    def next(self) -> None:
        """Start the head of the queue if it may start now (any thread; the start in the loop's slack)."""
        with self._lock:
            if self._starting is not None:
                self._again = True  # what made this call may have come after that start's look
                return
            if self.paused or not self._queued:
                return
            head = min(self._queued.values(), key=Entry.order)
            self._starting = head.entry
        self._start(head).add_done_callback(lambda fut: self._jobs.put(lambda: self._started(head, fut)))

    def _started(self, entry: Entry, fut: Future[Any]) -> None:
        exc = fut.exception()
        result = None if exc is not None else fut.result()
        with self._lock:
            self._starting = None
            again, self._again = self._again, False
            deferred, self._after_look = self._after_look, []
            waits = result is None and exc is None
            if not waits:
                self._queued.pop(entry.entry, None)
            if result is not None:  # in one step with leaving the queue: `status` always has it
                entry.run_id, entry.first_cycle = result["run_id"], result["first_cycle"]
                entry.state = STARTED
                self.current = entry
        for change in deferred:  # before the next look, which may pick this entry again
            change()
        if waits:  # not now: a FAULT, or another's run going; tried again when that changes
            if again:
                self.next()  # a run ended (or a reset) while this one looked: look again
            return
        if exc is not None:
            message = exc.message if isinstance(exc, RpcError) else str(exc)
            log.warning("queued run refused at its start", entry=entry.entry, reason=message)
            self._leave(entry, REFUSED, message)
            self.next()
            return
        log.info("queued run started", entry=entry.entry, run=entry.run_id)
        self._leave(entry, STARTED, None)

    def _leave(self, entry: Entry, state: str, reason: str | None) -> None:
        entry.state, entry.reason, entry.changed_wall_ns = state, reason, time.time_ns()
        self._write(_update(entry))
        self._changed(state, entry)

    def _view(self, entry: Entry) -> dict[str, Any]:
        waiting = sorted(self._queued.values(), key=Entry.order)
        position = waiting.index(entry) + 1 if entry in waiting else None
        return {**entry.to_dict(), "position": position, "paused": self.paused}

    def _changed(self, change: str, entry: Entry | None) -> None:
        snap = self.snapshot()
        self._publish({"change": change, "entry": None if entry is None else entry.to_dict(), **snap})
