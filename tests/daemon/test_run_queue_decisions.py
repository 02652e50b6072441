"""The queue's changes to an entry whose start is being decided (daemon/run_queue.py).

Each submit looks at the queue's head, even while another's run goes (that look answers "wait").
Under load the look took long enough that a submitter's cancel right after its submit was refused
`entry 2 is starting now` (tests/client/test_run_queue.py, beside two CPU hogs). A change now waits
for the look's outcome: the entry still queued is changed; one that started names its run.

The queue here is the daemon's own class on a real records file; the loop's side of a start (the
decision) is a future the test completes, so the look is held open as long as the test likes.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import pytest

from usmswitch.daemon.records import RecordStore
from usmswitch.daemon.run_queue import PARAMS, Entry, RunQueue
from usmswitch.protocol.wire import RpcError

ME = "me@here pid 1 (lab.py)"
BOB = "bob@elsewhere pid 2 (bob.py)"
RUN = dict.fromkeys(PARAMS) | {"period_ns": 25_000_000, "count": 3, "allow_late": False, "take_over": False}


class Looks:
    """The queue's `start`: each look at an entry is a future the test decides."""

    def __init__(self) -> None:
        self.asked: list[tuple[Entry, Future[Any]]] = []
        self.cond = threading.Condition()

    def __call__(self, entry: Entry) -> Future[Any]:
        fut: Future[Any] = Future()
        with self.cond:
            self.asked.append((entry, fut))
            self.cond.notify_all()
        return fut

    def next(self, n: int) -> tuple[Entry, Future[Any]]:
        """The `n`th look (1-based), once the queue has asked for it."""
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.asked) >= n, 10), f"no look #{n}"
            return self.asked[n - 1]


@pytest.fixture
def queue(tmp_path: Path) -> Iterator[tuple[RunQueue, Looks, RecordStore]]:
    store = RecordStore(tmp_path / "records.sqlite", driver="sim", rig="t")
    looks = Looks()
    q = RunQueue(store.write, looks, lambda payload: None)
    q.start()
    yield q, looks, store
    q.stop()
    store.close()


def _in_file(store: RecordStore, column: str, entry: int) -> Any:
    """The entry's `column` as the records file has it (read by the record writer, in its order)."""
    sql = f"SELECT {column} FROM run_queue WHERE entry = ?"
    return store.write(lambda conn: conn.execute(sql, (entry,)).fetchone()[0]).result(10)


def test_a_cancel_during_the_look_waits_for_it_and_takes_the_entry_out(queue: Any) -> None:
    q, looks, store = queue
    view = q.submit(RUN, ME, 0).result(10)
    entry, look = looks.next(1)  # the submit's own look, held open
    assert entry.entry == view["entry"]
    cancelled = q.cancel(entry.entry, ME, False)
    assert not cancelled.done(), "answered while the entry's start was still being decided"
    look.set_result(None)  # another's run goes: the entry waits
    assert cancelled.result(10)["state"] == "cancelled"
    assert q.snapshot()["queued"] == []
    assert _in_file(store, "state", entry.entry) == "cancelled"


def test_a_cancel_during_a_look_that_starts_the_run_names_the_run(queue: Any) -> None:
    q, looks, _ = queue
    q.submit(RUN, ME, 0).result(10)
    entry, look = looks.next(1)
    cancelled = q.cancel(entry.entry, ME, False)
    look.set_result({"run_id": 7, "first_cycle": 41})
    with pytest.raises(RpcError, match=f"entry {entry.entry} has started as run 7: stop_cycling ends it"):
        cancelled.result(10)
    assert q.snapshot()["current"]["run_id"] == 7


def test_a_new_priority_during_the_look_is_made_after_it(queue: Any) -> None:
    q, looks, store = queue
    first = q.submit(RUN, ME, 0).result(10)["entry"]
    looks.next(1)[1].set_result(None)  # waits
    second = q.submit(RUN, ME, 0).result(10)["entry"]
    head, look = looks.next(2)  # the second submit looks at the head: the first
    assert head.entry == first
    moved = q.set_priority(first, 5, ME, False)
    assert not moved.done()
    look.set_result(None)
    assert (moved.result(10)["entry"], moved.result(10)["priority"]) == (first, 5)
    assert [e["entry"] for e in q.snapshot()["queued"]] == [first, second]
    assert _in_file(store, "priority", first) == 5


def test_what_is_refused_is_refused_at_once_even_during_a_look(queue: Any) -> None:
    """Another's entry without operator, an entry not queued: no wait for the look."""
    q, looks, _ = queue
    bobs = q.submit(RUN, BOB, 0).result(10)["entry"]
    looks.next(1)  # held open
    with pytest.raises(RpcError, match="bob@elsewhere's: its submitter cancels it, or an operator"):
        q.cancel(bobs, ME, False).result(0)
    with pytest.raises(RpcError, match="entry 99 is not queued"):
        q.cancel(99, ME, True).result(0)
    with pytest.raises(RpcError, match="entry 99 is not queued"):
        q.set_priority(99, 1, ME, True).result(0)
