"""Fig. 11-14: prediction against measurement, and closed-loop control at T = 12 ms @ 40 kHz and
24 ms @ 40.5 kHz; the paper's AR(1) controls, and every shipped model is scored on the same strokes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from usmswitch.drivers import Direction
from usmswitch.predictor import AR_MODELS, DEFAULT_MODEL, MODELS, make_predictors

from .context import MS, Context
from .data import Strokes
from .figures import (
    DIRECTION_COLOURS,
    DIRECTION_NAMES,
    MICRO,
    histogram_with_normal,
    legend_beside,
    new_figure,
    thin,
)

#: (T, drive frequency, the paper's std, max error % of T, operating-time band %) per condition.
CONDITIONS = ((12 * MS, 40_000.0, 95_300, 0.41, 0.85), (24 * MS, 40_500.0, 102_700, 0.44, 0.42))
STROKES = 1000
#: Strokes per direction left out as the predictors' cold start (their window).
SETTLE = 100
ORDERS: tuple[int | str, ...] = (1, 2, 3, "auto")


def controlling_label(run: Any) -> str:
    """The row name of the model that controlled a run, from its record (the simulated rig's runs
    are the paper's AR(1), as `SimulatedRig` makes them)."""
    if run is None:
        return "paper AR(1), controlling"
    s = run["settings"]
    if s.get("mode") == "open":
        return "open loop (fixed delay), not controlling"
    model = s.get("model") or "?"
    order = s.get("order")
    order = order[0] if isinstance(order, list) and order else order
    name = f"{model} AR({order})" if model in AR_MODELS else model
    default = " (default)" if model == DEFAULT_MODEL else ""
    return f"{name}{default}, controlling"


def _period(target_ns: int) -> int:
    return target_ns + 13 * MS  # room for a late stroke, as the daemon's period check wants


def one_step(s: Strokes, model: str, order: int | str | None, nominal_ns: int) -> np.ndarray:
    """Each stroke's one-step error t - t_hat of a fresh predictor run over the same strokes
    (per direction, NaN for a stroke it cannot learn from), in cycle order. The predictor is told
    each stroke's recorded temperature and drive frequency (the models beyond the paper use them);
    `order` is for the AR models only (None for the others)."""
    err = np.full(len(s), np.nan)
    options = {} if order is None else {"order": order, "window": 100}
    ps = make_predictors(model, [nominal_ns, nominal_ns], **options)  # as the daemon makes them
    for i in range(len(s)):
        t = s.operating_ns[i]
        if np.isnan(t):
            continue
        cond = {
            k: float(v)
            for k, v in (("temperature_c", s.temperature_c[i]), ("frequency_hz", s.frequency_hz[i]))
            if not np.isnan(v)
        }
        p = ps[int(s.direction[i])]
        err[i] = t - p.predict(cond)
        p.update(int(t), cond)
    return err


def _shipped() -> list[tuple[str, int | str | None, str]]:
    """(model, order, row name) of every shipped model; the default is named so."""
    out: list[tuple[str, int | str | None, str]] = []
    for model in MODELS:
        orders: tuple[int | str | None, ...] = ORDERS if model in AR_MODELS else (None,)
        for order in orders:
            name = model if order is None else f"{model} AR({order})"
            default = model == DEFAULT_MODEL and order in (None, 1)
            out.append((model, order, f"{name} (default)" if default else name))
    return out


def _row(
    target_ns: int, freq: float, model: str, strokes: int, err: np.ndarray, floor: float | None, how: str
) -> dict[str, Any]:
    e = err[~np.isnan(err)]
    std = float(np.std(e, ddof=1)) if len(e) > 1 else None
    mx = int(np.max(np.abs(e))) if len(e) else None
    return {
        "target_ns": target_ns,
        "frequency_hz": freq,
        "model": model,
        "strokes": strokes,
        "std_ns": None if std is None else round(std, 1),
        "max_abs_error_ns": mx,
        "max_abs_error_pct": None if mx is None else round(100 * mx / target_ns, 3),
        "floor_ns": None if floor is None else round(floor, 1),
        "measured": how,
    }


def run(ctx: Context) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    conditions: list[dict[str, Any]] = []
    figures: list[str] = []
    panels = 1 if ctx.recorded is not None else len(CONDITIONS)
    fig_hist, ax_hist = new_figure(1, panels, width=4.8 * panels, height=4.0)  # each title whole
    conds = CONDITIONS if ctx.recorded is None else CONDITIONS[:1]  # a records file holds one run
    for k, (target_ns, freq, paper_std, paper_pct, band_pct) in enumerate(conds):
        s = ctx.strokes(
            f"closed-loop {target_ns // MS} ms",
            ctx.count(STROKES, least=2 * SETTLE + 40),
            _period(target_ns),
            target_ns,
            frequency_hz=freq,
        )
        if ctx.recorded is not None:
            target_ns = int(np.median(s.target_ns))
            freq = float(np.nanmedian(s.frequency_hz)) if not np.all(np.isnan(s.frequency_hz)) else freq
            # The paper's figures of the condition nearest the recorded T.
            _, _, paper_std, paper_pct, band_pct = min(CONDITIONS, key=lambda c: abs(c[0] - target_ns))
        nominal = int(np.nanmedian(s.operating_ns)) if s.arrived else 10_000_000
        floor = None
        if ctx.rig is not None and ctx.rig.simulated:
            model = ctx.sim("floor").model
            floor = float(np.mean([model.innovation_floor_ns(d) for d in (Direction.ON, Direction.OFF)]))
        settled = s.settled(SETTLE)
        # The prediction error t - t_hat (what the model did) apart from the switch time's error,
        # command to arrival from the stamps (what the rig did: start lateness included).
        rows.append(
            _row(
                target_ns,
                freq,
                controlling_label(s.run),
                len(settled),
                settled.operating_ns - settled.t_hat_ns,
                floor,
                "closed loop: t - t_hat",
            )
        )
        for model_name, order, row_name in _shipped():
            err = one_step(s, model_name, order, nominal)
            keep = np.isin(s.cycle, settled.cycle)
            rows.append(
                _row(target_ns, freq, row_name, int(keep.sum()), err[keep], floor, "one-step, same strokes")
            )
        total_pct = (
            100 * np.nanmax(np.abs(settled.total_ns - target_ns)) / target_ns if len(settled) else None
        )
        lateness = settled.lateness_ns[~np.isnan(settled.lateness_ns)]
        conditions.append(
            {
                "target_ns": target_ns,
                "frequency_hz": freq,
                "run_id": s.run_id,
                "strokes": len(s),
                "late": s.late,
                "stalls": s.stalls,
                "operating_time_within_pct": None if total_pct is None else round(float(total_pct), 3),
                # Zero lateness: the switch time's error is the prediction error, by construction.
                "lateness_max_ns": int(lateness.max()) if len(lateness) else None,
                "paper": {"std_ns": paper_std, "max_error_pct": paper_pct, "within_pct": band_pct},
            }
        )
        figures += _figures(ctx, s, target_ns, freq, band_pct)
        a = ax_hist[0][k]
        for d, name in enumerate(DIRECTION_NAMES):
            histogram_with_normal(a, settled.of(d).error_ns / 1e3, name, DIRECTION_COLOURS[d])
        a.set_xlabel(f"error = total - T ({MICRO})")
        a.set_ylabel(f"density (1/{MICRO})")
        a.set_title(f"T = {target_ns / MS:g} ms, {freq / 1e3:g} kHz (Fig. 14)")
        legend_beside(a, fontsize=7)
    figures += ctx.save(fig_hist, "fig14_error_histogram")
    return {"rows": rows, "conditions": conditions, "figures": figures, "settle_strokes": SETTLE}


def _figures(ctx: Context, s: Strokes, target_ns: int, freq: float, band_pct: float) -> list[str]:
    tag = f"{target_ns // MS}ms"
    fig, ax = new_figure(2, 1)
    a = ax[0][0]
    for d, name in enumerate(DIRECTION_NAMES):
        sd = s.of(d)
        x, y = thin(sd.cycle, sd.operating_ns / 1e6)
        a.plot(x, y, ".", ms=2, color=DIRECTION_COLOURS[d], label=f"measured, {name}")
        x, y = thin(sd.cycle, sd.t_hat_ns / 1e6)
        a.plot(x, y, "-", lw=0.8, color=DIRECTION_COLOURS[d], alpha=0.7, label=f"predicted t_hat, {name}")
    a.set_xlabel("cycle")
    a.set_ylabel("operating time (ms)")
    a.set_title(f"Prediction against measurement, T = {target_ns / MS:g} ms, {freq / 1e3:g} kHz (Fig. 11)")
    legend_beside(a, fontsize=7)
    b = ax[1][0]
    x, y = thin(s.cycle, s.total_ns / 1e6)
    b.plot(x, y, ".", ms=2, color="tab:green", label="total = arrival - command")
    t = target_ns / 1e6
    b.axhline(t, color="k", lw=0.8, label=f"T = {t:g} ms")
    for sign in (-1, 1):
        b.axhline(t * (1 + sign * band_pct / 100), color="tab:red", lw=0.8, ls="--")
    b.set_xlabel("cycle")
    b.set_ylabel("total operating time (ms)")
    b.set_title(f"Closed loop; dashed: the paper's ±{band_pct} % (Fig. {12 if target_ns == 12 * MS else 13})")
    legend_beside(b, fontsize=7)
    return ctx.save(fig, f"fig11_13_closed_loop_{tag}", runs=[s.run_id])
