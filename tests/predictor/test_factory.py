"""make_predictor, DEFAULT_MODEL and the conditions-aware calls: every model by name, the paper's exact."""

from __future__ import annotations

import msgpack
import pytest
from ar_series import ar_no_intercept

from usmswitch.predictor import DEFAULT_MODEL, MODELS, ARPredictor, Predictor, make_predictor

CONDITIONS = {"frequency_hz": 40_000.0, "voltage_v": 500.0, "temperature_c": 31.5, "idle_ns": 50_000_000}


def test_the_default_model_is_one_of_the_models() -> None:
    assert DEFAULT_MODEL in MODELS
    assert isinstance(make_predictor(nominal_ns=10_000_000), Predictor)


def test_paper_is_the_papers_ar_predictor_exactly() -> None:
    t = ar_no_intercept([0.9, 0.1], 300, seed=3)
    ours = make_predictor("paper", nominal_ns=10_000_000, order=2, window=50)
    ref = ARPredictor(order=2, window=50, model="paper", nominal_ns=10_000_000)
    assert isinstance(ours, ARPredictor) and ours.model == "paper"
    for v in t:
        ours.update(v, CONDITIONS)
        ref.update(v)
        assert ours.predict(CONDITIONS) == ref.predict()  # conditions are taken and ignored by Eq. 2


@pytest.mark.parametrize("model", MODELS)
def test_every_model_predicts_with_or_without_conditions_and_round_trips_through_msgpack(model: str) -> None:
    t = ar_no_intercept([1.0], 200, seed=1)
    p = make_predictor(model, nominal_ns=10_000_000)
    assert p.predict() == 10_000_000.0  # nothing seen: the nominal
    p.update(t[0])
    assert p.predict() == float(t[0])  # one stroke: the last stroke
    for v in t[1:100]:
        p.update(v)
    for v in t[100:]:
        p.update(v, CONDITIONS)
    assert p.ready
    state = msgpack.unpackb(msgpack.packb(p.state()))
    q = type(p).from_state(state)
    assert q.predict(CONDITIONS) == p.predict(CONDITIONS)
    assert q.predict() == p.predict()


def test_a_bad_model_or_option_is_named() -> None:
    with pytest.raises(ValueError, match="'lstm'"):
        make_predictor("lstm")
    with pytest.raises(ValueError, match="takes no option forgetting"):
        make_predictor("paper", forgetting=0.99)
