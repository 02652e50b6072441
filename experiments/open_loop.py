"""Fig. 6: open-loop strokes at a fixed drive (39.6 kHz, 500 Vpp): how dispersed the operating time is."""

from __future__ import annotations

from typing import Any

import numpy as np

from .context import MS, Context
from .data import describe_ns
from .figures import DIRECTION_COLOURS, DIRECTION_NAMES, legend_beside, new_figure

FREQUENCY_HZ = 39_600.0
STROKES = 500
PERIOD_NS = 25 * MS


def run(ctx: Context) -> dict[str, Any]:
    n = ctx.count(STROKES)
    s = ctx.strokes(
        "open-loop", n, PERIOD_NS, 12 * MS, mode="open", open_delay_ns=0, frequency_hz=FREQUENCY_HZ
    )
    out: dict[str, Any] = {
        "frequency_hz": FREQUENCY_HZ,
        "voltage_vpp": 500.0,
        "strokes": len(s),
        "run_id": s.run_id,
    }
    out["all"] = describe_ns(s.operating_ns)
    for d, name in enumerate(DIRECTION_NAMES):
        out[name] = describe_ns(s.of(d).operating_ns)
    fig, ax = new_figure()
    a = ax[0][0]
    for d, name in enumerate(DIRECTION_NAMES):
        sd = s.of(d)
        a.plot(
            np.arange(1, len(sd) + 1),
            sd.operating_ns / 1e6,
            ".",
            ms=3,
            color=DIRECTION_COLOURS[d],
            label=name,
        )
    a.set_xlabel("switch operation of the direction (cycle)")
    a.set_ylabel("operating time (ms)")
    a.set_title(f"Open loop at {FREQUENCY_HZ / 1e3:.1f} kHz, 500 Vpp (Fig. 6)")
    legend_beside(a)
    out["figures"] = ctx.save(fig, "fig06_open_loop")
    return out
