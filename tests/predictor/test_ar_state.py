"""state() round-trips through msgpack, and the restored predictor predicts exactly as the original."""

from __future__ import annotations

import math

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from usmswitch.predictor import STATE_FORMAT, ARPredictor, min_samples

strokes = st.integers(min_value=9_000_000, max_value=11_000_000) | st.integers(min_value=1, max_value=4)


@st.composite
def predictors(draw: st.DrawFn) -> ARPredictor:
    model = draw(st.sampled_from(["paper", "centered"]))
    nominal = draw(st.none() | st.integers(min_value=1, max_value=2**53))
    if draw(st.booleans()):
        max_order = draw(st.integers(min_value=1, max_value=3))
        window = draw(st.integers(min_value=min_samples(max_order, model), max_value=40))
        every = draw(st.integers(min_value=1, max_value=12))
        p = ARPredictor("auto", window, model, nominal, max_order=max_order, reselect_every=every)
    else:
        order = draw(st.integers(min_value=1, max_value=4))
        window = draw(st.integers(min_value=order + 2, max_value=40))
        p = ARPredictor(order, window, model, nominal)
    p.extend(draw(st.lists(strokes, max_size=90)))
    return p


def _observe(p: ARPredictor) -> tuple:
    t_hat = p.predict() if (p.nominal_ns is not None or p.count) else None
    return (t_hat, p.coefficients, p.ready, p.order, p.count, p.seen, p.degenerate)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(p=predictors(), future=st.lists(strokes, max_size=60))
def test_restored_predictor_predicts_exactly_like_the_original(p: ARPredictor, future: list[int]) -> None:
    wire = msgpack.packb(p.state())
    q = ARPredictor.from_state(msgpack.unpackb(wire))
    assert q.state() == p.state()
    assert _observe(q) == _observe(p)
    for v in future:
        p.update(v)
        q.update(v)
        got, want = _observe(q), _observe(p)
        assert got == want
        if got[0] is not None:
            assert math.isfinite(got[0])
    assert q.state() == p.state()


def _state() -> dict:
    p = ARPredictor(order=2, window=10, model="centered", nominal_ns=10_000_000)
    p.extend([10_000_000 + 1000 * i for i in range(12)])
    return p.state()


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("format", "usmswitch.predictor.ar/0", "format"),
        ("order", 0, "order"),
        ("window", 3, "window"),
        ("model", "ols", "model"),
        ("nominal_ns", -1, "-1"),
        ("samples", [10_000_000, 1.5], "1.5"),
        ("samples", [10_000_000] * 11, "samples"),
        ("samples", "10000000", "samples"),
        ("current_order", 3, "current_order"),
        ("seen", 5, "seen"),
        ("since_select", -2, "since_select"),
    ],
)
def test_a_bad_state_is_refused_naming_what_is_wrong(field: str, value, message: str) -> None:
    d = _state()
    d[field] = value
    with pytest.raises(ValueError, match=message):
        ARPredictor.from_state(d)


def test_a_state_without_a_field_or_not_a_dict_is_refused() -> None:
    d = _state()
    del d["samples"]
    with pytest.raises(ValueError, match="lacks samples"):
        ARPredictor.from_state(d)
    with pytest.raises(ValueError, match="dict"):
        ARPredictor.from_state([1, 2])  # type: ignore[arg-type]
    assert _state()["format"] == STATE_FORMAT
