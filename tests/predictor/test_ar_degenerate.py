"""Degenerate windows, cold start and caching: finite documented results, never NaN, never a raise."""

from __future__ import annotations

import math
from fractions import Fraction

import pytest
from ar_series import exact_least_squares
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from usmswitch.predictor import SOUND_FIT, ARPredictor
from usmswitch.predictor import ar as ar_module
from usmswitch.predictor.exact import NormalPlan


@pytest.mark.parametrize("model", ["paper", "centered"])
@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_a_constant_window_predicts_the_constant(order: int, model: str) -> None:
    c = 10_250_000
    p = ARPredictor(order=order, window=30, model=model)
    p.extend([c] * 45)
    assert p.predict() == float(c)
    coef = p.coefficients
    assert all(math.isfinite(a) for a in coef)
    if model == "paper":
        # Lag 1 alone explains it (a_1 = 1); the others are linear combinations of it and are dropped.
        assert coef == (1.0,) + (0.0,) * (order - 1)
        assert p.degenerate == (order > 1)
    else:
        # Every lag is constant, i.e. collinear with the intercept: the intercept is the constant.
        assert coef == (float(c),) + (0.0,) * order
        assert p.degenerate
    assert p.residual_variance == 0.0


@pytest.mark.parametrize("model", ["paper", "centered"])
def test_a_period_two_series_drops_the_dependent_lag_and_still_fits_exactly(model: str) -> None:
    a, b = 9_900_000, 10_100_000
    t = [a, b] * 20
    p = ARPredictor(order=3, window=20, model=model)
    p.extend(t)
    assert p.degenerate  # lag 3 equals lag 1 over the window
    assert p.predict() == float(a)  # the next stroke of the pattern
    assert p.residual_variance == 0.0
    assert all(math.isfinite(x) for x in p.coefficients)


def test_an_underdetermined_minimal_window_is_finite_and_interpolates() -> None:
    # window = order + 2 gives 2 rows for 4 parameters (centered AR(3)).
    p = ARPredictor(order=3, window=5, model="centered")
    assert p.min_ready == 5
    p.extend([10_000_000, 10_300_000, 9_800_000, 10_100_000, 10_050_000, 9_950_000])
    assert p.ready and p.degenerate
    assert math.isfinite(p.predict())
    assert p.residual_variance == 0.0


def test_cold_start_nominal_then_last_stroke_then_the_papers_ar1_until_the_fit_is_sound() -> None:
    p = ARPredictor(order=2, window=50, model="centered", nominal_ns=12_000_000)
    assert p.min_ready == SOUND_FIT  # more parameters than the paper's AR(1): wait for a sound fit
    assert p.predict() == 12_000_000.0  # nothing seen: the nominal
    t = [10_000_000 + 1000 * (i * i % 7) for i in range(SOUND_FIT)]
    for i, v in enumerate(t[:-1]):
        p.update(v)
        assert not p.ready
        assert p.coefficients == () and p.solution is None and p.residual_variance == 0.0
        x = [Fraction(u) for u in t[: i + 1]]
        if len(x) < 3:
            assert p.predict() == float(x[-1])  # the last stroke, never the nominal again
        else:
            a1 = sum(u * w for u, w in zip(x[1:], x[:-1], strict=True)) / sum(u * u for u in x[:-1])
            assert p.predict() == float(a1 * x[-1])  # Eq. 5-6 for m = 1 on the window, exact
    p.update(t[-1])
    assert p.ready
    assert len(p.coefficients) == 3


def test_the_papers_ar1_is_ready_at_three_strokes_and_small_windows_cap_the_wait() -> None:
    assert ARPredictor(order=1, window=100).min_ready == 3
    assert ARPredictor(order=1, window=100, model="centered").min_ready == SOUND_FIT
    assert ARPredictor(order=3, window=100).min_ready == SOUND_FIT
    assert ARPredictor(order=3, window=20).min_ready == 20  # never more than the window


def test_cold_start_without_a_nominal_predicts_the_last_stroke_or_refuses_when_empty() -> None:
    p = ARPredictor(order=1, window=10)
    with pytest.raises(RuntimeError, match="nominal_ns"):
        p.predict()
    p.update(10_000_000)
    p.update(10_000_003)
    assert p.predict() == 10_000_003.0


@pytest.mark.parametrize("order", [3, 4])  # 3 in closed form, 4 by the elimination
def test_predict_solves_once_per_stroke(monkeypatch: pytest.MonkeyPatch, order: int) -> None:
    calls = []
    real = NormalPlan.solve
    real_small = ar_module.solve_small

    def counting(self, a):
        calls.append(1)
        return real(self, a)

    def counting_small(a, m):
        sol = real_small(a, m)
        if sol is not None:  # None: not solved here, the elimination solves
            calls.append(1)
        return sol

    monkeypatch.setattr(NormalPlan, "solve", counting)
    monkeypatch.setattr(ar_module, "solve_small", counting_small)
    p = ARPredictor(order=order, window=30)
    p.extend([10_000_000 + 1000 * ((i * 37) % 11) for i in range(40)])
    assert calls == []  # updates alone do not solve
    first = p.predict()
    assert p.predict() == first
    _ = p.coefficients, p.intercept, p.degenerate, p.solution
    assert len(calls) == 1
    p.update(10_003_000)
    p.predict()
    _ = p.coefficients
    assert len(calls) == 2


tiny = st.lists(st.sampled_from([10_000_000, 10_000_001, 10_000_003]), min_size=1, max_size=40)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    t=tiny,
    order=st.integers(min_value=1, max_value=4),
    model=st.sampled_from(["paper", "centered"]),
    extra=st.integers(min_value=0, max_value=12),
)
def test_near_degenerate_windows_are_finite_and_an_exact_least_squares_fit(t, order, model, extra) -> None:
    # Values 1 ns apart on 10 ms make singular and very ill-conditioned windows common (lstsq itself
    # is not accurate there), so the reference is exact rational least squares.
    p = ARPredictor(order=order, window=order + 2 + extra, model=model, nominal_ns=10_000_000)
    for v in t:
        p.update(v)
        t_hat = p.predict()
        assert math.isfinite(t_hat)
        assert all(math.isfinite(c) for c in p.coefficients)
        if not p.ready:
            continue
        win = p.samples()
        rank, rss, coef = exact_least_squares(win, order, model)
        rows = len(win) - order
        # Any least-squares solution has the residuals of the projection: the basic one included.
        assert p.residual_variance == float(rss / rows)
        if coef is None:
            assert p.degenerate
            continue
        assert not p.degenerate
        last = [Fraction(x) for x in win[::-1][:order]]
        regressors = [Fraction(1), *last] if model == "centered" else last
        exact = sum((c * x for c, x in zip(coef, regressors, strict=True)), Fraction(0))
        assert t_hat == float(exact)  # one correctly rounded division
        assert p.coefficients == tuple(float(c) for c in coef)  # each one correctly rounded too
