"""The predictor equals a fresh numpy lstsq fit of the same window at every stroke (issue 2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ar_series import ar_around_mean, design, drifting, lstsq_forecast, steps

from usmswitch.predictor import ARPredictor

N_STROKES = 10_000
WINDOW = 100
SERIES = {
    "random_ar": lambda: ar_around_mean([0.55, 0.25], N_STROKES, seed=11),
    "drifting": lambda: drifting(N_STROKES, seed=12),
    "steps": lambda: steps(N_STROKES, seed=13),
}


@pytest.fixture(scope="module", params=sorted(SERIES))
def series(request: pytest.FixtureRequest) -> tuple[str, list[int]]:
    return request.param, SERIES[request.param]()


@pytest.mark.parametrize("model", ["paper", "centered"])
@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_prediction_equals_fresh_lstsq_at_every_stroke(series, order: int, model: str) -> None:
    name, t = series
    arr = np.asarray(t, dtype=float)
    p = ARPredictor(order=order, window=WINDOW, model=model, nominal_ns=10_000_000)
    worst = 0.0
    worst_at = -1
    checked = 0
    for i, v in enumerate(t):
        p.update(v)
        if not p.ready:
            assert math.isfinite(p.predict())  # the cold-start fallback (test_ar_degenerate checks it)
            continue
        win = arr[max(0, i + 1 - WINDOW) : i + 1]
        x, y = design(win, order, model)
        coef = np.linalg.lstsq(x, y, rcond=None)[0]
        last = win[::-1][:order]
        ref = coef[0] + coef[1:] @ last if model == "centered" else coef @ last
        rel = abs(p.predict() - ref) / abs(ref)
        if rel > worst:
            worst, worst_at = rel, i
        checked += 1
    assert checked == N_STROKES - p.min_ready + 1
    assert worst <= 1e-9, f"{name} AR({order}) {model}: rel diff {worst:.3e} at stroke {worst_at}"


@pytest.mark.parametrize("model", ["paper", "centered"])
@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_coefficients_and_residual_variance_equal_lstsq(series, order: int, model: str) -> None:
    name, t = series
    p = ARPredictor(order=order, window=WINDOW, model=model)
    for i, v in enumerate(t[:3000]):
        p.update(v)
        if i < WINDOW or i % 37:
            continue
        win = p.samples()
        ref_hat, coef = lstsq_forecast(win, order, model)
        assert p.predict() == pytest.approx(ref_hat, rel=1e-9)
        got = np.array(p.coefficients)
        assert got.shape == coef.shape
        # Every coefficient (slopes and intercept) to 1e-9; lstsq's own error here is <= ~5e-11.
        np.testing.assert_allclose(got, coef, rtol=1e-9, atol=0, err_msg=f"{name} stroke {i}")
        x, y = design(win, order, model)
        r = y - x @ coef
        assert p.residual_variance == pytest.approx(float(r @ r) / len(y), rel=1e-9)
        if model == "centered":
            assert p.intercept == got[0]
        else:
            assert p.intercept == 0.0
