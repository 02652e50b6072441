"""The closed-form solve of orders 2 and 3 against the fraction-free elimination it stands in for."""

from __future__ import annotations

import numpy as np
import pytest

from usmswitch.predictor.exact import NormalPlan, solve_small


def _normal_equations(x: list[int], m: int) -> list[int]:
    """Flat upper-triangle sums (NormalPlan layout) of the AR(m) rows of x."""
    plan = NormalPlan(m)
    n = len(x)
    cols = [x[m - j : n - j] for j in range(m + 1)]
    a = [0] * plan.size
    for idx, j, k in plan.pairs:
        a[idx] = sum(u * v for u, v in zip(cols[j], cols[k], strict=True))
    return a


@pytest.mark.parametrize("m", [2, 3])
@pytest.mark.parametrize("seed", range(20))
def test_closed_form_equals_the_elimination_bit_for_bit(m: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = [int(v) for v in np.rint(1e7 + np.cumsum(rng.normal(0.0, 1e5, 100)))]
    a = _normal_equations(x, m)
    assert solve_small(a, m) == NormalPlan(m).solve(a[:])


@pytest.mark.parametrize("m", [2, 3])
def test_a_singular_system_is_left_to_the_elimination(m: int) -> None:
    # A constant series: every lag's column is the same, so X^T X is singular and lags must be dropped.
    a = _normal_equations([10_000_000] * 40, m)
    assert solve_small(a, m) is None
    assert NormalPlan(m).solve(a[:])[2]  # the elimination drops it


def test_other_orders_are_not_solved_in_closed_form() -> None:
    a = _normal_equations(list(range(10_000_000, 10_000_400, 7)), 4)
    assert solve_small(a, 4) is None
