"""Plots of a run from its cycle records, in the paper's forms (Fig. 6, 11, 12, 14).

matplotlib is the `plot` extra: imported here only, so the daemon never needs it.
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable
from pathlib import Path

from usmswitch.daemon.record import CycleRecord, Flag


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
        std = statistics.pstdev(errs) if len(errs) > 1 else 0.0
        ax_h.hist(errs, bins=60, histtype="step", lw=1.2, color=colour, label=f"{name}: std {std:.1f} us")
    late = [r for r in recs if r.flags & Flag.LATE]
    if late:
        ax_e.plot(
            [r.cycle for r in late], [r.error_ns / 1e3 for r in late], "x", color="red", ms=4, label="late"
        )
    target = recs[-1].target_ns
    for pct in (0.42, 0.85):
        band = target * pct / 100 / 1e3
        ax_e.axhline(band, color="grey", lw=0.6, ls="--")
        ax_e.axhline(-band, color="grey", lw=0.6, ls="--")
    ax_t.set_ylabel("operating time (ms)")
    ax_t.set_title(title or f"{len(recs)} strokes, T = {target / 1e6:g} ms")
    ax_e.set_ylabel("error = total - T (us)")
    ax_e.set_xlabel("cycle")
    ax_e.text(0.01, 0.97, "dashed: +-0.42 % and +-0.85 % of T (the paper's bounds)",
              transform=ax_e.transAxes, va="top", fontsize=8)  # fmt: skip
    ax_h.set_xlabel("error (us)")
    ax_h.set_ylabel("strokes")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
