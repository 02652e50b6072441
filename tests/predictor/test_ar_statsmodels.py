"""The predictor equals statsmodels' AutoReg on the same window, and its AIC follows AutoReg's."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ar_series import ar_around_mean, drifting, steps

from usmswitch.predictor import ARPredictor, aic_table

WINDOW = 100


def _fit(window: list[int], order: int, trend: str, hold_back: int | None = None):
    # Imported here, not at the top: statsmodels takes ~2 s of CPU to import, which every process
    # of make test would pay to collect this file, and only the one that runs it needs.
    from statsmodels.tsa.ar_model import AutoReg

    return AutoReg(np.asarray(window, dtype=float), lags=order, trend=trend, hold_back=hold_back).fit()


@pytest.mark.parametrize("order", [1, 2, 3, 4])
@pytest.mark.parametrize("series", ["random_ar", "drifting", "steps"])
def test_paper_model_equals_autoreg_trend_n(series: str, order: int) -> None:
    t = {
        "random_ar": lambda: ar_around_mean([0.6, 0.2], 1500, seed=21),
        "drifting": lambda: drifting(1500, seed=22),
        "steps": lambda: steps(1500, seed=23),
    }[series]()
    p = ARPredictor(order=order, window=WINDOW, model="paper")
    fits = 0
    for i, v in enumerate(t):
        p.update(v)
        if i < WINDOW or i % 53:
            continue
        res = _fit(p.samples(), order, "n")
        np.testing.assert_allclose(p.coefficients, res.params, rtol=1e-9, atol=0)
        ref = float(res.forecast(1)[0])
        assert abs(p.predict() - ref) <= 1e-9 * ref
        assert p.residual_variance == pytest.approx(res.sigma2, rel=1e-9)
        fits += 1
    assert fits >= 20


@pytest.mark.parametrize("order", [1, 3])
def test_centered_model_equals_autoreg_trend_c(order: int) -> None:
    t = ar_around_mean([0.5, 0.3], 800, seed=24)
    p = ARPredictor(order=order, window=WINDOW, model="centered")
    for i, v in enumerate(t):
        p.update(v)
        if i < WINDOW or i % 71:
            continue
        res = _fit(p.samples(), order, "c")
        np.testing.assert_allclose(p.coefficients, res.params, rtol=1e-9, atol=0)  # (const, a_1..a_m)
        assert abs(p.predict() - float(res.forecast(1)[0])) <= 1e-9 * p.predict()
        assert p.residual_variance == pytest.approx(res.sigma2, rel=1e-9)


@pytest.mark.parametrize(("model", "trend"), [("paper", "n"), ("centered", "c")])
def test_aic_is_autoregs_aic_less_its_constant(model: str, trend: str) -> None:
    # Ours: N ln(sigma2) + 2k over N = n - max_order common rows. AutoReg with hold_back=max_order:
    # -2 llf + 2 (k + 1) = N (ln 2pi + ln sigma2 + 1) + 2k + 2. The difference is the same for all m.
    t = ar_around_mean([0.7], 300, seed=25)
    max_order = 5
    table = aic_table(t, max_order, model)
    n_rows = len(t) - max_order
    assert table.n_rows == n_rows
    for m in range(1, max_order + 1):
        res = _fit(t, m, trend, hold_back=max_order)
        assert res.nobs == n_rows
        assert table.sigma2_ns2[m - 1] == pytest.approx(res.sigma2, rel=1e-9)
        expected = res.aic - n_rows * (1 + math.log(2 * math.pi)) - 2
        assert table.values[m - 1] == pytest.approx(expected, rel=1e-12, abs=1e-6)
    p = ARPredictor(order=1, window=len(t), model=model, max_order=max_order)
    p.extend(t)
    assert [p.aic(m) for m in range(1, max_order + 1)] == list(table.values)
