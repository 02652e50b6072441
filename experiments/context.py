"""What every experiment gets: where to write, the rig (or a records file's run), and how many strokes."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from usmswitch.client.plots import runs_text

from .data import Strokes
from .figures import save
from .rig import Progress, Rig, RunSpec, SimulatedRig

MS = 1_000_000

#: Makes a progress callback for a task of `total` strokes named `label` (a context manager).
ProgressFactory = Callable[[str, int], "contextmanager[Progress]"]


@contextmanager
def no_progress(label: str, total: int) -> Iterator[Progress]:
    yield lambda n: None


class NeedsSimulatedRig(RuntimeError):
    """The experiment needs what only the simulated rig has (a position sensor, the ambient)."""


class NeedsStrokes(RuntimeError):
    """The experiment has nothing to analyse: no rig and no records."""


@dataclass
class Context:
    """An experiment's inputs: `rig` makes strokes, or `recorded` holds a records file's run."""

    out: Path
    rig: Rig | None = None
    recorded: Strokes | None = None
    seed: int | None = None
    #: Stroke counts are the paper's times this (tests and quick looks use less than 1).
    scale: float = 1.0
    progress: ProgressFactory = no_progress
    notes: list[str] = field(default_factory=list)
    #: For the figures' titles: the rig's name and the date of its strokes ("2025-06-01 14:27:03").
    rig_name: str = ""
    date: str = ""
    #: The runs the current experiment made (the CLI empties it before each experiment).
    run_ids: list[int] = field(default_factory=list)

    @property
    def figures(self) -> Path:
        return self.out / "figures"

    def count(self, paper_count: int, least: int = 40) -> int:
        """How many strokes to make for what the paper made `paper_count` of."""
        return max(least, round(paper_count * self.scale))

    def sim(self, what: str) -> SimulatedRig:
        """The simulated rig, or NeedsSimulatedRig saying why `what` needs it."""
        if isinstance(self.rig, SimulatedRig):
            return self.rig
        raise NeedsSimulatedRig(f"{what} needs the simulated rig ({self._where()})")

    def strokes(self, name: str, count: int, period_ns: int, target_ns: int, **kw: object) -> Strokes:
        """A run on the rig, with a progress bar; or the recorded run when analysing records."""
        if self.recorded is not None:
            return self.recorded
        if self.rig is None:
            raise NeedsStrokes(f"{name}: no rig and no records to analyse")
        with self.progress(name, count) as advance:
            made = self.rig.run(RunSpec(name, count, period_ns, target_ns, **kw), advance)  # type: ignore[arg-type]
        if made.run_id is not None:
            self.run_ids.append(made.run_id)
        return made

    def save(self, fig: Any, name: str, runs: list[int | None] | None = None) -> list[str]:
        """The figure saved (figures.save) under a title naming its runs (default: the
        experiment's so far), the rig and the date."""
        if runs is None:
            runs = [self.recorded.run_id] if self.recorded is not None else list(self.run_ids)
        return save(fig, self.figures, name, stamp=f"{runs_text(runs)}, rig {self.rig_name}, {self.date}")

    def _where(self) -> str:
        if self.recorded is not None:
            return "this analyses a records file"
        return "a live rig has no position sensor or ambient control"
