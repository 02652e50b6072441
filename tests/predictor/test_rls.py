"""The "rls" model: condition-normalised least squares with forgetting."""

from __future__ import annotations

import math

import msgpack
import pytest
from test_kalman import series

from usmswitch.predictor import SOUND_FIT, ARPredictor, make_predictor, make_predictors
from usmswitch.predictor.rls import RlsPredictor


def _stepped(n: int, seed: int, rate: float = 0.1) -> tuple[list[int], list[dict]]:
    """Strokes whose drive steps 40 <-> 40.5 kHz every 300, ln t moving `rate` per kHz."""
    conds = [{"frequency_hz": 40_000.0 + 500.0 * ((i // 300) % 2), "voltage_v": 500.0} for i in range(n)]
    t = [
        round(8e6 * s * math.exp(rate * (c["frequency_hz"] - 40_000.0) / 1000))
        for s, c in zip(series(n, seed=seed), conds, strict=True)
    ]
    return t, conds


def test_cold_start_then_the_fit_and_a_learned_step_is_predicted() -> None:
    t, conds = _stepped(2400, seed=3)
    p = make_predictor("rls", nominal_ns=8_000_000)
    ar = ARPredictor(order=1, window=SOUND_FIT, nominal_ns=8_000_000)
    errors = []
    for i, (v, c) in enumerate(zip(t, conds, strict=True)):
        if i < SOUND_FIT:
            assert p.predict(c) == ar.predict() and not p.ready  # the paper's AR(1) while cold
        errors.append(abs(v - p.predict(c)))
        p.update(v, c)
        ar.update(v)
    assert p.ready and len(p.coefficients) == 2
    assert errors[300] > 300_000  # the first step is news
    assert p.known_sensitivities[0] == pytest.approx(0.1, abs=0.02)
    assert max(errors[i] for i in range(900, 2400, 300)) < 250_000  # later steps: a stroke's scatter
    quiet = [errors[i] for i in range(400, 2400) if i % 300 > 5]
    assert math.sqrt(sum(e * e for e in quiet) / len(quiet)) < 110_000  # floor ~84 us


def test_the_directions_share_the_sensitivities_and_the_state_round_trips() -> None:
    t, conds = _stepped(700, seed=4)
    on, off = make_predictors("rls", [8_000_000, 8_000_000], sensitivities=(0.1, None, None))
    for v, c in zip(t, conds, strict=True):
        on.update(v, c)
    assert off.known_sensitivities == on.known_sensitivities
    q = RlsPredictor.from_state(msgpack.unpackb(msgpack.packb(on.state())))
    c = {"frequency_hz": 40_000.0, "voltage_v": 500.0}
    assert q.predict(c) == on.predict(c) and q.coefficients == on.coefficients
    for v in t[:50]:
        q.update(v, c)
        on.update(v, c)
        assert q.predict(c) == on.predict(c)
    cold = make_predictor("rls", nominal_ns=8_000_000)
    cold.extend(t[:5])
    assert RlsPredictor.from_state(cold.state()).predict() == cold.predict()
    with pytest.raises(ValueError, match="fit"):
        RlsPredictor.from_state({**on.state(), "fit": [0.0, float("nan")]})
    with pytest.raises(ValueError, match="format"):
        RlsPredictor.from_state({**on.state(), "format": "x"})
    with pytest.raises(ValueError, match="option"):
        make_predictor("rls", nominal_ns=8_000_000, order=2)
