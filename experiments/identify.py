"""Fig. 8 and Table 1: the speed response at each drive frequency 39.5-41.5 kHz, and Eq. 1's
parameters w_n^2, 2 xi w_n and K w_n identified from it, beside the paper's Table 1 (sim only: a real
rig would need a position or speed sensor)."""

from __future__ import annotations

from typing import Any

import numpy as np

from usmswitch.protocol.record import CycleRecord
from usmswitch.sim.params import TABLE1_2XI_WN, TABLE1_FREQUENCY_HZ, TABLE1_K_WN, TABLE1_WN2

from .context import MS, Context
from .figures import legend_beside, new_figure


def fit_second_order(tau: np.ndarray, speed: np.ndarray) -> tuple[float, float, float]:
    """Least squares of y'' = -b y' - a y + c on a sampled step response (tau in the table's time
    unit): returns (a = w_n^2, b = 2 xi w_n, c = a * steady speed)."""
    dt = float(tau[1] - tau[0])
    d1 = np.gradient(speed, dt)
    d2 = np.gradient(d1, dt)
    inner = slice(2, len(tau) - 2)  # the end points' one-sided differences are the roughest
    x = np.column_stack([-d1[inner], -speed[inner], np.ones(len(tau) - 4)])
    (b, a, c), *_ = np.linalg.lstsq(x, d2[inner], rcond=None)
    return float(a), float(b), float(c)


def run(ctx: Context) -> dict[str, Any]:
    sim = ctx.sim("identification")
    unit = sim.params.table_time_unit_ns
    rows = []
    fig, ax = new_figure()
    a_ax = ax[0][0]
    for i, freq in enumerate(TABLE1_FREQUENCY_HZ):
        grabbed: list[Any] = []

        def grab(rec: CycleRecord, grabbed: list[Any] = grabbed) -> None:
            if rec.direction == 0 and sim.model.last_stroke is not None and not grabbed:
                grabbed.append(sim.model.last_stroke)

        sim.loop.listeners.append(grab)
        try:
            ctx.strokes(f"identify {freq / 1e3:g} kHz", 2, 25 * MS, 12 * MS, mode="open", frequency_hz=freq)
        finally:
            sim.loop.listeners.remove(grab)
        stroke = grabbed[0]
        prof = sim.model.profile(stroke, step_ns=10_000)
        moving = (prof.t_ns >= stroke.dead_ns) & (prof.speed_mm_s > 0)
        tau = (prof.t_ns[moving] - stroke.dead_ns) / unit
        speed = prof.speed_mm_s[moving] * unit / 1e9  # mm per table unit
        a, b, c = fit_second_order(tau, speed)
        k_wn = c / sim.model.gain_mm_per_kwn  # the drive's displacement gain, calibrated at 40 kHz
        rows.append(
            {
                "frequency_hz": freq,
                "wn2": round(a, 1),
                "two_xi_wn": round(b, 2),
                "k_wn": round(k_wn, 1),
                "paper": {"wn2": TABLE1_WN2[i], "two_xi_wn": TABLE1_2XI_WN[i], "k_wn": TABLE1_K_WN[i]},
                # What the identification should recover: the simulated rig's own Eq. 1 at this frequency.
                "model": {
                    "wn2": sim.params.table_wn2[i],
                    "two_xi_wn": sim.params.table_2xi_wn[i],
                    "k_wn": sim.params.table_k_wn[i],
                },
                "operating_ns": stroke.operating_ns,
            }
        )
        a_ax.plot(prof.t_ns / 1e6, prof.speed_mm_s / 1e3, label=f"{freq / 1e3:g} kHz")
    a_ax.set_xlabel("time from drive on (ms)")
    a_ax.set_ylabel("speed (m/s)")
    a_ax.set_title("Speed response at different drive frequencies, 500 Vpp (Fig. 8)")
    legend_beside(a_ax)
    return {
        "rows": rows,
        "time_unit_ns": unit,
        "note": "one stroke per frequency, friction and warm-up included: the identified K w_n carries "
        "the stroke's friction scale (a few %), as an identification on a real rig would",
        "figures": ctx.save(fig, "fig08_speed_by_frequency"),
    }
