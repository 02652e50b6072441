"""Fig. 9: operating time at motor temperatures 25, 27.5 and 30 C (sim only: the ambient is a setting
of the simulated rig; on a real rig put it in a climate chamber and run `open-loop`).

Each temperature's run meets the same friction and noise (the rig model rewound to one state: common
random numbers), so the runs differ by the temperature alone and not by the friction's slow drift
between them, which is as large as the effect. The trend (mean operating time per C) is also taken on
further seeds of the rig, and the report gives its spread across them.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .context import MS, Context
from .data import describe_ns
from .figures import DIRECTION_NAMES, legend_beside, new_figure
from .rig import RunSpec, SimulatedRig

TEMPERATURES_C = (25.0, 27.5, 30.0)
STROKES = 200
#: A long period: the motor barely heats (duty ~4 %), so it runs at the ambient set.
PERIOD_NS = 200 * MS
#: Further seeds of the rig the trend is taken on, and their strokes per temperature.
SPREAD_SEEDS = 4
SPREAD_STROKES = 100


def _settle(sim: SimulatedRig, temp: float) -> None:
    sim.with_ambient(temp)
    # Idle six thermal time constants first (virtual time): the motor settles to the new ambient.
    sim.daq.clock.sleep_until(sim.daq.clock.now_ns() + 6 * sim.params.thermal_tau_ns)


def _slope_ms_per_c(temps: list[float], means_ns: list[float]) -> float:
    return float(np.polyfit(temps, np.asarray(means_ns) / 1e6, 1)[0])


def run(ctx: Context) -> dict[str, Any]:
    sim = ctx.sim("the temperature experiment")
    fig, ax = new_figure()
    a = ax[0][0]
    rows = []
    same = sim.model.noise_state()
    for temp in TEMPERATURES_C:
        _settle(sim, temp)
        sim.model.rewind(same)
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
    legend_beside(a, title="motor temperature")
    temps = [r["motor_c_mean"] for r in rows]
    slope = _slope_ms_per_c(temps, [r["all"]["mean_ns"] for r in rows])
    slopes = [slope, *_other_seeds(ctx, sim)]
    return {
        "rows": rows,
        "slope_ms_per_c": round(slope, 4),
        "slopes_ms_per_c": [round(x, 4) for x in slopes],
        "slope_spread_ms_per_c": round(float(np.std(slopes, ddof=1)), 4) if len(slopes) > 1 else None,
        "every_seed_slower_when_warmer": all(x > 0 for x in slopes),
        "figures": ctx.save(fig, "fig09_temperature"),
    }


def _other_seeds(ctx: Context, sim: SimulatedRig) -> list[float]:
    """The trend on further seeds of the same rig (a throwaway records file each)."""
    out = []
    base = sim.seed if sim.seed is not None else 0
    count = max(40, round(SPREAD_STROKES * min(1.0, ctx.scale * 10)))
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(1, SPREAD_SEEDS + 1):
            other = SimulatedRig(Path(tmp) / f"seed{k}.sqlite", base + 1000 * k, params=sim.params)
            try:
                same = other.model.noise_state()
                means, temps = [], []
                for temp in TEMPERATURES_C:
                    _settle(other, temp)
                    other.model.rewind(same)
                    s = other.run(RunSpec(f"temperature {temp:g} C", count, PERIOD_NS, 12 * MS, mode="open"))
                    means.append(float(np.nanmean(s.operating_ns)))
                    temps.append(float(np.nanmean(s.temperature_c)))
                out.append(_slope_ms_per_c(temps, means))
            finally:
                other.close()
    return out
