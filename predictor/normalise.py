"""Condition normalisation: the part of a stroke's log time the known conditions explain, learned online.

A stroke's time scales with its drive frequency, drive voltage and motor temperature. `ConditionModel`
says how much ln t moves when the conditions change from the last stroke's, s . (c - c_last), so that the
model of the remaining process (friction and noise) shifts its level by that and sees no step when the
drive setting changes. Only changes are used, never absolute levels: an error in s costs s_err . dc
once, and the process model corrects it at the next stroke. The sensitivities s are learned by
recursive least squares with forgetting on the process model's one-step error at the strokes where a
condition stepped (`MIN_STEP`): ln t_k - (ln t_hat_k + s . (c_k - c_{k-1})) = s_err . (c_k - c_{k-1}) +
innovation, the covariance capped so it never blows up. The one-step error is the innovation alone
(variance ~ the floor's), where the difference of two strokes' log times carries two strokes' scatter
and the friction's change (about 1.4x as much variance on the default rig). A missing condition holds
its last value; `idle_ns` is not used (its effect is the motor's cooling, which the temperature
carries).

Units keep s of order one: frequency in kHz, voltage in 100 V, temperature in C.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from .conditions import Conditions

#: The conditions normalised, and the unit each is taken in (kHz, 100 V, C; `_delta` inlines these).
KEYS = ("frequency_hz", "voltage_v", "temperature_c")
SCALES = (1e-3, 1e-2, 1.0)
#: Prior variance of each sensitivity (ln per unit) and the cap on its posterior variance: wide for the
#: drive (a 0.5 kHz or 50 V step moves a USM's speed by 5-20 %), narrow for temperature (a few % per C at
#: most), whose per-stroke changes are tiny beside the stroke's scatter and would teach noise.
P0 = (1.0, 1.0, 1e-3)
#: A change smaller than this (1 Hz, 0.1 V, 0.1 C) between two strokes teaches nothing (the stroke's
#: scatter hides it; the process model tracks a slow drift), so RLS runs only on real steps.
MIN_STEP = (1e-3, 1e-3, 0.1)
#: Prior variance of sensitivities the rig knows (`ConditionModel(prior)`: measured at commissioning or
#: learned before): standard deviations of 0.01 per kHz, 0.01 per 100 V and 0.003 per C. A
#: commissioning measures the drive's to +-0.003 (`usmswitch-experiment drive-sensitivity`); its value
#: is the chord of the change it made, and a step of the same kind but another size has a chord a few
#: hundredths away (the simulated rig: 0.146-0.167 per kHz for +0.25 to +1 kHz). The first stroke
#: after a step then moves s by ~a fifth of its one-step error (mostly the stroke's scatter), not ~all
#: of it as a wide prior did, which passed the first direction's scatter to the other's first stroke;
#: a step that acts otherwise than s says beyond its uncertainty resets the variance (`SURPRISE`).
P_KNOWN = (1e-4, 1e-4, 1e-5)
#: A step's one-step error beyond this many variances (3 sd) of what s's uncertainty and the scatter
#: allow resets the stepped sensitivities' variance to P0 (`_rls`).
SURPRISE = 9.0
#: Forgetting of the sensitivities' information per informative stroke.
FORGET = 0.995
#: Variance of the process model's one-step error in ln t until the caller knows better (`learn`'s
#: noise_var): a 1 % stroke scatter.
NOISE_VAR = 1e-4


class ConditionModel:
    """Learns d ln t / d condition online; says how much a change of conditions moves ln t. O(9)."""

    __slots__ = ("_c", "_known", "_p", "_s")

    def __init__(self, prior: Sequence[float | None] | None = None) -> None:
        """`prior`: d ln t per kHz, per 100 V, per C known beforehand (variance P_KNOWN); None for one
        not known (0, variance P0)."""
        n = len(KEYS)
        given = [None] * n if prior is None else check_sensitivities(prior)
        self._s = [0.0 if v is None else v for v in given]
        var = [P0[i] if v is None else P_KNOWN[i] for i, v in enumerate(given)]
        self._p = [[var[i] if i == j else 0.0 for j in range(n)] for i in range(n)]
        # Whether each sensitivity is known (given, or learned from a step of its condition).
        self._known = [v is not None for v in given]
        self._c: list[float | None] = [None] * n  # the last stroke's conditions (held when missing)

    @property
    def sensitivities(self) -> tuple[float, ...]:
        """d ln t per kHz, per 100 V, per C, as learned."""
        return tuple(self._s)

    @property
    def known(self) -> tuple[float | None, ...]:
        """The sensitivities given or learned from a step, None for one never seen to act: what a
        predictor built later may start from (`ConditionModel(prior)`)."""
        return tuple(s if k else None for s, k in zip(self._s, self._known, strict=True))

    def share_from(self, other: ConditionModel) -> None:
        """Learn the sensitivities together with `other` (the other direction of the same motor: the
        drive acts on both alike), so a step one direction has seen is known to the other at once.
        Each keeps its own last conditions and stroke; the sharing is not part of `state()`."""
        self._s = other._s
        self._p = other._p
        self._known = other._known

    def _delta(self, conditions: Conditions | None) -> tuple[list[float], list[float | None]] | None:
        """(c - c_last per key, c) for these conditions; None when nothing known changed."""
        if not conditions:
            return None
        get = conditions.get
        l0, l1, l2 = self._c
        # Each in its unit; a missing or non-finite one holds its last value (inlined: the hot path;
        # v - v == 0 is False exactly for NaN and the infinities).
        v = get("frequency_hz")
        c0 = v * 1e-3 if v is not None and v - v == 0 else l0
        v = get("voltage_v")
        c1 = v * 1e-2 if v is not None and v - v == 0 else l1
        v = get("temperature_c")
        c2 = float(v) if v is not None and v - v == 0 else l2
        if c0 == l0 and c1 == l1 and c2 == l2:
            return None
        if l0 is None or l1 is None or l2 is None or c0 is None or c1 is None or c2 is None:
            dc = [
                0.0 if c0 is None or l0 is None else c0 - l0,
                0.0 if c1 is None or l1 is None else c1 - l1,
                0.0 if c2 is None or l2 is None else c2 - l2,
            ]
        else:
            dc = [c0 - l0, c1 - l1, c2 - l2]
        return dc, [c0, c1, c2]

    def shift(self, conditions: Conditions | None) -> float:
        """s . (c - c_last): how much these conditions move ln t from the last stroke's."""
        d = self._delta(conditions)
        if d is None:
            return 0.0
        s = self._s
        dc = d[0]
        return s[0] * dc[0] + s[1] * dc[1] + s[2] * dc[2]

    def learn(
        self, y: float, y_hat: float | None, conditions: Conditions | None, noise_var: float = NOISE_VAR
    ) -> float:
        """Take a stroke's log time `y` and conditions, `y_hat` being the process model's prediction of
        it before the conditions' shift (None: it has none yet). When a condition stepped since the
        last stroke, s is updated from the one-step error y - (y_hat + s . dc), and the shift the change
        made by s so updated is returned (the stroke itself is the best evidence of how its step acted).
        `noise_var` is the variance of that error which the conditions do not explain."""
        d = self._delta(conditions)
        if d is None:
            return 0.0
        dc, c = d
        self._c = c
        s = self._s
        if y_hat is not None and (
            abs(dc[0]) >= MIN_STEP[0] or abs(dc[1]) >= MIN_STEP[1] or abs(dc[2]) >= MIN_STEP[2]
        ):
            self._rls(y - y_hat, dc, noise_var)
            known = self._known
            for i in range(len(dc)):
                if abs(dc[i]) >= MIN_STEP[i]:
                    known[i] = True
        return s[0] * dc[0] + s[1] * dc[1] + s[2] * dc[2]

    def _rls(self, dy: float, x: list[float], noise_var: float) -> None:
        n = len(x)
        p = self._p
        px = [sum(p[i][j] * x[j] for j in range(n)) for i in range(n)]
        denom = FORGET * noise_var + sum(x[i] * px[i] for i in range(n))
        err = dy - sum(self._s[i] * x[i] for i in range(n))
        if err * err > SURPRISE * denom:
            # The step acted otherwise than s said, by more than s's uncertainty and the scatter
            # explain (a chord commissioned for another change, a rig that changed): the variance of
            # each sensitivity that stepped goes back to the wide prior, so this stroke teaches it.
            for i in range(n):
                if abs(x[i]) >= MIN_STEP[i]:
                    for j in range(n):
                        p[i][j] = p[j][i] = 0.0
                    p[i][i] = P0[i]
            px = [sum(p[i][j] * x[j] for j in range(n)) for i in range(n)]
            denom = FORGET * noise_var + sum(x[i] * px[i] for i in range(n))
        for i in range(n):
            self._s[i] += px[i] * err / denom
        for i in range(n):
            for j in range(n):
                p[i][j] = (p[i][j] - px[i] * px[j] / denom) / FORGET
        for i in range(n):  # cap: never more uncertain than the prior
            if p[i][i] > P0[i]:
                f = math.sqrt(P0[i] / p[i][i])
                for j in range(n):
                    p[i][j] *= f
                    p[j][i] *= f

    def state(self) -> dict[str, Any]:
        """Plain-typed state (msgpack-safe)."""
        return {
            "s": list(self._s),
            "p": [list(r) for r in self._p],
            "c": list(self._c),
            "known": list(self._known),
        }

    @classmethod
    def from_state(cls, d: Any) -> ConditionModel:
        """Rebuild from `state()`; ValueError naming the field if it is bad."""
        m = cls()
        n = len(KEYS)
        if not isinstance(d, dict):
            raise ValueError(f"condition state must be a dict, got {type(d).__name__}")
        for key in ("s", "c"):
            v = d.get(key)
            if not isinstance(v, list | tuple) or len(v) != n:
                raise ValueError(f"condition state {key} must be a list of {n}, got {v!r}")
            if key == "s":
                m._s = [_num(key, x) for x in v]
            else:
                setattr(m, "_" + key, [None if x is None else _num(key, x) for x in v])
        p = d.get("p")
        if not isinstance(p, list | tuple) or len(p) != n or any(len(r) != n for r in p):
            raise ValueError(f"condition state p must be {n}x{n}, got {p!r}")
        m._p = [[_num("p", x) for x in r] for r in p]
        known = d.get("known", [False] * n)  # a state written before it was kept: nothing known
        if (
            not isinstance(known, list | tuple)
            or len(known) != n
            or not all(isinstance(k, bool) for k in known)
        ):
            raise ValueError(f"condition state known must be {n} booleans, got {known!r}")
        m._known = list(known)
        return m


def _num(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"condition state {name} holds {v!r}, not a finite number")
    return float(v)


def check_sensitivities(v: Any) -> list[float | None]:
    """Three finite numbers or None (d ln t per kHz, per 100 V, per C); ValueError naming the value."""
    if (
        isinstance(v, str | bytes)
        or not isinstance(v, Sequence)
        or len(v) != len(KEYS)
        or not all(
            x is None or (not isinstance(x, bool) and isinstance(x, int | float) and math.isfinite(x))
            for x in v
        )
    ):
        raise ValueError(
            f"sensitivities must be 3 finite numbers or None (per kHz, per 100 V, per C), got {v!r}"
        )
    return [None if x is None else float(x) for x in v]
