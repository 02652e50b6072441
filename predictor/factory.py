"""Any predictor by name: `make_predictor(model, nominal_ns=..., **options)`, `DEFAULT_MODEL`, `Predictor`.

Every model answers the same calls as `ARPredictor` (the daemon's loop, warm start and status use
these and nothing else), so the paper's exact method stays one config word away (`model = "paper"`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

from .ar import ARPredictor
from .checks import AR_MODELS, MODELS
from .conditioned import ConditionedPredictor
from .conditions import Conditions
from .kalman import KalmanPredictor
from .rls import RlsPredictor

#: The options each model takes.
_AR_OPTIONS = frozenset({"order", "window", "max_order", "reselect_every"})
OPTIONS: dict[str, frozenset[str]] = {
    "paper": _AR_OPTIONS,
    "centered": _AR_OPTIONS,
    "kalman": frozenset({"sensitivities"}),
    "rls": frozenset({"sensitivities"}),
}

#: The model the daemon runs when its config does not name one.
DEFAULT_MODEL = "kalman"


@runtime_checkable
class Predictor(Protocol):
    """What the daemon asks of a stroke-time predictor (one per direction)."""

    @property
    def ready(self) -> bool:
        """False while predictions come from the cold-start fallback, not the model's own fit."""
        ...

    @property
    def order(self) -> int:
        """The AR order in use (1 for models that are not AR(m) fits)."""
        ...

    @property
    def coefficients(self) -> tuple[float, ...]:
        """The model's current coefficients, () while cold."""
        ...

    def update(self, t_ns: int, conditions: Conditions | None = None) -> None:
        """Learn the stroke just finished (ns) under its conditions."""
        ...

    def predict(self, conditions: Conditions | None = None) -> float:
        """t_hat of the next stroke (ns) under its conditions."""
        ...

    def extend(self, samples: Any) -> None:
        """Feed stored strokes in order (warm start)."""
        ...

    def state(self) -> dict[str, Any]:
        """Plain-typed (msgpack-safe) state."""
        ...


def make_predictor(model: str = DEFAULT_MODEL, nominal_ns: int | None = None, **options: Any) -> Predictor:
    """Build the predictor `model` names (one of `MODELS`) with its options; ValueError naming a bad one.

    "paper" is the paper's Eq. 2-6 exactly, "centered" the same with a least-squares intercept; both
    take `order` (1..8 or "auto"), `window`, `max_order` and `reselect_every` (see `ARPredictor`).
    "kalman" (`KalmanPredictor`) takes `sensitivities`: d ln t per kHz, per 100 V, per C as the rig
    knows them (commissioning, or what it learned before), so a drive step is predicted at once.
    "rls" (`RlsPredictor`: condition-normalised least squares with forgetting) takes the same.
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    allowed = OPTIONS[model]
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ValueError(f"model {model!r} takes no option {', '.join(unknown)} (it takes {sorted(allowed)})")
    if model in AR_MODELS:
        return ARPredictor(model=model, nominal_ns=nominal_ns, **options)
    if model == "rls":
        return RlsPredictor(nominal_ns=nominal_ns, **options)
    return KalmanPredictor(nominal_ns=nominal_ns, **options)


def make_predictors(model: str, nominals_ns: Sequence[int | None], **options: Any) -> list[Predictor]:
    """One predictor per direction (each with its own nominal), sharing what the model learns of the
    motor as a whole: "kalman" and "rls" learn how the drive and temperature act from both directions'
    strokes."""
    out = [make_predictor(model, nominal_ns=n, **options) for n in nominals_ns]
    first = out[0] if out else None
    for p in out[1:]:
        if isinstance(p, ConditionedPredictor) and type(first) is type(p):
            p.share_conditions_with(first)  # type: ignore[arg-type]
    return out
