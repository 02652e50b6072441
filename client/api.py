"""The daemon's methods as Python calls, shared by the blocking `Client` and the `AsyncClient`.

Each method turns friendly arguments into the documented params (docs/protocol.md) and returns
`self.call(...)`: the result for `Client`, an awaitable of it for `AsyncClient`. Durations are
taken as text with a unit ("12ms", "10.5 ms") or integers of nanoseconds; a bare number in text
is refused, so a target is never silently taken in the wrong unit.
"""

from __future__ import annotations

import getpass
import os
import socket
import sys
from abc import ABC, abstractmethod
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from usmswitch.protocol.record import check_label, check_notes
from usmswitch.protocol.sockets import client_socket_paths, rig_socket_path
from usmswitch.protocol.units import parse_duration_ns

from .types import CycleRecord, Cycling, RunInfo, Stats, Status, Targets

#: A duration as the client takes it: "12ms", "10.5 ms", "250us", or integer nanoseconds.
Duration = str | int


def duration_ns(name: str, value: Duration) -> int:
    """`value` in integer nanoseconds; ValueError naming the argument and the form it wants."""
    if isinstance(value, float):
        raise ValueError(
            f"{name}={value!r}: a float has no unit; write text with one, e.g. '12ms', or integer ns"
        )
    try:
        return parse_duration_ns(value)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None


def find_socket(rig: str | None = None, env: Mapping[str, str] | None = None) -> Path:
    """The daemon's socket as `usmswitchctl` finds it: rig's instance when named, else the first
    of $USMSWITCH_SOCKET, $USMSWITCH_RIG's instance, this user's daemon, the service's."""
    if rig is not None:
        return rig_socket_path(rig)
    env = os.environ if env is None else env
    # A socket named on purpose is that daemon or none: never silently another one.
    for var in ("USMSWITCH_SOCKET", "USMSWITCH_RIG"):
        if env.get(var):
            path = Path(env[var]) if var == "USMSWITCH_SOCKET" else rig_socket_path(env[var])
            if not path.exists():
                raise FileNotFoundError(
                    f"${var}={env[var]} names {path}, which does not exist (is that daemon running?); "
                    f"unset {var} to find the local daemon"
                )
            return path
    candidates = client_socket_paths(env)
    for path in candidates:
        if path.exists():
            return path
    raise FileNotFoundError(
        f"no daemon socket found (looked at {', '.join(map(str, candidates))}); "
        "pass its path, or set USMSWITCH_SOCKET"
    )


class Api(ABC):
    """The documented methods; a transport subclass provides `call(method, *params)`."""

    @abstractmethod
    def call(self, method: str, *params: Any) -> Any:
        """Send one request; its result (or an awaitable of it, for the asyncio client)."""

    def ping(self) -> str:
        """Check that the daemon's server answers ("pong")."""
        return self.call("ping")

    def status(self) -> Status:
        """State, mode, fault, driver, versions, uptime and targets."""
        return self.call("status")

    def get_target(self) -> Targets:
        """The target total time T of each direction, in ns."""
        return self.call("get_target")

    def set_target(self, target: Duration, direction: str = "both", *, allow_late: bool = False) -> Targets:
        """Set T ("12ms" or ns) for "on", "off" or "both", from the next armed stroke.

        A target below what the rig reaches (its predicted stroke plus the loop's margin) is refused
        with INVALID_PARAMS naming the shortest reachable one, unless `allow_late`.
        """
        target_ns = duration_ns("target", target)  # checked before anything is sent
        return self.call("set_target", target_ns, direction, allow_late)

    def stats(
        self, run: int | None = None, *, cycles: tuple[int, int] | None = None, label: str | None = None
    ) -> Stats:
        """Statistics of a run (default: the current or last one), of cycles (first, last), or of
        every run with `label`: pooled over all their strokes (`on`, `off`, `all`) and per run
        (`per_run`, each as `stats(run)`), with the runs (`runs`)."""
        first, last = (None, None) if cycles is None else cycles
        if label is None:  # a daemon from before labels takes three params
            return self.call("stats", run, first, last)
        return self.call("stats", run, first, last, check_label(label))

    def history(self, n: int = 20, run: int | None = None) -> list[CycleRecord]:
        """The last `n` stroke records (of one run, or any), oldest first."""
        return self.call("history", n, run)

    def export_chunk(
        self,
        run: int | None = None,
        first: int = 1,
        last: int | None = None,
        max_strokes: int = 10_000,
        label: str | None = None,
    ) -> dict[str, Any]:
        """One chunk of an export: {"strokes", "last_cycle", "csv"}, the CSV lines (no header) of up
        to `max_strokes` strokes from cycle `first` on (of a run, of the runs with `label`); ask
        again from last_cycle + 1 until none."""
        if label is None:
            return self.call("export", run, first, last, max_strokes)
        return self.call("export", run, first, last, max_strokes, check_label(label))

    def runs(self, n: int = 20, label: str | None = None) -> list[RunInfo]:
        """The last `n` runs (with that label), oldest first."""
        return self.call("runs", n) if label is None else self.call("runs", n, check_label(label))

    def switch(self, direction: str = "next") -> CycleRecord:
        """Make one stroke ("on", "off" or "next") and return its record once it has finished."""
        return self.call("switch", direction)

    def start_cycling(
        self,
        period: Duration,
        count: int = 0,
        *,
        target: Duration | None = None,
        allow_late: bool = False,
        take_over: bool = False,
        owner: str | None = None,
        label: str | None = None,
        notes: str | None = None,
    ) -> Cycling:
        """Open a run: alternate on/off strokes every `period`, `count` of them (0: until stopped),
        at `target` when given (else the current targets).

        The daemon's own start-up run (`make run`) gives way to it. A run that a client or an
        experiment started raises WrongState naming it, unless `take_over` ends it first. `owner`
        (default: this user, host, pid and program) is who the run is recorded as started by; the
        daemon's own start-up run is owned by "autostart", and gives way to any other. `label` (a
        short word: `runs --label`, `stats --label` find it) and `notes` (free text) say what the
        run is for; `annotate_run` edits them later.
        """
        period_ns = duration_ns("period", period)
        target_ns = None if target is None else duration_ns("target", target)
        who = run_owner() if owner is None else owner
        params = [period_ns, count, target_ns, allow_late, take_over, who]
        if label is not None or notes is not None:  # a daemon from before labels takes six params
            params += [check_label(label) if label else label, None if notes is None else check_notes(notes)]
        return self.call("start_cycling", *params)

    def annotate_run(
        self,
        run: int,
        notes: str | None = None,
        *,
        label: str | None = None,
        operator: bool = False,
        owner: str | None = None,
    ) -> RunInfo:
        """Set a run's notes and/or label (None: unchanged; "": cleared), during or after it; returns
        the run. A run another person started (its owner's `user@host`) is refused with WrongState
        unless `operator`: as `take_over`, a guard against editing another's run by mistake."""
        if label:
            check_label(label)
        if notes is not None:
            check_notes(notes)
        who = run_owner() if owner is None else owner
        return self.call("annotate_run", run, notes, label, who, operator)

    def submit_entry(
        self,
        period: Duration,
        count: int = 0,
        *,
        target: Duration | None = None,
        allow_late: bool = False,
        label: str | None = None,
        notes: str | None = None,
        priority: int = 0,
        take_over: bool = False,
        owner: str | None = None,
    ) -> dict[str, Any]:
        """Put a run in the daemon's queue (`submit`): it starts when its turn comes (highest
        `priority` first, then in order), after the run going ends; `take_over` starts it at once,
        ending the run going. Returns its queue entry (`entry`, `position`, `state`); `submit` (on
        Client and AsyncClient) returns a run object that follows it to its start and end."""
        period_ns = duration_ns("period", period)
        target_ns = None if target is None else duration_ns("target", target)
        if label:
            check_label(label)
        if notes is not None:
            check_notes(notes)
        who = run_owner() if owner is None else owner
        return self.call(
            "submit", period_ns, count, target_ns, allow_late, label, notes, priority, take_over, who
        )

    def queue_cancel(self, entry: int, *, operator: bool = False, owner: str | None = None) -> dict[str, Any]:
        """Take a queued run out of the queue: its submitter's (the same `user@host`), or any with
        `operator`. Returns the entry, cancelled."""
        return self.call("queue_cancel", entry, run_owner() if owner is None else owner, operator)

    def queue_priority(
        self, entry: int, priority: int, *, operator: bool = False, owner: str | None = None
    ) -> dict[str, Any]:
        """A queued run's priority changed (-1000..1000, higher first), which moves it in the queue:
        its submitter's (the same `user@host`), or any with `operator`. Returns the entry and its
        new `position`."""
        return self.call("queue_priority", entry, priority, run_owner() if owner is None else owner, operator)

    def queue_pause(self, *, operator: bool = False) -> dict[str, Any]:
        """No queued run starts until resumed (the run going goes on); an operator's to do."""
        return self.call("queue_pause", operator)

    def queue_resume(self, *, operator: bool = False) -> dict[str, Any]:
        """The queue goes on (after a restart it waits paused until this); an operator's to do."""
        return self.call("queue_resume", operator)

    def stop_cycling(self) -> dict[str, Any]:
        """Stop cycling after the stroke in progress; the reply carries the ended run."""
        return self.call("stop_cycling")

    def set_mode(self, mode: str, open_delay: Duration | None = None) -> dict[str, Any]:
        """Closed loop ("closed": AR-predicted delay) or open loop ("open": a fixed delay)."""
        if open_delay is None:
            return self.call("set_mode", mode)
        delay_ns = duration_ns("open_delay", open_delay)
        return self.call("set_mode", mode, delay_ns)

    def reset_fault(self) -> dict[str, Any]:
        """Clear a latched FAULT so strokes may run again."""
        return self.call("reset_fault")

    def set_drive(
        self,
        *,
        frequency_hz: float | None = None,
        voltage_vpp: float | None = None,
        enabled: bool | None = None,
    ) -> dict[str, Any]:
        """Set the drive board's excitation (only the given keys); returns the drive's state."""
        settings: dict[str, Any] = {}
        if frequency_hz is not None:
            settings["frequency_hz"] = frequency_hz
        if voltage_vpp is not None:
            settings["voltage_vpp"] = voltage_vpp
        if enabled is not None:
            settings["enabled"] = enabled
        return self.call("set_drive", settings)


def run_owner() -> str:
    """Who starts a run, for the daemon's records and for the refusal another client reads:
    user, host, pid and program."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = f"uid {os.getuid()}"
    program = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "python"
    return f"{user}@{socket.gethostname()} pid {os.getpid()} ({program})"[:200]
