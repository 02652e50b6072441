"""Condition-normalised least squares with forgetting: an AR(1) with intercept on the log stroke time
less what the known conditions explain, fitted by recursive least squares.

x = ln t - O, O the sum of the shifts the known conditions' changes made (`normalise.ConditionModel`,
s . dc at each change), so a drive step or the motor's warming is no step in x. x_k - m = c + a (x_{k-1}
- m) + e (m: the first x, so the regressors are of order 0.1, not 16) is fitted by recursive least
squares with forgetting `FORGET` (memory ~1 / (1 - FORGET) strokes), the covariance capped at its prior
so a long run of identical strokes cannot blow it up. The prediction is O' + m + c + a (x - m), O' the
offset under the next stroke's conditions. Fixed memory, O(1) per stroke (a 2x2 update).

Cold start as "kalman": the nominal, the last stroke, the paper's AR(1) until `SOUND_FIT` strokes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from .checks import MAX_T_NS, check_stroke_ns
from .conditioned import ConditionedPredictor, finite_number, finite_numbers
from .conditions import Conditions
from .normalise import NOISE_VAR

STATE_FORMAT = "usmswitch.predictor.rls/1"
#: Forgetting per stroke: memory ~100 strokes (the friction wanders over tens to hundreds).
FORGET = 0.99
#: Prior (and cap) of the covariance of (c, a), and the start: c = 0, a = 1 (repeat the last stroke).
P_PRIOR = 100.0


class RlsPredictor(ConditionedPredictor):
    """AR(1) + intercept on the condition-normalised log stroke time, recursive least squares."""

    __slots__ = ("_a", "_c", "_m", "_off", "_p", "_var", "_x")

    model = "rls"
    STATE_FORMAT = STATE_FORMAT

    def __init__(
        self, nominal_ns: int | None = None, sensitivities: Sequence[float | None] | None = None
    ) -> None:
        super().__init__(nominal_ns, sensitivities)
        self._c = 0.0
        self._a = 1.0
        self._p = [P_PRIOR, 0.0, P_PRIOR]  # (c c, c a, a a)
        self._off = 0.0  # O: what the conditions' changes moved ln t, summed
        self._m = 0.0
        self._x = 0.0  # the last stroke's x - m
        self._var = NOISE_VAR  # the one-step error's variance, forgotten as the fit is

    @property
    def coefficients(self) -> tuple[float, ...]:
        """(c, a) of the fit on x - m; while cold, the paper's AR(1)'s (a_1,) or ()."""
        cold = self._cold
        return (self._c, self._a) if cold is None else cold.coefficients

    def update(self, t_ns: int, conditions: Conditions | None = None) -> None:
        """Learn the stroke just finished (ns) under its conditions. O(1)."""
        if type(t_ns) is not int or t_ns <= 0 or t_ns > MAX_T_NS:
            t_ns = check_stroke_ns(t_ns)
        z = math.log(t_ns)
        if self._count == 0:
            self._cm.learn(z, None, conditions)
            self._m = z
            self._x = 0.0
        else:
            m, x0 = self._m, self._x
            y_hat = self._off + m + self._c + self._a * x0  # before the conditions' shift
            moved = self._cm.learn(z, y_hat, conditions, self._var)
            self._off = off = self._off + moved
            x = z - off - m
            # RLS on the regressors (1, x0) -> x, P = (pcc, pca, paa) symmetric.
            pcc, pca, paa = self._p
            g0 = pcc + pca * x0
            g1 = pca + paa * x0
            e = x - self._c - self._a * x0
            den = FORGET + g0 + g1 * x0
            self._c += g0 * e / den
            self._a += g1 * e / den
            pcc = (pcc - g0 * g0 / den) / FORGET
            pca = (pca - g0 * g1 / den) / FORGET
            paa = (paa - g1 * g1 / den) / FORGET
            if pcc > P_PRIOR or paa > P_PRIOR:  # cap: never more uncertain than the prior
                f = P_PRIOR / max(pcc, paa)
                pcc, pca, paa = pcc * f, pca * f, paa * f
            self._p = [pcc, pca, paa]
            self._var = FORGET * self._var + (1.0 - FORGET) * e * e
            self._x = x
        self._taken(t_ns)

    def predict(self, conditions: Conditions | None = None) -> float:
        """t_hat of the next stroke (ns) under its conditions (the last ones told when None)."""
        if self._cold is not None:
            return self._cold.predict()
        return math.exp(self._off + self._m + self._c + self._a * self._x + self._cm.shift(conditions))

    def state(self) -> dict[str, Any]:
        """Plain-typed state (msgpack-safe); `from_state` rebuilds one that predicts identically."""
        return self._state(
            fit=[self._c, self._a], p=list(self._p), offset=self._off, m=self._m, x=self._x, var=self._var
        )

    @classmethod
    def from_state(cls, d: Any) -> RlsPredictor:
        """Rebuild from `state()`; ValueError naming the field if the state is bad."""
        p = cls._restore(d)
        p._c, p._a = finite_numbers(d, "fit", 2)
        p._p = finite_numbers(d, "p", 3)
        p._off, p._m, p._x, p._var = (finite_number(d, k) for k in ("offset", "m", "x", "var"))
        return p

    def __repr__(self) -> str:
        return f"RlsPredictor(seen={self._seen}, ready={self.ready}, c_a={self.coefficients})"
