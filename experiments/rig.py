"""Where an experiment's strokes are made: the simulated rig in-process, or a live daemon.

`SimulatedRig` runs the daemon's own parts, in virtual time, in this process: `SimDaq` over the
rig model, one `ARPredictor` per direction, `ControlLoop`, and a `RecordStore` writing the run's
`records.sqlite`, so an experiment's strokes are made and recorded exactly as the daemon makes and
records them, 100,000 in seconds. `LiveRig` asks a running daemon (a real rig) through the client.
Both return each run's strokes as `Strokes`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from usmswitch.client import Client
from usmswitch.daemon.loop import ControlLoop, Mode
from usmswitch.daemon.record import CycleRecord
from usmswitch.daemon.records import RecordStore
from usmswitch.predictor import ARPredictor
from usmswitch.sim import SimDaq
from usmswitch.sim.model import UsmSwitchModel
from usmswitch.sim.params import RigParams

from .data import Strokes

Progress = Callable[[int], None]  # called with the strokes made since the last call


@dataclass(frozen=True)
class RunSpec:
    """One run an experiment asks for: its name, strokes, period, target and drive."""

    name: str
    count: int
    period_ns: int
    target_ns: int
    mode: str = "closed"
    open_delay_ns: int = 0
    frequency_hz: float | None = None
    voltage_vpp: float | None = None


class Rig(Protocol):
    """What an experiment needs of a rig."""

    simulated: bool
    seed: int | None

    def run(self, spec: RunSpec, progress: Progress | None = None) -> Strokes: ...

    def close(self) -> None: ...


class SimulatedRig:
    """The simulated rig and the daemon's loop, in virtual time, recording to `records_path`."""

    simulated = True

    def __init__(
        self,
        records_path: Path,
        seed: int,
        *,
        params: RigParams | None = None,
        model: str = "paper",
        order: int | str = 1,
        window: int = 100,
    ) -> None:
        self.seed = seed
        self.params = params or RigParams()
        self.model = UsmSwitchModel(self.params, seed=seed)
        self.daq = SimDaq(self.model)
        self.daq.open()
        self.store = RecordStore(records_path, driver="sim", rig=f"sim-seed-{seed}")
        nominal = self.params.nominal_operating_ns
        self.predictors = [
            ARPredictor(order=order, window=window, model=model, nominal_ns=nominal) for _ in range(2)
        ]
        self.loop = ControlLoop(
            self.daq,
            self.predictors,
            target_ns=12_000_000,
            sink=self.store.submit,
            first_cycle=self.store.last_cycle() + 1,
            first_run_id=self.store.last_run_id() + 1,
            run_sink=self.store.submit_run,
        )
        self._collected: list[CycleRecord] = []
        self._progress: Progress | None = None
        self.loop.listeners.append(self._collect)

    def _collect(self, rec: CycleRecord) -> None:
        self._collected.append(rec)
        if self._progress is not None:
            self._progress(1)

    def run(self, spec: RunSpec, progress: Progress | None = None) -> Strokes:
        """One run; the model and the predictors carry on from the last run."""
        self.model.set_drive(
            frequency_hz=spec.frequency_hz or self.params.reference_frequency_hz,
            voltage_vpp=spec.voltage_vpp or self.params.reference_voltage_vpp,
        )
        self.loop.set_mode(Mode(spec.mode), spec.open_delay_ns)
        self.loop.set_targets([spec.target_ns, spec.target_ns])  # a short target is the experiment's choice
        self._collected = []
        self._progress = progress
        settings = {
            "experiment": spec.name,
            "seed": self.seed,
            "frequency_hz": self.model.frequency_hz,
            "voltage_vpp": self.model.voltage_vpp,
        }
        try:
            run = self.loop.run_cycles(spec.period_ns, spec.count, kind="experiment", settings=settings)
        finally:
            self._progress = None
        records, self._collected = self._collected, []
        return Strokes.from_records((r.to_dict() for r in records), run_id=run.run_id)

    def with_ambient(self, ambient_c: float) -> None:
        """The lab's temperature (Fig. 9): the motor cools toward it from now on."""
        self.model.params = dataclasses.replace(self.model.params, ambient_c=ambient_c)

    def close(self) -> None:
        self.daq.close()
        self.store.close()


class LiveRig:
    """A running daemon (a real rig) through its socket: runs as `Client.run` makes them."""

    simulated = False
    seed = None

    def __init__(self, address: str | None) -> None:
        self.client = Client(address, timeout=30)
        status = self.client.status()
        if status["state"] == "fault":
            self.client.close()
            raise RuntimeError(f"the rig is in FAULT ({status['fault']}): `usmswitchctl reset` first")

    def run(self, spec: RunSpec, progress: Progress | None = None) -> Strokes:
        c = self.client
        if c.status()["state"] == "cycling":
            c.stop_cycling()
        if spec.frequency_hz is not None or spec.voltage_vpp is not None:
            # A drive board or the sim: else UNAVAILABLE.
            c.set_drive(frequency_hz=spec.frequency_hz, voltage_vpp=spec.voltage_vpp)
        c.set_mode(spec.mode, spec.open_delay_ns if spec.mode == "open" else None)
        run = c.run(
            count=spec.count, period=spec.period_ns, target=spec.target_ns, allow_late=True, timeout=10
        )
        records: list[dict[str, Any]] = []
        for rec in run:
            records.append(dict(rec))
            if progress is not None:
                progress(1)
        return Strokes.from_records(records, run_id=run.run_id)

    def close(self) -> None:
        self.client.close()
