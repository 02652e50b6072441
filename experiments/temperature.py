"""Fig. 9: operating time at motor temperatures 25, 27.5 and 30 C (sim only: the ambient is a setting
of the simulated rig; on a real rig put it in a climate chamber and run `open-loop`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .context import MS, Context
from .data import describe_ns
from .figures import DIRECTION_NAMES, new_figure, save

TEMPERATURES_C = (25.0, 27.5, 30.0)
STROKES = 200
#: A long period: the motor barely heats (duty ~4 %), so it runs at the ambient set.
PERIOD_NS = 200 * MS


def run(ctx: Context) -> dict[str, Any]:
    sim = ctx.sim("the temperature experiment")
    fig, ax = new_figure()
    a = ax[0][0]
    rows = []
    for temp in TEMPERATURES_C:
        sim.with_ambient(temp)
        # Idle six thermal time constants first (virtual time): the motor settles to the new ambient.
        sim.daq.clock.sleep_until(sim.daq.clock.now_ns() + 6 * sim.params.thermal_tau_ns)
        s = ctx.strokes(f"temperature {temp:g} C", ctx.count(STROKES), PERIOD_NS, 12 * MS, mode="open")
        row: dict[str, Any] = {
            "ambient_c": temp,
            "motor_c_mean": round(float(np.nanmean(s.temperature_c)), 2),
            "all": describe_ns(s.operating_ns),
            "run_id": s.run_id,
        }
        for d, name in enumerate(DIRECTION_NAMES):
            row[name] = describe_ns(s.of(d).operating_ns)
        rows.append(row)
        a.plot(
            np.arange(1, len(s) + 1), s.operating_ns / 1e6, ".", ms=3, label=f"{row['motor_c_mean']:.1f} C"
        )
    sim.with_ambient(sim.params.ambient_c)
    a.set_xlabel("switch operation (cycle)")
    a.set_ylabel("operating time (ms)")
    a.set_title("Operating time at different motor temperatures (Fig. 9)")
    a.legend(title="motor temperature")
    return {"rows": rows, "figures": save(fig, ctx.figures, "fig09_temperature")}
