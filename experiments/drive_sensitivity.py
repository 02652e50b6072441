"""Commissioning: how the drive moves the stroke time on this rig, d ln t per kHz and per 100 V.

The "kalman" predictor moves its level by s . dc when the drive setting changes; told s beforehand
(`[control] sensitivity_frequency`, `sensitivity_voltage`), it predicts even the first step of a kind
it has never seen, which otherwise errs by the whole step (~1 ms). This measures s the way a lab
would: open-loop blocks of strokes at the operating point, each step away from it (frequency up and
down, voltage up and down) bracketed by blocks at the operating point, `REPEATS` times. Each step's
effect is its block's mean ln t less the mean of the two operating-point blocks around it, so the
slow drift of friction and warmth cancels; s is the least-squares fit of those effects to the steps,
per direction pooled, with its standard error. The temperature's sensitivity is not measured here
(it needs the motor held at other temperatures; the predictor learns it as the motor warms).

Runs on the simulated rig or a live one with a drive board (`--socket`); the strokes stay in the
records, one run per block.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .context import MS, Context

#: The drive changes commissioned, away from the operating point and back, each bracketed: (frequency
#: offset Hz, voltage offset V). Near resonance a USM's response is far from linear (detuning either way
#: slows it), so commission the changes the rig will be run with: by default detuning up by 500 Hz and
#: lowering the voltage by 50 V, the two ways an operator slows a USM (`--frequency-step`,
#: `--voltage-step`).
STEPS = ((500.0, 0.0), (0.0, -50.0))
#: Short blocks, many times: friction wanders over tens of strokes, so neighbouring blocks share it and
#: the bracketed difference keeps only the stroke-to-stroke scatter.
REPEATS = 20
#: Strokes per block (both directions); the first stroke of each direction after a change is left out
#: (a drive board may apply the setting within a stroke).
BLOCK = 6
PERIOD_NS = 25 * MS
#: The paper's operating point (the daemon's default drive).
FREQUENCY_HZ = 40_000.0
VOLTAGE_VPP = 500.0


@dataclass(frozen=True)
class DriveSensitivity:
    """d ln t per kHz and per 100 V measured at an operating point, with standard errors."""

    per_khz: float
    per_100v: float
    stderr_per_khz: float
    stderr_per_100v: float
    frequency_hz: float
    voltage_vpp: float
    blocks: int

    @property
    def sensitivities(self) -> tuple[float, float, None]:
        """As `make_predictor("kalman", sensitivities=...)` takes them (temperature not measured)."""
        return (self.per_khz, self.per_100v, None)

    def config_lines(self) -> str:
        """The `[control]` lines that tell the daemon (docs/config.md)."""
        return (
            f'sensitivity_frequency = "{self.per_khz:.4g}/kHz"\n'
            f'sensitivity_voltage = "{self.per_100v:.4g}/100V"\n'
        )


def _block_mean(log_t: np.ndarray, direction: np.ndarray) -> float:
    """Mean ln t of a block: each direction's mean without its first stroke, averaged over the two."""
    means = []
    for d in (0, 1):
        v = log_t[direction == d][1:]
        v = v[~np.isnan(v)]
        if len(v):
            means.append(float(np.mean(v)))
    return float(np.mean(means)) if means else math.nan


def measure(
    ctx: Context,
    frequency_hz: float = FREQUENCY_HZ,
    voltage_vpp: float = VOLTAGE_VPP,
    steps: tuple[tuple[float, float], ...] = STEPS,
    repeats: int = REPEATS,
) -> DriveSensitivity:
    """Run the bracketed steps on the rig and fit d ln t per kHz and per 100 V."""
    block = BLOCK
    means: list[float] = []
    settings: list[tuple[float, float]] = []

    def run_block(df: float, dv: float) -> None:
        f, v = frequency_hz + df, voltage_vpp + dv
        s = ctx.strokes(
            f"drive-sensitivity {f / 1e3:g} kHz {v:g} Vpp",
            block,
            PERIOD_NS,
            12 * MS,
            mode="open",
            open_delay_ns=0,
            frequency_hz=f,
            voltage_vpp=v,
        )
        means.append(_block_mean(np.log(s.operating_ns), s.direction))
        settings.append((df, dv))

    run_block(0.0, 0.0)
    for _ in range(repeats):
        for df, dv in steps:
            run_block(df, dv)
            run_block(0.0, 0.0)
    # Each step's effect against the operating-point blocks on either side (drift cancels).
    x, y = [], []
    for i in range(1, len(means) - 1, 2):
        df, dv = settings[i]
        x.append((df / 1e3, dv / 1e2))
        y.append(means[i] - (means[i - 1] + means[i + 1]) / 2)
    xa, ya = np.asarray(x), np.asarray(y)
    keep = ~np.isnan(ya)
    xa, ya = xa[keep], ya[keep]
    if len(ya) < 3:
        raise RuntimeError(f"drive-sensitivity: only {len(ya)} steps had strokes; the rig stalled?")
    coef, *_ = np.linalg.lstsq(xa, ya, rcond=None)
    resid = ya - xa @ coef
    dof = max(1, len(ya) - 2)
    cov = np.linalg.inv(xa.T @ xa) * float(resid @ resid) / dof
    return DriveSensitivity(
        per_khz=float(coef[0]),
        per_100v=float(coef[1]),
        stderr_per_khz=float(math.sqrt(cov[0, 0])),
        stderr_per_100v=float(math.sqrt(cov[1, 1])),
        frequency_hz=frequency_hz,
        voltage_vpp=voltage_vpp,
        blocks=len(means),
    )


def run(ctx: Context) -> dict[str, Any]:
    """The experiment `usmswitch-experiment drive-sensitivity`: measure, and the config lines to keep."""
    m = measure(ctx)
    return {
        "frequency_hz": m.frequency_hz,
        "voltage_vpp": m.voltage_vpp,
        "blocks": m.blocks,
        "per_khz": round(m.per_khz, 5),
        "per_100v": round(m.per_100v, 5),
        "stderr_per_khz": round(m.stderr_per_khz, 5),
        "stderr_per_100v": round(m.stderr_per_100v, 5),
        "config": m.config_lines(),
        "note": "d ln t per kHz and per 100 V (0.1/kHz: ~10 % longer strokes per kHz), the temperature's "
        "not measured; put the config lines in [control] (docs/config.md)",
    }
