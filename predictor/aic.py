"""AIC order selection (paper Eq. 8-9): AIC(m) = N ln(sigma^2) + 2k.

The "fit" table is here; `selection.py` adds the "rolling" one (it runs the predictor) and
`aic_table`/`select_order`, which choose between them. Two readings of sigma^2, both over one
common set of N strokes so that the orders are compared fairly:

- `criterion="fit"` (the default, and what `ARPredictor(order="auto")` uses): sigma^2 = RSS_m / N, the
  maximum-likelihood residual variance of the least-squares AR(m) fit over the last N = n - max_order
  strokes of the n samples (the first max_order strokes are held back as lags for every order), and
  k = m (+1 for the centered model's intercept). This is statsmodels' convention with
  `AutoReg(samples, lags=m, trend="n", hold_back=max_order)`: its `aic` equals
  ours + N (1 + ln 2 pi) + 2, the same for every m, so both pick the same order.
- `criterion="rolling"`: sigma^2 is the mean square of the one-step prediction errors
  gamma_{n+1} = t_{n+1} - t_hat_{n+1} (Eq. 9) of a limited-memory predictor with the given `window`,
  over the strokes predicted from a full window (cold-start predictions would inflate the higher orders).
  This is Eq. 9 read literally, and it is
  the only reading under which AIC can grow with m as fast as the paper's Table 2 does (for the
  in-sample fit on common rows, RSS cannot grow with m, so AIC(m+1) - AIC(m) <= 2).

sigma^2 is in ns^2 (the paper's Table 2 is in us^2: its values are ours - N ln 10^6), floored at
1/12 ns^2, the variance of rounding to whole nanoseconds, so that an exact fit gives a finite AIC.
Ties go to the lower order.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from .checks import MAX_ORDER, check_int, check_model, check_stroke_ns
from .exact import NormalPlan

# One index plan per largest order (AIC's sums use the flat layout of `NormalPlan`).
_PLANS = {m: NormalPlan(m) for m in range(1, MAX_ORDER + 1)}

#: Variance of rounding a time to a whole nanosecond; the floor of sigma^2.
SIGMA2_FLOOR_NS2 = 1.0 / 12.0


@dataclass(frozen=True, slots=True)
class AicTable:
    """AIC(m) for m = 1..max_order over N strokes, in the form of the paper's Table 2."""

    orders: tuple[int, ...]
    values: tuple[float, ...]
    sigma2_ns2: tuple[float, ...]
    n_rows: int  # N of Eq. 8
    model: str
    criterion: str

    @property
    def best(self) -> int:
        """The order with the smallest AIC (the lower one on a tie)."""
        return self.orders[min(range(len(self.values)), key=self.values.__getitem__)]

    def format(self, decimals: int = 1) -> str:
        """The two-row table of the paper's Table 2 (m / AIC(m))."""
        head = ["m", *[str(m) for m in self.orders]]
        body = ["AIC (m)", *[f"{v:.{decimals}f}" for v in self.values]]
        widths = [max(len(a), len(b)) for a, b in zip(head, body, strict=True)]
        return "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in (head, body))

    def __str__(self) -> str:
        return self.format()


def _aic(n_rows: int, sigma2: float, k: int) -> float:
    return n_rows * math.log(max(sigma2, SIGMA2_FLOOR_NS2)) + 2 * k


def min_samples(max_order: int, model: str) -> int:
    """Fewest samples the "fit" criterion needs: N = n - max_order must exceed the parameters by 2."""
    return 2 * max_order + 2 + (model == "centered")


def fit_table(samples: Iterable[int], max_order: int = MAX_ORDER, model: str = "paper") -> AicTable:
    """Eq. 8, `criterion="fit"`, for every order 1..max_order over `samples` (ns, oldest first)."""
    check_model(model)
    check_int("max_order", max_order, 1, MAX_ORDER)
    values = [check_stroke_ns(v) for v in samples]
    need = min_samples(max_order, model)
    if len(values) < need:
        raise ValueError(
            f"AIC up to order {max_order} ({model}) needs at least {need} strokes, got {len(values)}"
        )
    n = len(values)
    # Common rows i = max_order..n-1: column 0 the target, column j its lag j.
    columns = [values[max_order - j : n - j] for j in range(max_order + 1)]
    gram = _PLANS[max_order].gram(columns)
    return table_from_gram(gram, [sum(col) for col in columns], n - max_order, model)


def table_from_gram(gram: list[int], sums: list[int], n_rows: int, model: str = "paper") -> AicTable:
    """Eq. 8 from the common rows' exact sums (see `aic_values`) as the table."""
    aics, sigma2 = aic_values(gram, sums, n_rows, model)
    return AicTable(tuple(range(1, len(sums))), aics, sigma2, n_rows, model, "fit")


def aic_values(
    gram: list[int], sums: list[int], n_rows: int, model: str = "paper"
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(AIC(m), sigma^2) for m = 1..M from the common rows' exact sums: `gram` the upper triangle of
    [[y.y, y^T X], [X^T y, X^T X]] over lags 0..M in the flat layout of `NormalPlan(M)` (read, not
    changed) and `sums` the columns' sums (used by "centered"). O(M^3), no pass over the strokes."""
    max_order = len(sums) - 1
    plan = _PLANS[max_order]
    c = 1 if model == "centered" else 0
    if c:
        a = [0] * plan.size
        for idx, j, k in plan.gram_pairs:
            a[idx] = n_rows * gram[idx] - sums[j] * sums[k]
    else:
        a = gram[:]
    scale = n_rows * (n_rows if c else 1)
    sigma2 = tuple([num / (den * scale) for num, den in plan.nested_rss(a)])
    return tuple([_aic(n_rows, s2, m + c) for m, s2 in enumerate(sigma2, 1)]), sigma2
