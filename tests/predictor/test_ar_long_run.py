"""10^6 updates: no drift (the sums stay exact) and no growth in memory (tracemalloc)."""

from __future__ import annotations

import gc
import tracemalloc

import numpy as np
from ar_series import lstsq_forecast

from usmswitch.predictor import ARPredictor


def _long_series(n: int, seed: int) -> list[int]:
    # Wide swings (5..15 ms) so that the sums pass through many magnitudes on the way.
    rng = np.random.default_rng(seed)
    slow = 5e6 * np.sin(np.arange(n) * 2 * np.pi / 97_003.0)
    return [int(v) for v in np.rint(1e7 + slow + rng.normal(0.0, 1e5, n))]


def _fresh(p: ARPredictor) -> ARPredictor:
    q = ARPredictor(order=p.order, window=p.window, model=p.model)
    q.extend(p.samples())
    return q


def _assert_equals_fresh_fit(p: ARPredictor) -> None:
    q = _fresh(p)
    # A predictor built from just the window is bit-identical: the sums did not drift.
    assert p.solution == q.solution
    assert p.predict() == q.predict()
    assert p.coefficients == q.coefficients
    ref, coef = lstsq_forecast(p.samples(), p.order, p.model)
    assert abs(p.predict() - ref) <= 1e-9 * ref
    np.testing.assert_allclose(p.coefficients, coef, rtol=1e-9)


def _run(p: ARPredictor, values: list[int], start: int, stop: int) -> None:
    update = p.update
    predict = p.predict
    for i in range(start, stop):  # no slicing: a copy of the input would show as growth
        update(values[i])
        predict()


def _traced_run(p: ARPredictor, values: list[int], start: int) -> tuple[int, int, int]:
    """Feed values[start:] under tracemalloc: (memory after a tenth, at the end, peak) above the start."""
    gc.collect()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tenth = start + (len(values) - start) // 10
        _run(p, values, start, tenth)
        early = tracemalloc.get_traced_memory()[0] - base
        _run(p, values, tenth, len(values))
        current, peak = tracemalloc.get_traced_memory()
        return early, current - base, peak - base
    finally:
        tracemalloc.stop()


def test_a_million_ar1_updates_equal_a_fresh_fit_in_flat_memory() -> None:
    values = _long_series(1_000_000, seed=31)
    p = ARPredictor(order=1, window=100, model="paper")
    p.extend(values[:1000])
    _assert_equals_fresh_fit(p)
    _run(p, values, 1000, 900_000)
    _assert_equals_fresh_fit(p)
    # tracemalloc slows every allocation down several times: trace the last 100k strokes only.
    early, end, peak = _traced_run(p, values, 900_000)
    assert p.seen == 1_000_000
    _assert_equals_fresh_fit(p)
    assert end - early <= 1024, f"memory grew by {end - early} bytes over 90k updates"
    assert peak <= 64 * 1024, f"peak {peak} bytes above the start"


def test_general_path_updates_equal_a_fresh_fit_in_flat_memory() -> None:
    # The O(m^2) general path (order 3, centered) with its exact elimination on every stroke.
    values = _long_series(48_000, seed=32)
    p = ARPredictor(order=3, window=100, model="centered")
    p.extend(values[:10_000])
    _assert_equals_fresh_fit(p)
    _run(p, values, 10_000, 45_000)
    early, end, peak = _traced_run(p, values, 45_000)
    _assert_equals_fresh_fit(p)
    assert end - early <= 1024, f"memory grew by {end - early} bytes over 2.7k updates"
    assert peak <= 64 * 1024, f"peak {peak} bytes above the start"
