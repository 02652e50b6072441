"""The simulated rig's memory across daemon restarts: friction and warmth saved beside the records.

A real rig does not forget its friction or cool instantly when the daemon restarts; a fresh model
would, and with the same seed it would replay the same strokes to a warm-started predictor. So the
sim's slow state (`UsmSwitchModel.state`) is written to `rig.json` in the state directory now and
then and at stop, and taken up at start with the motor cooled for the time the daemon was away.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import structlog

from usmswitch.drivers import Daq

from .statefile import write_private_json

log = structlog.get_logger("usmswitch.rig")

RIG_STATE_FILE = "rig.json"
#: How often a running daemon writes the rig's state (a kill -9 loses at most this much of it).
SAVE_EVERY_NS = 30_000_000_000


class RigMemory:
    """Saves and restores one simulated rig's state; a no-op for a driver without a model."""

    def __init__(self, state_dir: Path, daq: Daq) -> None:
        self.path = state_dir / RIG_STATE_FILE
        self.model = getattr(daq, "model", None)
        self.clock = daq.clock
        self._next_save_ns = time.monotonic_ns() + SAVE_EVERY_NS

    @property
    def active(self) -> bool:
        return self.model is not None and hasattr(self.model, "state")

    def restore(self) -> dict[str, Any] | None:
        """Take up the saved state, if any; a bad file is logged and the rig starts fresh."""
        if not self.active or not self.path.exists():
            return None
        try:
            saved = json.loads(self.path.read_text())
            idle_ns = max(0, time.time_ns() - int(saved["saved_wall_ns"]))
            self.model.restore(saved["rig"], self.clock.now_ns(), idle_ns)  # type: ignore[union-attr]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("rig state not restored: the rig starts fresh", path=str(self.path), error=str(exc))
            return None
        log.info(
            "rig state restored",
            path=str(self.path),
            idle_s=round(idle_ns / 1e9, 1),
            strokes=saved["rig"]["strokes"],
            motor_above_ambient_c=round(saved["rig"]["theta_c"], 2),
        )
        return saved["rig"]  # type: ignore[no-any-return]

    def save(self) -> None:
        """Write the state now (atomically: a reader never sees half a file)."""
        if not self.active:
            return
        state = {"saved_wall_ns": time.time_ns(), "rig": self.model.state(self.clock.now_ns())}  # type: ignore[union-attr]
        try:
            write_private_json(self.path, state)
        except OSError as exc:
            log.warning("rig state not saved", path=str(self.path), error=str(exc))

    def maybe_save(self, now_ns: int) -> None:
        """Save when the interval is up (the loop's housekeeping calls it)."""
        if self.active and now_ns >= self._next_save_ns:
            self._next_save_ns = now_ns + SAVE_EVERY_NS
            self.save()
