"""What the predictors learned of how the drive and the temperature act, kept across daemon restarts.

A conditions-aware predictor ("kalman") learns d ln t per kHz, per 100 V and per C from the drive
steps and the warming it sees (`known_sensitivities`). A warm start feeds it only the stored stroke
times, which carry no conditions, so without this file a restarted daemon would meet its next drive
step as news again. `sensitivities.json` in the state directory keeps them with what they belong to:
the driver, the rig and the model, and the `[control] sensitivity_*` values configured when they were
learned. They are taken at start only when all of those still match: a re-commissioned rig (other
configured values), another rig or driver, or another model starts from its configuration. Written
atomically, when they changed (checked at most every `CHECK_EVERY_NS` from the loop's slack hooks,
never mid-stroke) and at stop.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import structlog

from .statefile import write_private_json

log = structlog.get_logger("usmswitch.sensitivities")

SENSITIVITIES_FILE = "sensitivities.json"
FORMAT = 1
#: How often a running daemon looks whether what the predictors know changed (a kill -9 loses at most
#: what they learned since).
CHECK_EVERY_NS = 1_000_000_000

Sensitivities = tuple[float | None, float | None, float | None]


def _plain(values: Sequence[float | None] | None) -> list[float | None] | None:
    return None if values is None else [None if v is None else float(v) for v in values]


def _checked(values: Any) -> Sensitivities:
    if not isinstance(values, list) or len(values) != 3:
        raise ValueError(f"sensitivities must be a list of 3, got {values!r}")
    for v in values:
        ok = v is None or (not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v))
        if not ok:
            raise ValueError(f"sensitivities hold {v!r}, not a finite number or null")
    return (values[0], values[1], values[2])


class SensitivityMemory:
    """Loads and saves one daemon's learned sensitivities; a no-op for a model that learns none."""

    def __init__(
        self,
        state_dir: Path,
        *,
        driver: str,
        rig: str,
        model: str,
        configured: Sequence[float | None] | None,
    ) -> None:
        self.path = state_dir / SENSITIVITIES_FILE
        self.owner = {"driver": driver, "rig": rig, "model": model, "configured": _plain(configured)}
        self.predictor: Any = None
        self._saved: Sensitivities | None = None
        self._next_check_ns = 0

    def load(self) -> Sensitivities | None:
        """The sensitivities saved for this driver, rig, model and configuration, or None (no file,
        another owner, a bad file: logged, and the configuration's values hold)."""
        if not self.path.exists():
            return None
        try:
            saved = json.loads(self.path.read_text())
            if not isinstance(saved, dict) or saved.get("format") != FORMAT:
                raise ValueError(f"format {saved.get('format') if isinstance(saved, dict) else saved!r}")
            values = _checked(saved.get("sensitivities"))
        except (OSError, ValueError) as exc:
            log.warning("sensitivities not restored: bad file", path=str(self.path), error=str(exc))
            return None
        differs = {k: saved.get(k) for k, v in self.owner.items() if saved.get(k) != v}
        if differs:
            log.info(
                "sensitivities not restored: learned for another setup",
                path=str(self.path),
                saved={k: saved.get(k) for k in differs},
                now={k: self.owner[k] for k in differs},
            )
            return None
        self._saved = values
        log.info("sensitivities restored", path=str(self.path), sensitivities=list(values))
        return values

    def watch(self, predictor: Any) -> None:
        """Save what `predictor` (either direction's: they learn together) knows from now on."""
        self.predictor = predictor if hasattr(predictor, "known_sensitivities") else None

    def maybe_save(self, now_ns: int) -> None:
        """Save when what the predictor knows changed (the loop's slack hooks call it)."""
        if self.predictor is not None and now_ns >= self._next_check_ns:
            self._next_check_ns = now_ns + CHECK_EVERY_NS
            self.save()

    def save(self) -> None:
        """Write what the predictor knows now if it changed since the last save (atomically: a reader
        never sees half a file); nothing while it knows nothing."""
        if self.predictor is None:
            return
        known = tuple(self.predictor.known_sensitivities)
        if known == self._saved or all(v is None for v in known):
            return
        state = {
            "format": FORMAT,
            **self.owner,
            "sensitivities": _plain(known),
            "units": ["ln t per kHz", "ln t per 100 V", "ln t per C"],
            "saved_wall_ns": time.time_ns(),
        }
        try:
            write_private_json(self.path, state)
        except OSError as exc:
            log.warning("sensitivities not saved", path=str(self.path), error=str(exc))
            return
        self._saved = known  # type: ignore[assignment]
        log.info("sensitivities saved", path=str(self.path), sensitivities=list(known))
