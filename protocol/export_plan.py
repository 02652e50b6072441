"""Which `export` requests a reader of an export sends, and what each reply means (docs/protocol.md
`export`). Sans I/O: `Client.export_csv` and the panel's CSV (server/rpc_process.py) drive one each
over their own transport.

A request for the cycles a..a+K-1 with `max_strokes` K is complete by construction (cycles are
unique integers), so a few such ranges are kept in flight: the server's reader processes build the
next chunks while one travels and is written (issue 36: one chunk at a time, an export over the
socket was 2.6x `sqlite3 -csv`). Where the strokes start is not known beforehand (a run's first
cycle, the next run of a label's after a gap), so an open-ended request for one stroke asks first:
its cycle is where the ranges start, none means the export is done. A range that comes back short
(a gap, or the end) stops the asking ahead; once the ranges in flight are answered, such a probe
from where they left off says whether there is more.
"""

from __future__ import annotations

from collections import deque

from .rpc_params import MAX_EXPORT_STROKES

#: Range requests kept in flight: one more than the reader processes of the server's large-reads
#: lane (Limits.max_reads, 2), so a reader that finishes a chunk starts the next one queued at once
#: instead of waiting for the client to take that chunk (and write the one before) and ask again.
AHEAD = 3
#: Strokes a chunk, as exports ask them: half the protocol's most (MAX_EXPORT_STROKES), so that an
#: export of 10,000 strokes is two chunks built at once, not one built alone; a request costs the
#: reader ~0.5 ms beside ~35 ms of SQL for its 5,000 strokes.
CHUNK = 5000
#: The highest cycle a request may name (rpc_params' bound on first_cycle and last_cycle).
MAX_CYCLE = 2**62


class ExportPlan:
    """The requests of one export from cycle `first` to `last` (None: to the end), ranges of
    `max_strokes` cycles, up to `ahead` of them in flight. Send what `requests()` returns, each as
    `export [run, first_cycle, last_cycle, max_strokes, ...]`; give each reply, oldest first, to
    `answered`, which says whether its chunk is part of the export (a probe's is not); the export is
    done when nothing is in flight after a `requests()`."""

    def __init__(
        self,
        first: int = 1,
        last: int | None = None,
        max_strokes: int = MAX_EXPORT_STROKES,
        ahead: int = AHEAD,
    ) -> None:
        if max_strokes < 1 or ahead < 1:
            raise ValueError(f"max_strokes and ahead must be >= 1, got {max_strokes} and {ahead}")
        self.max_strokes = max_strokes
        self.ahead = ahead
        self.end = MAX_CYCLE if last is None else min(last, MAX_CYCLE)
        #: The first cycle no chunk handed over has covered: where an export that broke off resumes.
        self.resume = first
        self._next: int | None = None  # the next range's first cycle; None: probe first
        self._done = False
        #: The requests in flight, oldest first: (first_cycle, last_cycle, max_strokes, a probe).
        self.in_flight: deque[tuple[int, int | None, int, bool]] = deque()

    def requests(self) -> list[tuple[int, int | None, int]]:
        """The (first_cycle, last_cycle, max_strokes) of the requests to send now (none: wait for
        a reply, or, when nothing is in flight, the export is done)."""
        if self._done:
            return []
        out: list[tuple[int, int | None, int, bool]] = []
        if self._next is not None:
            while len(self.in_flight) + len(out) < self.ahead and self._next <= self.end:
                a, b = self._next, min(self._next + self.max_strokes - 1, self.end)
                out.append((a, b, self.max_strokes, False))
                self._next = b + 1
        elif not self.in_flight and self.resume <= self.end:
            out.append((self.resume, None if self.end == MAX_CYCLE else self.end, 1, True))
        self.in_flight.extend(out)
        return [(a, b, most) for a, b, most, _ in out]

    def answered(self, strokes: int, last_cycle: int | None) -> bool:
        """The reply to the oldest request in flight, its `strokes` and `last_cycle`: True when its
        chunk is the export's next (a probe's is not: its stroke is read again in the range)."""
        a, b, _, probe = self.in_flight.popleft()
        if probe:
            if not strokes:
                self._done = True  # no stroke from `a` to the end
            else:
                assert last_cycle is not None
                self._next = self.resume = last_cycle
            return False
        assert b is not None
        self.resume = b + 1
        if strokes < b - a + 1:  # a gap or the end: none further ahead until a probe says
            self._next = None
        return True

    def restart(self) -> None:
        """The requests in flight are lost (a connection broke): ask again from `resume`."""
        self.in_flight.clear()
        self._next = None
