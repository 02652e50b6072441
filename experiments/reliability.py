"""Fig. 15-16: 100,000 on/off strokes at a fixed T = 10.5 ms: every stroke arrives, none is late."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .context import MS, Context
from .figures import legend_beside, new_figure, thin

STROKES = 100_000
TARGET_NS = 10_500_000
PERIOD_NS = 25 * MS


def run(ctx: Context) -> dict[str, Any]:
    n = ctx.count(STROKES)
    t0 = time.monotonic()
    s = ctx.strokes("reliability", n, PERIOD_NS, TARGET_NS)
    seconds = time.monotonic() - t0
    stroke_mm = ctx.rig.params.stroke_mm if ctx.rig is not None and ctx.rig.simulated else 5.0  # type: ignore[attr-defined]
    # An arrival at the far sensor is a full stroke: the sensors sit `stroke_mm` apart (Fig. 16).
    travel_mm = np.where(np.isnan(s.operating_ns), np.nan, stroke_mm)
    out = {
        "cycles": len(s),
        "arrived": s.arrived,
        "late": s.late,
        "stalls": s.stalls,
        "failed": s.failed,
        "target_ns": TARGET_NS if ctx.recorded is None else int(np.median(s.target_ns)),
        "seconds": round(seconds, 2),
        "run_id": s.run_id,
        "total_max_ns": int(np.nanmax(s.total_ns)) if s.arrived else None,
        "operating_max_ns": int(np.nanmax(s.operating_ns)) if s.arrived else None,
        "delay_min_ns": int(np.min(s.delay_ns)) if len(s) else None,
    }
    fig, ax = new_figure(2, 1)
    a = ax[0][0]
    x, y = thin(s.cycle, s.total_ns / 1e6)
    a.plot(x, y, ".", ms=1.5, color="tab:green", label="total = arrival - command")
    x, y = thin(s.cycle, s.operating_ns / 1e6)
    a.plot(x, y, ".", ms=1.5, color="tab:gray", alpha=0.5, label="operating time (drive on to arrival)")
    a.axhline(out["target_ns"] / 1e6, color="k", lw=0.8, label=f"T = {out['target_ns'] / 1e6:g} ms")
    a.set_xlabel("cycle")
    a.set_ylabel("time (ms)")
    a.set_title(f"Reliability: {len(s):,} on/off strokes at a fixed {out['target_ns'] / 1e6:g} ms (Fig. 15)")
    legend_beside(a, fontsize=7)
    b = ax[1][0]
    x, y = thin(s.cycle, travel_mm)
    b.plot(x, y, ".", ms=1.5, color="tab:blue")
    b.set_ylim(0, stroke_mm * 1.2)
    b.set_xlabel("cycle")
    b.set_ylabel("travel per cycle (mm)")
    b.set_title(f"{s.arrived:,} of {len(s):,} cycles travelled the full {stroke_mm:g} mm (Fig. 16)")
    out["figures"] = ctx.save(fig, "fig15_16_reliability")
    return out
