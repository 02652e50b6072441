"""AR(1) + noise Kalman predictor on the condition-normalised log stroke time, parameters found online.

The stroke time's log, its level moved by the known conditions' changes (`normalise.ConditionModel`), is
z = mu + F + w: F an AR(1) process (friction, phi), w white noise. Its best one-step predictor is the
steady-state Kalman filter, z_hat = mu + phi (level - mu) with level = z_hat + K (z - z_hat), fixed by
two numbers: phi and the gain K (which the ratio of F's innovation to w's variance sets). Neither is
known on a real rig and both differ between rigs, so a fixed grid of (phi, K) filters, and one filter
whose phi is fitted by least squares (K = 1: the friction seen without stroke noise), run side by side
and the one with the least exponentially forgotten one-step squared error (about the last 100
strokes) predicts: prediction-error estimation of the two parameters, O(grid) per stroke, fixed memory.
mu is the mean of z over about the last 200 strokes. phi = 1 with a high K nearly repeats the last
stroke, what the paper's AR(1) does on a rig like the paper's; a smaller K averages out stroke noise;
phi < 1 pulls a mean-reverting friction back toward its mean.

Cold start: the nominal, then the last stroke, then the paper's AR(1) (`ARPredictor`) until
`SOUND_FIT` strokes; the filters learn meanwhile.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from .ar import SOUND_FIT
from .checks import MAX_T_NS, check_int, check_stroke_ns
from .conditioned import ConditionedPredictor, finite_number, finite_numbers
from .conditions import Conditions
from .normalise import NOISE_VAR

STATE_FORMAT = "usmswitch.predictor.kalman/3"
#: The (phi, K) grid: gains at phi = 1 from the last stroke itself (K = 1: a random walk under little
#: noise, where the paper's AR(1) is at home) down to 0.1 (a drifting level under much stroke noise),
#: two slowly mean-reverting filters, and three for a stationary process around its mean (phi 0.6, 0.3
#: and the mean itself, phi 0: issue 24's AR(1) with phi 0.1-0.6 plus noise, where the six filters of
#: the first grid were 1.03-1.08x the floor), and (0.9, 0.2) for a mean-reverting friction under much
#: noise (the level-shifts class between its jumps). Fewer candidates means less chance of picking
#: one by luck; each member here was measured to pay for itself on some class of process
#: (docs/predictor.md).
GRID = (
    (1.0, 1.0),
    (1.0, 0.85),
    (1.0, 0.55),
    (1.0, 0.33),
    (1.0, 0.18),
    (1.0, 0.1),
    (0.95, 0.8),
    (0.8, 1.0),
    (0.6, 0.65),
    (0.3, 0.7),
    (0.9, 0.2),
    (0.0, 0.0),
)
#: Beside the grid, one filter whose phi is fitted (K = 1): z_hat = mu + phi (z - mu), phi by least
#: squares on the deviations from mu, clipped to 0..1. It is the best one-step predictor of a stationary
#: friction seen without stroke noise whatever its phi, where the grid's nearest members are a few % off
#: (an AR(1) at phi 0.6 without noise: (0.6, 0.65) 1.023x the floor in theory, (0.8, 1) 1.031x, picked
#: between them 1.03-1.035x). Its index in the levels and scores, after GRID's.
FITTED = len(GRID)
#: Forgetting of the fitted phi's sums: memory ~ 1 / (1 - FIT_FORGET) strokes. The estimate's error
#: costs ~ (1 - FIT_FORGET) / 2 of the floor's variance.
FIT_FORGET = 0.995
#: Forgetting of the filters' squared errors (memory ~ 1 / (1 - FORGET) strokes).
FORGET = 0.99
#: Strokes over which mu is averaged.
MU_STROKES = 200
#: A stroke whose innovation (the chosen filter's one-step error) is beyond SUSPECT standard deviations
#: of that filter's recent error is suspect: it teaches nothing (no filter, score beyond SUSPECT^2
#: variances, mu nor the cold-start fit takes it) unless the next stroke of the direction is as far off
#: on the same side, which makes the two a level shift: every filter then restarts at their mean.
SUSPECT = 3.0
#: The scale of the robust rule is the chosen filter's recent error: from this many strokes on.
ROBUST_FROM = 10
#: A suspect beyond BIG standard deviations is news the predictor learns from: was it a level shift
#: (the next stroke confirmed it) or an outlier (the next stroke came back)? Gaussian noise reaches
#: this once in ~150,000 strokes, so what crosses it is one of the two.
BIG = 4.5
#: The belief that a big suspect is a level shift starts at SHIFT_PRIOR / (SHIFT_PRIOR + 1): an
#: outlier barely moves the next prediction (issue 24's outlier rule) until shifts have been seen.
#: Each judged suspect's weight is forgotten by SHIFT_FORGET (memory ~ 20 of them): a rig's habits
#: change.
SHIFT_PRIOR = 0.05
SHIFT_FORGET = 0.95
LEAN = 4.5


def _grid_step(
    levels: list[float], scores: list[float], z: float, mu: float, moved: float, phi_fit: float
) -> tuple[list[float], list[float]]:
    """One stroke z through every filter of GRID and the fitted one (phi `phi_fit`, K = 1): (new levels,
    new scores). Each filter predicts pr = phi level + (1 - phi) mu + moved (the known conditions moved
    ln t by `moved`; since phi + (1 - phi) = 1 the prediction moves by exactly that), then level =
    pr + K (z - pr) and score = FORGET score + (z - pr)^2. Written out with GRID's numbers: the loop
    over GRID costs 2.5x as much, the most of a stroke (tests/predictor/test_kalman.py checks the two
    agree)."""
    v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, _, v12 = levels  # phi = 0: the mean alone
    s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12 = scores
    p0 = v0 + moved
    p1 = v1 + moved
    p2 = v2 + moved
    p3 = v3 + moved
    p4 = v4 + moved
    p5 = v5 + moved
    p6 = 0.95 * v6 + 0.05 * mu + moved
    p7 = 0.8 * v7 + 0.2 * mu + moved
    p8 = 0.6 * v8 + 0.4 * mu + moved
    p9 = 0.3 * v9 + 0.7 * mu + moved
    p10 = 0.9 * v10 + 0.1 * mu + moved
    p11 = mu + moved
    p12 = phi_fit * v12 + (1.0 - phi_fit) * mu + moved
    e0 = z - p0
    e1 = z - p1
    e2 = z - p2
    e3 = z - p3
    e4 = z - p4
    e5 = z - p5
    e6 = z - p6
    e7 = z - p7
    e8 = z - p8
    e9 = z - p9
    e10 = z - p10
    e11 = z - p11
    e12 = z - p12
    return (
        [
            z,
            p1 + 0.85 * e1,
            p2 + 0.55 * e2,
            p3 + 0.33 * e3,
            p4 + 0.18 * e4,
            p5 + 0.1 * e5,
            p6 + 0.8 * e6,
            z,
            p8 + 0.65 * e8,
            p9 + 0.7 * e9,
            p10 + 0.2 * e10,
            p11,
            z,
        ],
        [
            0.99 * s0 + e0 * e0,
            0.99 * s1 + e1 * e1,
            0.99 * s2 + e2 * e2,
            0.99 * s3 + e3 * e3,
            0.99 * s4 + e4 * e4,
            0.99 * s5 + e5 * e5,
            0.99 * s6 + e6 * e6,
            0.99 * s7 + e7 * e7,
            0.99 * s8 + e8 * e8,
            0.99 * s9 + e9 * e9,
            0.99 * s10 + e10 * e10,
            0.99 * s11 + e11 * e11,
            0.99 * s12 + e12 * e12,
        ],
    )


def _members(phi_fit: float) -> tuple[tuple[float, float], ...]:
    """(phi, K) of every filter: GRID's, then the fitted one."""
    return (*GRID, (phi_fit, 1.0))


def _fitted_phi(sxy: float, sxx: float) -> float:
    """The least-squares phi of the deviations from mu, x_k = phi x_{k-1}, clipped to 0..1 (0: none yet)."""
    if sxx <= 0.0 or sxy <= 0.0:
        return 0.0
    return 1.0 if sxy >= sxx else sxy / sxx


def _hold(levels: list[float], mu: float, moved: float, phi_fit: float) -> list[float]:
    """Every filter's prediction with no measurement (a suspect stroke): pr = phi level + (1 - phi) mu
    + moved."""
    return [phi * v + (1.0 - phi) * mu + moved for (phi, _), v in zip(_members(phi_fit), levels, strict=True)]


def _pending(v: Any) -> tuple[float, float, float]:
    """State field `pending`: (innovation, ln t, lean); a state from before the lean has two."""
    n = len(v) if isinstance(v, list | tuple) else 0
    got = finite_numbers({"pending": v}, "pending", 2 if n == 2 else 3)
    return (got[0], got[1], got[2] if n == 3 else 0.0)


class KalmanPredictor(ConditionedPredictor):
    """AR(1) + noise Kalman filter on the log stroke time, (phi, K) chosen online by recent error."""

    __slots__ = (
        "_best",
        "_judged",
        "_level",
        "_mu",
        "_pending",
        "_phi_fit",
        "_score",
        "_shifts",
        "_sxx",
        "_sxy",
        "_zhat",
    )

    model = "kalman"
    STATE_FORMAT = STATE_FORMAT

    def __init__(
        self, nominal_ns: int | None = None, sensitivities: Sequence[float | None] | None = None
    ) -> None:
        super().__init__(nominal_ns, sensitivities)
        self._level = [0.0] * (FITTED + 1)
        self._score = [0.0] * (FITTED + 1)
        # The fitted filter's phi and its forgotten sums of x_k x_{k-1} and x_{k-1}^2 (x = z - mu).
        self._sxy = self._sxx = self._phi_fit = 0.0
        self._mu = 0.0
        self._zhat = 0.0  # ln t_hat of the next stroke before its conditions' shift
        self._best = 0
        # A suspect stroke not yet judged: (its innovation, its ln t, what the belief in a shift added
        # to the next prediction), else None.
        self._pending: tuple[float, float, float] | None = None
        # Big suspects judged, and of those the level shifts (forgotten sums): the belief in a shift.
        self._judged = 0.0
        self._shifts = 0.0

    # ---- the Predictor calls -------------------------------------------------------------------

    @property
    def coefficients(self) -> tuple[float, ...]:
        """(phi, K) of the filter predicting now; while cold, the paper's AR(1)'s (a_1,) or ()."""
        cold = self._cold
        return self._phi_k(self._best) if cold is None else cold.coefficients

    def _phi_k(self, i: int) -> tuple[float, float]:
        """(phi, K) of filter i (GRID's, or the fitted one)."""
        return GRID[i] if i < FITTED else (self._phi_fit, 1.0)

    def update(self, t_ns: int, conditions: Conditions | None = None) -> None:
        """Learn the stroke just finished (ns) under its conditions. O(grid)."""
        if type(t_ns) is not int or t_ns <= 0 or t_ns > MAX_T_NS:
            t_ns = check_stroke_ns(t_ns)
        z = math.log(t_ns)
        # The best filter's recent one-step error variance: what the conditions' change cannot explain.
        noise = (1.0 - FORGET) * self._score[self._best] if self._count > SOUND_FIT else NOISE_VAR
        moved = self._cm.learn(z, self._zhat if self._count else None, conditions, noise)
        count = self._count
        if count == 0:
            self._mu = z
            self._level = [z] * (FITTED + 1)
            self._zhat = z
            self._taken(t_ns)
            return
        mu = self._mu
        scores = self._score
        best = self._best
        pending = self._pending
        # The chosen filter's prediction of this stroke, before the belief in a shift moved it.
        pb = self._zhat + moved - (0.0 if pending is None else pending[2])
        e = z - pb  # its innovation
        if count >= ROBUST_FROM:
            # The chosen filter's recent error variance: its forgotten sum over its weights' sum.
            m = count - 1
            var = scores[best] * ((1.0 - FORGET) / (1.0 - FORGET**m) if m < 2000 else 1.0 - FORGET)
            cap = SUSPECT * SUSPECT * var
            if e * e > cap:
                if pending is not None and 0.5 <= e / pending[0] <= 2.0:
                    # Off on the same side as the suspect before, by half to twice as much: a level
                    # shift (an outlier after a suspect stroke is not one). Every filter restarts at the
                    # two strokes' mean, mu moves with them.
                    self._judge(pending, var, shift=True)
                    new = 0.5 * (pending[1] + moved + z)
                    self._pending = None
                    self._level = [new] * (FITTED + 1)
                    self._mu = mu + moved + (new - pb)
                    self._score = [FORGET * sc + cap for sc in scores]
                    self._zhat = new
                    self._taken(t_ns)
                    return
                # Suspect: its innovation's influence redescends from SUSPECT sds to none at 2.5x that
                # (every filter's innovation scaled alike), every score takes the same bounded loss.
                if pending is not None:
                    self._judge(pending, var, shift=False)
                sd = math.sqrt(var)
                w = max(0.0, (2.5 * SUSPECT * sd / abs(e) - 1.0) / 1.5)
                phi_fit = self._phi_fit
                members = _members(phi_fit)
                levels = [
                    pr + k * w * (z - pr)
                    for (phi, k), pr in zip(members, _hold(self._level, mu, moved, phi_fit), strict=True)
                ]
                self._level = levels
                self._score = [FORGET * sc + cap for sc in scores]
                self._mu = mu = mu + moved
                zhat = mu + members[best][0] * (levels[best] - mu)
                # The next prediction leans toward this stroke by the belief that a big suspect is a
                # level shift (learned from the big suspects before it); the filters do not.
                lean = 0.0
                if e * e > LEAN * LEAN * var:
                    lean = (self._shifts + SHIFT_PRIOR) / (self._judged + SHIFT_PRIOR + 1.0) * (z - zhat)
                self._pending = (e, z, lean)
                self._zhat = zhat + lean
                self._taken(t_ns, min(MAX_T_NS, max(1, round(math.exp(pb + w * e)))))  # the cold fit
                return
        if pending is not None:
            self._judge(pending, (1.0 - FORGET) * scores[best], shift=False)
            self._pending = None
        phi_fit = self._phi_fit
        x0 = self._level[FITTED] - mu  # the last stroke's deviation from the mean, and this one's
        levels, scores = _grid_step(self._level, scores, z, mu, moved, phi_fit)
        x1 = z - moved - mu
        self._sxy = sxy = FIT_FORGET * self._sxy + x0 * x1
        self._sxx = sxx = FIT_FORGET * self._sxx + x0 * x0
        self._phi_fit = phi_fit = _fitted_phi(sxy, sxx)
        self._score = scores
        self._best = best = scores.index(min(scores))
        mu += moved
        n = count + 1
        mu += (z - mu) / (n if n < MU_STROKES else MU_STROKES)
        zhat = mu + (GRID[best][0] if best < FITTED else phi_fit) * (levels[best] - mu)
        self._level = levels
        self._mu = mu
        self._zhat = zhat
        self._taken(t_ns)

    def _judge(self, pending: tuple[float, float, float], var: float, *, shift: bool) -> None:
        """Count a judged suspect in the belief in a shift, if it was big."""
        if pending[0] * pending[0] > BIG * BIG * var:
            self._judged = SHIFT_FORGET * self._judged + 1.0
            self._shifts = SHIFT_FORGET * self._shifts + (1.0 if shift else 0.0)

    def predict(self, conditions: Conditions | None = None) -> float:
        """t_hat of the next stroke (ns) under its conditions (the last ones told when None)."""
        if self._cold is not None:
            return self._cold.predict()
        return math.exp(self._zhat + self._cm.shift(conditions))

    # ---- persistence ---------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """Plain-typed state (msgpack-safe); `from_state` rebuilds one that predicts identically."""
        pending = None if self._pending is None else list(self._pending)
        return self._state(
            level=list(self._level),
            score=list(self._score),
            fit=[self._sxy, self._sxx],
            mu=self._mu,
            best=self._best,
            pending=pending,
            judged=self._judged,
            shifts=self._shifts,
        )

    @classmethod
    def from_state(cls, d: Any) -> KalmanPredictor:
        """Rebuild from `state()`; ValueError naming the field if the state is bad."""
        p = cls._restore(d)
        n = FITTED + 1
        p._level = finite_numbers(d, "level", n)
        p._score = finite_numbers(d, "score", n)
        sxy, sxx = finite_numbers(d, "fit", 2)
        if sxx < 0.0:
            raise ValueError(f"predictor state fit must have a sum of squares >= 0, got {sxx!r}")
        p._sxy, p._sxx, p._phi_fit = sxy, sxx, _fitted_phi(sxy, sxx)
        p._mu = mu = finite_number(d, "mu")
        p._best = best = check_int("best", d.get("best"), 0, n - 1)
        p._pending = None if d.get("pending") is None else _pending(d["pending"])
        # Absent from states written before the belief in a shift was kept: none seen.
        p._judged = 0.0 if d.get("judged") is None else finite_number(d, "judged")
        p._shifts = 0.0 if d.get("shifts") is None else finite_number(d, "shifts")
        if not 0.0 <= p._shifts <= p._judged:
            raise ValueError(f"predictor state: shifts {p._shifts} must be within 0..judged {p._judged}")
        lean = 0.0 if p._pending is None else p._pending[2]
        p._zhat = mu + p._phi_k(best)[0] * (p._level[best] - mu) + lean
        return p

    def __repr__(self) -> str:
        return f"KalmanPredictor(seen={self._seen}, ready={self.ready}, phi_k={self.coefficients})"
