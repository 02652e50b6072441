"""Fig. 7: the mover's speed against time at cycles 50, 100 and 150 of an open-loop run (sim only:
a real rig's limit sensors give two instants per stroke, not a speed profile)."""

from __future__ import annotations

from typing import Any

import numpy as np

from usmswitch.protocol.record import CycleRecord

from .context import MS, Context
from .figures import legend_beside, new_figure
from .open_loop import FREQUENCY_HZ

CYCLES = (50, 100, 150)


def run(ctx: Context) -> dict[str, Any]:
    sim = ctx.sim("the speed profile")
    last = max(CYCLES) if ctx.scale >= 1 else max(3, round(max(CYCLES) * ctx.scale))
    wanted = sorted({max(1, round(c * last / max(CYCLES))) for c in CYCLES})
    profiles: dict[int, Any] = {}
    first = sim.loop.cycle

    def grab(rec: CycleRecord) -> None:
        k = rec.cycle - first + 1
        if k in wanted and sim.model.last_stroke is not None:
            profiles[k] = (rec, sim.model.profile(sim.model.last_stroke, step_ns=20_000))

    sim.loop.listeners.append(grab)
    try:
        ctx.strokes("speed", last, 25 * MS, 12 * MS, mode="open", frequency_hz=FREQUENCY_HZ)
    finally:
        sim.loop.listeners.remove(grab)
    fig, ax = new_figure()
    a = ax[0][0]
    out: dict[str, Any] = {"cycles": []}
    for k in wanted:
        rec, prof = profiles[k]
        moving = prof.speed_mm_s > 0
        a.plot(
            prof.t_ns / 1e6,
            prof.speed_mm_s / 1e3,
            label=f"cycle {k} ({'on' if rec.direction == 0 else 'off'}): {rec.operating_ns / 1e6:.3f} ms",
        )
        out["cycles"].append(
            {
                "cycle": k,
                "direction": "on" if rec.direction == 0 else "off",
                "operating_ns": rec.operating_ns,
                "peak_speed_mm_s": round(float(np.max(prof.speed_mm_s)), 1),
                "mean_speed_mm_s": round(float(np.mean(prof.speed_mm_s[moving])), 1)
                if moving.any()
                else None,
            }
        )
    a.set_xlabel("time from drive on (ms)")
    a.set_ylabel("speed (m/s)")
    a.set_title(f"Speed response at different cycles, {FREQUENCY_HZ / 1e3:.1f} kHz, 500 Vpp (Fig. 7)")
    legend_beside(a)
    out["figures"] = ctx.save(fig, "fig07_speed")
    return out
