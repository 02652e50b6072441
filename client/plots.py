"""Plots of a run from its cycle records, in the paper's forms (Fig. 6, 11, 12, 14).

matplotlib is the `plot` extra: imported here only, so the daemon never needs it. Every axis says
its quantity and unit; the strokes are marked where a run starts (records with `run_id`) and where
the target T changes (from the records' `target_ns`), so a sweep reads as its parts.
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from usmswitch.protocol.record import CycleRecord, Flag
from usmswitch.protocol.units import format_ns

# The paper's bounds on the closed-loop error, in % of T (dashed on the error plot).
PAPER_BOUNDS_PCT = (0.42, 0.85)


@dataclass(frozen=True)
class Mark:
    """A place on the cycle axis worth a line: a run's first stroke, or the first with a new T."""

    cycle: int
    kind: str  # "run" or "target"
    label: str


def run_marks(records: Sequence[CycleRecord]) -> list[Mark]:
    """Where runs start and where T changes, in cycle order (the first stroke's run counts as a start)."""
    marks: list[Mark] = []
    last_run: int | None = None
    last_target: dict[int, int] = {}
    for r in records:
        run_id = getattr(r, "run_id", None)  # records of schema < 3 have none
        if run_id is not None and run_id != last_run:
            marks.append(Mark(r.cycle, "run", f"run {run_id}"))
        last_run = run_id
        before = last_target.get(r.direction)
        if before is not None and r.target_ns != before:
            name = ("on", "off")[r.direction] if r.direction in (0, 1) else str(r.direction)
            marks.append(Mark(r.cycle, "target", f"T {name} {format_ns(r.target_ns)}"))
        last_target[r.direction] = r.target_ns
    return marks


def plot_run(records: Iterable[CycleRecord], path: str | Path, *, title: str = "") -> Path:
    """Write a PNG/PDF/SVG (by suffix) of operating time, t_hat, error against T and its histogram."""
    import matplotlib

    matplotlib.use("Agg")  # files only: no screen on a rig's host
    import matplotlib.pyplot as plt

    recs = [r for r in records if r.operating_ns is not None]
    if not recs:
        raise ValueError("no completed strokes to plot")
    fig, axes = plt.subplots(3, 1, figsize=(10, 10), constrained_layout=True)
    ax_t, ax_e, ax_h = axes
    for direction, name, colour in ((0, "on", "tab:blue"), (1, "off", "tab:orange")):
        mine = [r for r in recs if r.direction == direction]
        if not mine:
            continue
        cyc = [r.cycle for r in mine]
        ax_t.plot(cyc, [r.operating_ns / 1e6 for r in mine], ".", ms=2, color=colour, label=f"t ({name})")
        ax_t.plot(cyc, [r.t_hat_ns / 1e6 for r in mine], "-", lw=0.7, color=colour, alpha=0.6,
                  label=f"t_hat ({name})")  # fmt: skip
        errs = [r.error_ns / 1e3 for r in mine]
        ax_e.plot(cyc, errs, ".", ms=2, color=colour, label=name)
        std = statistics.stdev(errs) if len(errs) > 1 else 0.0  # sample std, as `stats` reports it
        ax_h.hist(errs, bins=60, histtype="step", lw=1.2, color=colour, label=f"{name}: std {std:.1f} us")
    late = [r for r in recs if r.flags & Flag.LATE]
    if late:
        ax_e.plot(
            [r.cycle for r in late], [r.error_ns / 1e3 for r in late], "x", color="red", ms=4, label="late"
        )
    # The paper's bounds follow T where it changes: a step line per bound, from each stroke's T.
    cycles = [r.cycle for r in recs]
    for pct in PAPER_BOUNDS_PCT:
        band = [r.target_ns * pct / 100 / 1e3 for r in recs]
        ax_e.step(cycles, band, where="post", color="grey", lw=0.6, ls="--")
        ax_e.step(cycles, [-b for b in band], where="post", color="grey", lw=0.6, ls="--")
    marks = run_marks(recs)
    for ax in (ax_t, ax_e):
        for m in marks:
            style = {"run": ("black", "-"), "target": ("tab:green", ":")}[m.kind]
            ax.axvline(m.cycle, color=style[0], ls=style[1], lw=0.8, alpha=0.7)
    for m in marks:
        ax_t.annotate(m.label, (m.cycle, 1.0), xycoords=("data", "axes fraction"), rotation=90,
                      va="top", ha="right", fontsize=7)  # fmt: skip
    targets = sorted({r.target_ns for r in recs})
    shown_t = ", ".join(format_ns(t) for t in targets[:4]) + (", ..." if len(targets) > 4 else "")
    ax_t.set_title(title or f"{len(recs)} strokes, T = {shown_t}")
    ax_t.set_xlabel("cycle")
    ax_t.set_ylabel("operating time t, predicted t_hat (ms)")
    ax_e.set_xlabel("cycle")
    ax_e.set_ylabel("error = total - T (us)")
    ax_e.text(0.01, 0.97, "dashed: +-0.42 % and +-0.85 % of T (the paper's bounds); "
              "lines: run starts (solid), T changes (dotted)",
              transform=ax_e.transAxes, va="top", fontsize=8)  # fmt: skip
    ax_h.set_xlabel("error = total - T (us)")
    ax_h.set_ylabel("strokes (count)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
