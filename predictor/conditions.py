"""A stroke's known conditions, as the predictors take them: a mapping of any of `CONDITION_KEYS`."""

from __future__ import annotations

from collections.abc import Mapping

#: Drive frequency (Hz), drive voltage (V peak to peak), motor temperature (C), time since the
#: direction's previous stroke (ns). Any may be missing; without any a predictor behaves as the paper's.
CONDITION_KEYS = ("frequency_hz", "voltage_v", "temperature_c", "idle_ns")

Conditions = Mapping[str, float | int]
