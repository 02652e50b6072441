"""Bad input is refused with a ValueError that names it, and leaves the predictor untouched."""

from __future__ import annotations

import math
from decimal import Decimal
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from usmswitch.predictor import MAX_T_NS, ARPredictor, check_stroke_ns

bad_strokes = (
    st.integers(max_value=0)
    | st.integers(min_value=MAX_T_NS + 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.booleans()
    | st.none()
    | st.text(max_size=8)
    | st.fractions()
    | st.decimals(allow_nan=True)
    | st.sampled_from([np.float64(1e7), np.bool_(True), np.int64(-3), np.uint64(0), [10_000_000]])
)


def _primed() -> ARPredictor:
    p = ARPredictor(order=2, window=20, model="centered", nominal_ns=10_000_000)
    p.extend([10_000_000 + 7919 * (i % 13) for i in range(30)])
    return p


@settings(max_examples=300, deadline=None)
@given(value=bad_strokes)
def test_a_bad_stroke_is_refused_naming_it_and_changes_nothing(value) -> None:
    p = _primed()
    before = p.state()
    t_hat = p.predict()
    with pytest.raises(ValueError) as info:
        p.update(value)
    assert repr(value) in str(info.value)
    with pytest.raises(ValueError):
        p.extend([10_000_000, value])  # checked whole before any stroke is taken
    with pytest.raises(ValueError):
        check_stroke_ns(value)
    assert p.state() == before
    assert p.predict() == t_hat


@settings(max_examples=100, deadline=None)
@given(value=st.integers(min_value=1, max_value=MAX_T_NS))
def test_every_positive_integer_up_to_2_53_is_taken_also_as_a_numpy_integer(value: int) -> None:
    a = _primed()
    b = _primed()
    a.update(value)
    b.update(np.int64(value))
    assert a.state() == b.state()
    assert a.predict() == b.predict()
    assert math.isfinite(a.predict())


def test_integral_floats_are_refused_too() -> None:
    p = _primed()
    for value in (1e7, 10_000_000.0, Fraction(10_000_000), Decimal(10_000_000)):
        with pytest.raises(ValueError, match="positive integer of nanoseconds"):
            p.update(value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"order": 0}, "order must be an integer in 1..8, got 0"),
        ({"order": 9}, "got 9"),
        ({"order": True}, "got True"),
        ({"order": 2.0}, "got 2.0"),
        ({"order": "3"}, "got '3'"),
        ({"order": "AUTO"}, "got 'AUTO'"),
        ({"order": 3, "window": 4}, "window must be an integer >= 5, got 4"),
        ({"window": 50.0}, "got 50.0"),
        ({"model": "ols"}, "got 'ols'"),
        ({"nominal_ns": 0}, "got 0"),
        ({"nominal_ns": 1.2e7}, "got 12000000.0"),
        ({"nominal_ns": float("nan")}, "got nan"),
        ({"max_order": 0}, "max_order must be an integer in 1..8, got 0"),
        ({"reselect_every": 0}, "reselect_every must be an integer >= 1, got 0"),
        ({"order": "auto", "window": 17}, "window must be an integer >= 18 for order='auto'"),
        ({"order": "auto", "window": 18, "model": "centered"}, ">= 19"),
    ],
)
def test_a_bad_setting_is_refused_naming_it(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(".", r"\.")):
        ARPredictor(**kwargs)


def test_aic_of_an_order_outside_1_to_max_order_is_refused() -> None:
    p = ARPredictor(order=1, window=40, max_order=3)
    p.extend([10_000_000 + (i * 7) % 11 * 1000 for i in range(40)])
    p.aic(3)
    for bad in (0, 4, 1.0, None):
        with pytest.raises(ValueError, match=repr(bad)):
            p.aic(bad)  # type: ignore[arg-type]
    q = ARPredictor(order=1, window=40, max_order=8)
    q.extend([10_000_000] * 10)
    with pytest.raises(ValueError, match="at least 18 strokes, got 10"):
        q.aic(1)
