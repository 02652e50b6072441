"""Input checks shared by the predictor's entry points: every bad value is named in a ValueError."""

from __future__ import annotations

import numbers
from typing import Any

#: Largest stroke time accepted: every sample then is an exact float64, like the data lstsq sees.
MAX_T_NS = 2**53
#: The models `ARPredictor` fits (Eq. 2 with or without an intercept).
AR_MODELS = ("paper", "centered")
#: Every model `make_predictor` builds: the AR fits and the models beyond the paper.
MODELS = (*AR_MODELS, "kalman", "rls")
MAX_ORDER = 8


def check_stroke_ns(value: Any) -> int:
    """Validate one stroke time: a positive integer of ns, at most 2**53 (ValueError naming the value)."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        v = int(value)
        if 0 < v <= MAX_T_NS:
            return v
    raise ValueError(f"stroke time must be a positive integer of nanoseconds <= 2**53, got {value!r}")


def check_strokes(samples: Any) -> list[int]:
    """Validate a sequence of stroke times, all of them before any is used (warm start)."""
    return [check_stroke_ns(v) for v in samples]


def check_int(name: str, value: Any, lo: int, hi: int | None = None) -> int:
    """Validate an integer setting in lo..hi (bool is not an integer here)."""
    if not isinstance(value, int) or isinstance(value, bool) or value < lo or (hi is not None and value > hi):
        bound = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        raise ValueError(f"{name} must be an integer {bound}, got {value!r}")
    return value


def check_model(value: Any) -> str:
    """Validate the name of a model `ARPredictor` fits."""
    if value not in AR_MODELS:
        raise ValueError(f"model must be one of {AR_MODELS}, got {value!r}")
    return value
