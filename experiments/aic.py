"""Table 2: AIC of AR orders 1..3 on a run's operating times, under each reading of Eq. 8-9 implemented."""

from __future__ import annotations

from typing import Any

import numpy as np

from usmswitch.predictor import AR_MODELS, CRITERIA, aic_table

from .context import Context, NeedsStrokes
from .data import Strokes
from .figures import DIRECTION_NAMES
from .open_loop import FREQUENCY_HZ, PERIOD_NS, STROKES

#: The paper's Table 2 (the paper does not say which direction or reading; ours are all printed).
PAPER_AIC = (3574.2, 3590.1, 3660.5)
MAX_ORDER = 3
WINDOW = 100


def tables(s: Strokes) -> list[dict[str, Any]]:
    """Every reading (criterion x model) per direction, over the strokes that completed."""
    out = []
    for d, name in enumerate(DIRECTION_NAMES):
        ops = s.of(d).operating_ns
        samples = [int(v) for v in ops[~np.isnan(ops)]]
        for criterion in CRITERIA:
            for model in AR_MODELS:
                try:
                    t = aic_table(
                        samples, MAX_ORDER, model, criterion, WINDOW if criterion == "rolling" else None
                    )
                except ValueError as exc:  # too few strokes for this reading
                    out.append({"direction": name, "criterion": criterion, "model": model, "error": str(exc)})
                    continue
                # Eq. 8 in the paper's units (sigma^2 in us^2): ours - N ln 10^6.
                us = [round(v - t.n_rows * np.log(1e6), 1) for v in t.values]
                out.append(
                    {
                        "direction": name,
                        "criterion": criterion,
                        "model": model,
                        "orders": list(t.orders),
                        "values": us,
                        "n": t.n_rows,
                        "best": t.best,
                    }
                )
    return out


def run(ctx: Context) -> dict[str, Any]:
    s = ctx.strokes("aic", ctx.count(STROKES), PERIOD_NS, 12_000_000, mode="open", frequency_hz=FREQUENCY_HZ)
    all_tables = tables(s)
    head = next(
        (t for t in all_tables if "values" in t and t["criterion"] == "fit" and t["model"] == "paper"), None
    )
    if head is None:
        why = next((t["error"] for t in all_tables if "error" in t), "no strokes")
        raise NeedsStrokes(f"aic: {len(s)} strokes of run {s.run_id} are too few to fit AR(1..3): {why}")
    return {
        "orders": head["orders"],
        "values": head["values"],
        "criterion": f"{head['criterion']}, model {head['model']}, direction {head['direction']}",
        "paper": list(PAPER_AIC),
        "run_id": s.run_id,
        "tables": all_tables,
    }
