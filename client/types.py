"""The shapes of what the daemon answers (docs/protocol.md), for type checkers and readers.

Every duration is an integer of nanoseconds (`_ns`); a person reads them through `format_ns`.
"""

from __future__ import annotations

from typing import Any, NamedTuple, TypedDict


class Targets(TypedDict):
    target_on_ns: int
    target_off_ns: int
    from_cycle: int  # the first stroke armed with these targets


class Status(TypedDict):
    state: str  # "idle", "cycling", "fault", "stopped"
    mode: str  # "closed" or "open"
    fault: str  # why FAULT is latched; "" when not
    driver: str
    driver_ok: bool  # the device answers (link up)
    protocol_version: int
    version: str
    uptime_ns: int
    cycle: int  # the number the next stroke will get
    target_on_ns: int
    target_off_ns: int
    driver_counters: dict[str, int]  # what the driver dropped or repaired (bounces, link errors, ...)
    records: dict[str, Any]  # the record writer: path, backlog, dropped, rejected, writer_error, ...
    metrics_url: str | None  # the Prometheus page, None when not served
    web_url: str | None  # the browser panel, without its token (usmswitchctl web-url adds it)
    rig: str  # [daemon] rig
    model: str  # [control] model
    order: int | str  # [control] order: 1..8 or "auto"
    scheduling: str  # the loop thread's: "SCHED_FIFO 50", "SCHED_OTHER (... not permitted: ...)"
    ready: bool  # every part runs (the socket answers a moment before, while the rest starts)
    run: RunInfo | None  # the run going (None: none)
    queue: dict[str, Any]  # the queue of runs: "paused", "current" (the entry running), "queued"


class DirectionStats(TypedDict, total=False):
    count: int  # completed strokes
    strokes: int  # completed + stalled
    operating_mean_ns: float
    operating_std_ns: float
    operating_max_abs_ns: int
    total_mean_ns: float
    total_std_ns: float
    total_max_abs_ns: int
    error_mean_ns: float
    error_std_ns: float
    error_max_abs_ns: int
    max_abs_error_pct: float
    abs_error_p50_ns: int | None
    abs_error_p95_ns: int | None
    abs_error_p99_ns: int | None
    lateness_p50_ns: int | None
    lateness_p99_ns: int | None
    lateness_p99_9_ns: int | None
    lateness_max_ns: int | None
    late: int
    stalls: int
    bounces: int
    faults: int
    target_ns: int | None  # "on" and "off" of a past run: the target its last stroke had
    order: int  # "on" and "off" only
    coefficients: list[float]
    ready: bool


class Stats(TypedDict, total=False):
    """The statistics of one run (the current or last one by default) or a range of cycles."""

    run: RunInfo | None  # the run covered (None: no run yet, every stroke since the start)
    first_cycle: int | None  # the strokes covered
    last_cycle: int | None
    state: str
    mode: str
    fault: str
    cycle: int
    target_on_ns: int
    target_off_ns: int
    spurious_edges: int
    overruns: int
    driver_bounces: int
    all: DirectionStats
    on: DirectionStats
    off: DirectionStats


class CycleRecord(TypedDict):
    cycle: int
    direction: int  # 0 = on (A -> B), 1 = off (B -> A)
    mode: str
    target_ns: int
    order: int
    coefficients: list[float]
    t_hat_ns: int
    delay_ns: int
    t_cmd_ns: int
    t_start_ns: int | None
    t_depart_ns: int | None
    t_arrive_ns: int | None
    operating_ns: int | None
    total_ns: int | None
    error_ns: int | None
    dead_ns: int | None
    lateness_ns: int | None
    temperature_c: float | None
    frequency_hz: float | None
    flags: int  # usmswitch.protocol.record.Flag bits
    wall_ns: int
    driver: str | None  # the driver that made the stroke ("sim", "serial", "usb")
    rig: str | None  # the rig's identity ([daemon] rig, the host name by default)
    run_id: int | None  # the run the stroke belongs to (None: outside any run)


class RunInfo(TypedDict):
    """One run: a start_cycling (or an experiment) from its first stroke to its last."""

    run_id: int
    kind: str  # "cycling" or "experiment"
    first_cycle: int
    last_cycle: int | None  # None while it runs
    started_wall_ns: int
    ended_wall_ns: int | None
    end_reason: str | None  # None while it runs; "done", "stopped", "fault: ...", "shutdown"
    settings: dict[str, Any]  # period_ns, count, target_on_ns, target_off_ns, mode, model, ...
    driver: str | None
    rig: str | None
    label: str | None  # what the run is for, a short word (None: none given)
    notes: str | None  # free text, editable during and after the run (annotate_run)


class Cycling(TypedDict):
    """start_cycling's reply: the run it opened."""

    run_id: int
    period_ns: int
    count: int  # 0: until stopped
    first_cycle: int
    target_on_ns: int
    target_off_ns: int
    warnings: list[str]


class Notification(NamedTuple):
    """One notification: its topic ("stroke", "state", "run", ...) and its single payload."""

    topic: str
    payload: Any

    @property
    def dropped(self) -> int:
        """For the server's "dropped" notification, how many it dropped for this connection; else 0."""
        if self.topic != "dropped" or type(self.payload) is not dict:
            return 0
        return int(self.payload.get("count", 0))
