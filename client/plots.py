"""Plots of a run from its cycle records, in the paper's forms (Fig. 6, 11, 12, 14).

matplotlib is the `plot` extra: imported here only, so the daemon never needs it. Every axis says
its quantity and unit (µs and ±, as a figure is read); the title names the run, the rig and the
date (from the records); legends sit beside the axes, never over the strokes; the strokes are
marked where a run starts (records with `run_id`) and where the target T changes (from the
records' `target_ns`), so a sweep reads as its parts. `legends_over_data` is the check of the
last, for these figures and the experiments' (experiments/figures.py).
"""

from __future__ import annotations

import datetime
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from usmswitch.protocol.record import CycleRecord, Flag
from usmswitch.protocol.units import format_ns

MICRO = "µs"

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
            marks.append(Mark(r.cycle, "target", f"T {name} {format_ns(r.target_ns, micro=MICRO)}"))
        last_target[r.direction] = r.target_ns
    return marks


def runs_text(run_ids: Iterable[int | None]) -> str:
    """ "run 7", "runs 3-5", "runs 3, 5, 9", or "no run" (records from before runs)."""
    ids = sorted({r for r in run_ids if r is not None})
    if not ids:
        return "no run"
    if len(ids) == 1:
        return f"run {ids[0]}"
    if ids == list(range(ids[0], ids[-1] + 1)):
        return f"runs {ids[0]}-{ids[-1]}"
    shown = ", ".join(str(r) for r in ids[:6])
    return f"runs {shown}" + (", ..." if len(ids) > 6 else "")


def wall_text(wall_ns: int | None) -> str:
    """A wall-clock time for people, ISO as `usmswitchctl` writes it (local time)."""
    if wall_ns is None:
        return "date unknown"
    return datetime.datetime.fromtimestamp(wall_ns / 1e9).strftime("%Y-%m-%d %H:%M:%S")


def figure_stamp(rigs: Iterable[str | None], run_ids: Iterable[int | None], wall_ns: int | None) -> str:
    """What a figure's title says of its data: "run 12, rig lab-a, 2025-06-01 14:27:03"."""
    names = sorted({r for r in rigs if r})
    rig = f"rig {', '.join(names)}" if names else "rig unknown"
    return f"{runs_text(run_ids)}, {rig}, {wall_text(wall_ns)}"


def legend_beside(ax: Any, **kw: Any) -> Any:
    """The axes' legend to its right, outside the data (constrained layout makes room for it)."""
    kw.setdefault("fontsize", 8)
    return ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, **kw)


def legends_over_data(fig: Any) -> list[str]:
    """The legends that cover a plotted point, line vertex or bar of their axes (laid out as saved)."""
    import numpy as np

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    out = []
    for ax in fig.axes:
        legend = ax.get_legend()
        if legend is None:
            continue
        box = legend.get_window_extent(renderer)
        shapes = [line.get_transform().transform(line.get_xydata()) for line in ax.get_lines()]
        shapes += [p.get_transform().transform(p.get_path().vertices) for p in ax.patches]
        shapes += [c.get_offset_transform().transform(c.get_offsets()) for c in ax.collections]
        covered = 0
        for xy in shapes:
            xy = np.asarray(xy, dtype=float).reshape(-1, 2)
            inside = (xy[:, 0] >= box.x0) & (xy[:, 0] <= box.x1) & (xy[:, 1] >= box.y0) & (xy[:, 1] <= box.y1)
            covered += int(np.count_nonzero(inside))
        if covered:
            out.append(f"{ax.get_title() or ax.get_ylabel()!r}: its legend covers {covered} points")
    return out


def plot_run(records: Iterable[CycleRecord], path: str | Path, *, title: str = "") -> Path:
    """Write a PNG/PDF/SVG (by suffix) of operating time, t_hat, error against T and its histogram."""
    import matplotlib.pyplot as plt

    fig = draw_run(records, title=title)
    out = Path(path)
    try:
        fig.savefig(out, dpi=110)
    finally:
        plt.close(fig)
    return out


def draw_run(records: Iterable[CycleRecord], *, title: str = "") -> Any:
    """The figure `plot_run` writes (matplotlib's Figure; the caller closes it)."""
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
        ax_h.hist(
            errs, bins=60, histtype="step", lw=1.2, color=colour, label=f"{name}: std {std:.1f} {MICRO}"
        )
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
    shown_t = ", ".join(format_ns(t, micro=MICRO) for t in targets[:4])
    shown_t += ", ..." if len(targets) > 4 else ""
    stamp = figure_stamp((r.rig for r in recs), (r.run_id for r in recs), recs[0].wall_ns)
    fig.suptitle(f"{title}\n{stamp}" if title else stamp)
    ax_t.set_title(f"{len(recs)} strokes, T = {shown_t}")
    ax_t.set_xlabel("cycle")
    ax_t.set_ylabel("operating time t, predicted t_hat (ms)")
    ax_e.set_xlabel("cycle")
    ax_e.set_ylabel(f"error = total - T ({MICRO})")
    bounds = " and ".join(f"±{pct} %" for pct in PAPER_BOUNDS_PCT)
    marked = "lines: run starts (solid), T changes (dotted)"
    ax_e.set_title(f"dashed: {bounds} of T (the paper's bounds); {marked}", fontsize=8, loc="left")
    ax_h.set_xlabel(f"error = total - T ({MICRO})")
    ax_h.set_ylabel("strokes (count)")
    for ax in axes:
        ax.grid(alpha=0.3)
        legend_beside(ax)
    return fig
