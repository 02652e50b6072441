"""What the conditions-aware models ("kalman", "rls") share, written once.

Both predict ln t through a `normalise.ConditionModel` (which the two directions of a motor share), fall
back the same way while cold (the nominal, then the last stroke, then the paper's AR(1) until
`SOUND_FIT` strokes), count the strokes they were given, warm-start from bare stroke times and keep the
same head and tail in their msgpack state. A model adds its own fit: `update`, `predict`, `state` (via
`_state`) and `from_state` (via `_restore`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, TypeVar

from .ar import SOUND_FIT, ARPredictor
from .checks import check_int, check_stroke_ns, check_strokes
from .normalise import ConditionModel

_P = TypeVar("_P", bound="ConditionedPredictor")


class ConditionedPredictor:
    """The cold start, the shared conditions, the counters and the state's frame of a model of ln t."""

    __slots__ = ("_cm", "_cold", "_count", "_nominal", "_seen")

    #: The model's name (`make_predictor`) and the `format` its state carries.
    model = ""
    STATE_FORMAT = ""

    def __init__(
        self, nominal_ns: int | None = None, sensitivities: Sequence[float | None] | None = None
    ) -> None:
        """`sensitivities`: d ln t per kHz, per 100 V, per C as the rig knows them (its commissioning,
        `usmswitch-experiment drive-sensitivity`, or what a predictor learned before); without them
        the first step of a kind is news (see `normalise.ConditionModel`)."""
        self._nominal = None if nominal_ns is None else check_stroke_ns(nominal_ns)
        self._cm = ConditionModel(sensitivities)
        self._cold: ARPredictor | None = ARPredictor(order=1, window=SOUND_FIT, nominal_ns=nominal_ns)
        self._count = 0
        self._seen = 0

    @property
    def ready(self) -> bool:
        """False while the cold-start fallback predicts (fewer than SOUND_FIT strokes)."""
        return self._cold is None

    @property
    def order(self) -> int:
        """1: an AR(1) model of the normalised log stroke time."""
        return 1

    @property
    def sensitivities(self) -> tuple[float, ...]:
        """d ln t per kHz, per 100 V, per C, as learned (see `normalise`)."""
        return self._cm.sensitivities

    @property
    def known_sensitivities(self) -> tuple[float | None, ...]:
        """The sensitivities given or learned from a step (None: never seen to act), what the daemon
        keeps across restarts (`sensitivities=` of a new predictor)."""
        return self._cm.known

    @property
    def seen(self) -> int:
        """Strokes ever given to this predictor."""
        return self._seen

    @property
    def nominal_ns(self) -> int | None:
        """The prediction before the first stroke."""
        return self._nominal

    def share_conditions_with(self, other: ConditionedPredictor) -> None:
        """Learn how the conditions act together with `other`, the other direction's predictor."""
        self._cm.share_from(other._cm)

    def extend(self, samples: Any) -> None:
        """Feed stored strokes in order (warm start); all are validated before any is taken."""
        for v in check_strokes(samples):
            self.update(v)  # type: ignore[attr-defined]  # each model's own

    def _taken(self, t_ns: int, cold_ns: int | None = None) -> None:
        """The end of every update: counted, and the cold-start fit fed until it is no longer needed
        (`cold_ns` in the stroke's place when given: what the model believes of a suspect stroke)."""
        self._count += 1
        self._seen += 1
        cold = self._cold
        if cold is not None:
            cold.update(t_ns if cold_ns is None else cold_ns)
            if self._count >= SOUND_FIT:
                self._cold = None

    # ---- persistence ---------------------------------------------------------------------------

    def _state(self, **fit: Any) -> dict[str, Any]:
        """The state: the shared frame around the model's own `fit` fields (all plain, msgpack-safe)."""
        return {
            "format": self.STATE_FORMAT,
            "nominal_ns": self._nominal,
            "conditions": self._cm.state(),
            "cold": None if self._cold is None else self._cold.state(),
            **fit,
            "count": self._count,
            "seen": self._seen,
        }

    @classmethod
    def _restore(cls: type[_P], d: Any) -> _P:
        """A predictor with the shared frame of state `d` taken (ValueError naming a bad field); the
        caller takes its model's own fields."""
        if not isinstance(d, dict) or d.get("format") != cls.STATE_FORMAT:
            raise ValueError(f"predictor state must be a dict of format {cls.STATE_FORMAT!r}")
        p = cls(nominal_ns=d.get("nominal_ns"))
        p._cm = ConditionModel.from_state(d.get("conditions"))
        p._cold = None if d.get("cold") is None else ARPredictor.from_state(d["cold"])
        p._count = check_int("count", d.get("count"), 0)
        p._seen = check_int("seen", d.get("seen"), p._count)
        return p


def finite_numbers(d: dict[str, Any], key: str, n: int) -> list[float]:
    """State field `key`: exactly `n` finite numbers (ValueError naming it otherwise)."""
    v = d.get(key)
    if not isinstance(v, list | tuple) or len(v) != n or not all(_finite(x) for x in v):
        raise ValueError(f"predictor state {key} must be {n} finite numbers, got {v!r}")
    return [float(x) for x in v]


def finite_number(d: dict[str, Any], key: str) -> float:
    """State field `key`: one finite number (ValueError naming it otherwise)."""
    v = d.get(key)
    if not _finite(v):
        raise ValueError(f"predictor state {key} must be a finite number, got {v!r}")
    return float(v)


def _finite(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
