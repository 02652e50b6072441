"""A live rig reached through the daemon's queue (`usmswitch-experiment ... --socket S --queue`).

On a shared rig a run going is another's: `LiveRig` is refused by it (unless `--take-over` ends
it); here the experiment waits its turn in the daemon's queue (`Client.submit`), as any script's
run does, and never ends another's run.

An experiment is several runs, each with its own mode and drive, which the rig keeps between runs
(they are the rig's settings, not the run's). Setting them while another's run goes would change
that run, and another's run started between two of the experiment's would run in the mode the
experiment left. So, once its turn comes, the experiment holds the rig until it ends, as an ARTIQ
experiment holds the hardware until it yields: its turn is a run of its own (a *hold*: slow,
strokes at the rig's settings, label `experiment-hold`), during which it sets the next run's mode
and drive; then it queues that run and the hold after it ahead of the queue (the highest priority)
and ends its hold, so the queue starts its run, then its next hold, and no one else's between
(unless another entry of the highest priority was queued before them). At its end, in its last
hold, it puts the rig's settings back as it found them when its turn came, then ends the hold: the
queue goes on. Only runs of its own are ever stopped: each stop first checks that the run going is
one of its entries. A hold is bounded (HOLD_NS of strokes): an experiment killed outright gives the
rig back within that; one that computes longer between its runs takes a new turn.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

from usmswitch.client import QueuedRun, RpcError
from usmswitch.daemon.loop import AUTOSTART_OWNER
from usmswitch.protocol.rpc_params import MAX_PRIORITY

from .data import Strokes
from .rig import LiveRig, Progress, RunSpec

MS = 1_000_000
#: How long a hold lasts at most if nothing ends it (the experiment ends it at once, normally).
HOLD_NS = 600_000_000_000
#: A hold's period at least: slow, a stroke now and then, whatever the mode set for the next run.
HOLD_PERIOD_NS = 200 * MS
HOLD_LABEL = "experiment-hold"
RUN_LABEL = "experiment"


class QueuedLiveRig(LiveRig):
    """A running daemon reached through its queue: waits its turn, then holds the rig for its runs."""

    def __init__(self, address: str | None, priority: int = 0, say: Callable[[str], None] = print) -> None:
        self.priority = priority
        self.say = say
        #: The queue entries submitted (holds and runs): only their runs are ever stopped.
        self.entries: set[int] = set()
        super().__init__(address, take_over=False)

    def _lend(self, status: dict[str, Any]) -> dict[str, Any]:
        """Wait for the turn; the settings as they are then are what `restore` puts back."""
        going = self._settings(status)["run"]
        try:
            self._take_turn()
        except BaseException:  # Ctrl-C while waiting: the turn leaves the queue
            with contextlib.suppress(Exception):
                self._cancel_waiting()
            raise
        before = self._settings(self.client.status())
        # The daemon's own start-up run gave way to the turn: started again at the end, as LiveRig does.
        autostart = going is not None and going["settings"].get("owner") == AUTOSTART_OWNER
        before["run"] = going if autostart else None
        return before

    def run(self, spec: RunSpec, progress: Progress | None = None) -> Strokes:
        c = self.client
        if self._going_entry() is None:  # a hold that ran out while the experiment computed
            self._take_turn()
        self._apply(spec)  # on the experiment's own hold: no one else's run changes
        run = c.submit(
            count=spec.count,
            period=spec.period_ns,
            target=spec.target_ns,
            allow_late=True,
            label=RUN_LABEL,
            notes=spec.name,
            priority=MAX_PRIORITY,
        )
        self.entries.add(run.entry["entry"])
        hold = self._submit_hold(MAX_PRIORITY)  # queued behind the run: the rig stays the experiment's
        self._end_own_run()  # the queue starts its head: the run
        strokes = self._follow(run, progress)
        next(iter(hold))  # its first stroke: the rig is held again
        return strokes

    def restore(self) -> list[str]:
        """In a run of its own: the settings put back, then that run ended (the queue goes on).
        Else (its turn never came, or was lost) its entries are cancelled and nothing is touched."""
        done: list[str] = []
        if self._going_entry() is not None:
            done += self._put_back(self.client.status())
        self._cancel_waiting()
        if self._end_own_run():
            done.append("cycling: the experiment's hold on the rig ended; the queue goes on")
            try:  # the daemon's start-up run, when it gave way to the turn and nothing waits
                if not self.client.status()["queue"]["queued"]:
                    done += self._start_again()
            except RpcError as exc:  # the queue started another's run meanwhile: it goes on
                done.append(f"cycling: the start-up run not started again ({exc.message})")
        self.before["run"] = None  # started again once at most
        self.restored += done
        return done

    # -- the turn and the holds ----------------------------------------------------------------------
    def _take_turn(self) -> None:
        hold = self._submit_hold(self.priority)
        e = hold.entry
        paused = " (the queue is paused: an operator resumes it)" if e.get("paused") else ""
        self.say(f"queued as entry {e['entry']}, position {e['position']}{paused}: waiting for the rig")
        next(iter(hold))  # its first stroke: the rig is the experiment's
        self.say(f"the rig is the experiment's (run {hold.run_id})")

    def _submit_hold(self, priority: int) -> QueuedRun:
        status = self.client.status()
        longest = max(status["target_on_ns"], status["target_off_ns"], status["open_delay_ns"])
        period = max(HOLD_PERIOD_NS, 2 * longest + 40 * MS)
        hold = self.client.submit(
            count=max(1, HOLD_NS // period),
            period=period,
            allow_late=True,
            label=HOLD_LABEL,
            notes="usmswitch-experiment holds the rig between its runs",
            priority=priority,
        )
        self.entries.add(hold.entry["entry"])
        return hold

    def _going_entry(self) -> int | None:
        """The experiment's entry whose run is going, if one is."""
        run = self.client.status()["run"]
        entry = None if run is None else (run.get("settings") or {}).get("queue_entry")
        return entry if entry in self.entries else None

    def _end_own_run(self) -> bool:
        """Stop the run going if it is one of the experiment's (checked just before)."""
        if self._going_entry() is None:
            return False
        self.client.stop_cycling()
        return True

    def _cancel_waiting(self) -> None:
        queued = self.client.status()["queue"]["queued"]
        for e in queued:
            if e["entry"] in self.entries:
                self.client.queue_cancel(e["entry"])
