"""AIC order selection by either reading of Eq. 9 (`aic.py` explains both): `aic_table`, `select_order`.

Apart from `aic.py` because the "rolling" reading runs `ARPredictor`, which itself uses the "fit"
table for `order="auto"`: this module sits above both.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from .aic import AicTable, _aic, fit_table
from .ar import ARPredictor
from .checks import MAX_ORDER, check_int, check_model, check_stroke_ns

CRITERIA = ("fit", "rolling")


def aic_table(
    samples: Iterable[int],
    max_order: int = MAX_ORDER,
    model: str = "paper",
    criterion: str = "fit",
    window: int | None = None,
) -> AicTable:
    """Eq. 8 for every order 1..max_order over `samples` (stroke times in ns, oldest first)."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    if criterion == "fit":
        if window is not None:
            raise ValueError(f"window applies to criterion='rolling' only, got window={window!r}")
        return fit_table(samples, max_order, model)
    check_model(model)
    check_int("max_order", max_order, 1, MAX_ORDER)
    return _rolling_table([check_stroke_ns(v) for v in samples], max_order, model, window)


def _rolling_table(values: list[int], max_order: int, model: str, window: int | None) -> AicTable:
    if window is None:
        raise ValueError("criterion='rolling' needs the predictor's window, got window=None")
    check_int("window", window, max_order + 2)
    predictors = [ARPredictor(order=m, window=window, model=model) for m in range(1, max_order + 1)]
    # Only predictions from a full window are scored: cold-start ones would inflate the higher orders.
    start = window
    n_rows = len(values) - start
    if n_rows < max_order + 2:
        raise ValueError(
            f"rolling AIC up to order {max_order} with window {window} needs at least "
            f"{start + max_order + 2} strokes, got {len(values)}"
        )
    sq: list[list[float]] = [[] for _ in predictors]
    for i, t in enumerate(values):
        for p, acc in zip(predictors, sq, strict=True):
            if i >= start:
                acc.append((t - p.predict()) ** 2)
            p.update(t)
    c = 1 if model == "centered" else 0
    sigma2 = [math.fsum(acc) / n_rows for acc in sq]
    orders = tuple(range(1, max_order + 1))
    aics = tuple(_aic(n_rows, s2, m + c) for m, s2 in zip(orders, sigma2, strict=True))
    return AicTable(orders, aics, tuple(sigma2), n_rows, model, "rolling")


def select_order(
    samples: Iterable[int],
    max_order: int = MAX_ORDER,
    model: str = "paper",
    criterion: str = "fit",
    window: int | None = None,
) -> tuple[int, AicTable]:
    """Pick the AR order by Eq. 8: (the order with the smallest AIC, the whole AIC table)."""
    table = aic_table(samples, max_order, model, criterion, window)
    return table.best, table
