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

from usmswitch.client import Client, RpcError, Run
from usmswitch.daemon.loop import AUTOSTART_OWNER, ControlLoop, Mode
from usmswitch.daemon.records import RecordStore
from usmswitch.predictor import ARPredictor
from usmswitch.protocol.record import CycleRecord
from usmswitch.protocol.units import format_ns
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
    #: The rig as its records name it (`[daemon] rig`; the simulated rig's "sim-seed-N").
    name: str

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
        self.name = f"sim-seed-{seed}"
        self.store = RecordStore(records_path, driver="sim", rig=self.name)
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
        # Not the daemon's bounded wait: the writer's close work (the runs' statistics) can take
        # seconds on a busy machine, and a store given up on leaves -wal and -shm when we exit.
        self.store.close(timeout_ns=None)


class LiveRig:
    """A running daemon (a real rig) through its socket: runs as `Client.run` makes them.

    The rig is lent, not given: every setting an experiment changes (targets, mode and open delay,
    drive frequency and voltage, the cycling that was going) is noted at the start and put back by
    `close()` (the CLI calls it however the experiment ends: done, failed, Ctrl-C). A run that a
    client started is never ended unasked: `take_over` (`--take-over`) says to; the daemon's own
    start-up run gives way by the daemon's rule, and is started again at the end.
    """

    simulated = False
    seed = None

    def __init__(self, address: str | None, take_over: bool = False) -> None:
        self.client = Client(address, timeout=30)
        self.take_over = take_over
        #: What `close()` put back, as lines for the report ("mode: open -> closed").
        self.restored: list[str] = []
        try:
            status = self.client.status()
            self.name = str(status.get("rig") or address or "the local daemon")
            if status["state"] == "fault":
                raise RuntimeError(f"the rig is in FAULT ({status['fault']}): `usmswitchctl reset` first")
            self.before = self._lend(status)
        except BaseException:
            self.client.close()
            raise

    def _lend(self, status: dict[str, Any]) -> dict[str, Any]:
        """The rig as it is lent (what `restore` puts back); refused while a client's run goes,
        unless taken over."""
        before = self._settings(status)
        going = before["run"]
        if going is not None and going["settings"].get("owner") != AUTOSTART_OWNER and not self.take_over:
            raise RuntimeError(
                f"run {going['run_id']} ({going['settings'].get('owner') or 'a client'}) is going on the"
                " rig: stop it first (`usmswitchctl stop`), or pass --take-over to end it now and start"
                " it again when the experiment ends (or --queue to wait for it in the daemon's queue)"
            )
        return before

    def _settings(self, status: dict[str, Any]) -> dict[str, Any]:
        """What an experiment may change, as it is now."""
        try:
            drive: dict[str, Any] | None = self.client.set_drive()  # no keys: reads the drive
        except RpcError:
            drive = None  # neither a drive board nor the sim's drive
        going = None
        if status["state"] == "cycling":
            runs = self.client.runs(1)
            going = runs[-1] if runs and runs[-1]["end_reason"] is None else None
        return {
            "mode": status["mode"],
            "open_delay_ns": status["open_delay_ns"],
            "target_on_ns": status["target_on_ns"],
            "target_off_ns": status["target_off_ns"],
            "drive": drive,
            "run": going,
        }

    def run(self, spec: RunSpec, progress: Progress | None = None) -> Strokes:
        self._apply(spec)
        run = self.client.run(
            count=spec.count,
            period=spec.period_ns,
            target=spec.target_ns,
            allow_late=True,
            take_over=self.take_over,
            timeout=10,
        )
        return self._follow(run, progress)

    def _apply(self, spec: RunSpec) -> None:
        """The run's drive and mode set on the rig (its target goes with the run)."""
        c = self.client
        if spec.frequency_hz is not None or spec.voltage_vpp is not None:
            # A drive board or the sim: else UNAVAILABLE.
            c.set_drive(frequency_hz=spec.frequency_hz, voltage_vpp=spec.voltage_vpp)
        c.set_mode(spec.mode, spec.open_delay_ns if spec.mode == "open" else None)

    def _follow(self, run: Run, progress: Progress | None) -> Strokes:
        """A run's strokes as they come, to its end."""
        records: list[dict[str, Any]] = []
        for rec in run:
            records.append(dict(rec))
            if progress is not None:
                progress(1)
        return dataclasses.replace(Strokes.from_records(records, run_id=run.run_id), run=run.info)

    def restore(self) -> list[str]:
        """Put back what was changed; the lines say what, for the report. Safe to call twice."""
        c = self.client
        now = c.status()
        done: list[str] = []
        if now["state"] == "cycling":  # an experiment's run cut short (Ctrl-C, a failure)
            c.stop_cycling()
            done.append("cycling: the experiment's run stopped")
        done += self._put_back(now)
        done += self._start_again()
        self.restored += done
        return done

    def _put_back(self, now: dict[str, Any]) -> list[str]:
        """The mode, targets and drive as they were lent (`now`: the status as it is)."""
        c, b = self.client, self.before
        done: list[str] = []
        if (now["mode"], now["open_delay_ns"]) != (b["mode"], b["open_delay_ns"]):
            c.set_mode(b["mode"], b["open_delay_ns"])
            done.append(
                f"mode: {now['mode']} (open delay {format_ns(now['open_delay_ns'])}) -> {b['mode']}"
                f" (open delay {format_ns(b['open_delay_ns'])})"
            )
        for d in ("on", "off"):
            key = f"target_{d}_ns"
            if now[key] != b[key]:
                c.set_target(b[key], d, allow_late=True)
                done.append(f"target {d}: {format_ns(now[key])} -> {format_ns(b[key])}")
        if b["drive"] is not None:
            drive = c.set_drive()
            for key, unit in (("frequency_hz", "Hz"), ("voltage_vpp", "Vpp")):
                if b["drive"].get(key) is not None and drive.get(key) != b["drive"][key]:
                    c.set_drive(**{key: b["drive"][key]})
                    done.append(f"drive {key}: {drive.get(key):g} {unit} -> {b['drive'][key]:g} {unit}")
        return done

    def _start_again(self) -> list[str]:
        """The run that was going when the rig was lent, started again (once)."""
        c, going = self.client, self.before["run"]
        done: list[str] = []
        if going is not None:
            s = going["settings"]
            count = s["count"] and max(1, s["count"] - self._made(going))
            run = c.start_cycling(s["period_ns"], count, owner=s.get("owner") or None)
            done.append(
                f"cycling: run {going['run_id']} ({s.get('owner') or 'a client'}) started again as run"
                f" {run['run_id']}, every {format_ns(s['period_ns'])}"
            )
        return done

    def _made(self, run: dict[str, Any]) -> int:
        """Strokes the run had made when it was taken over."""
        for r in self.client.runs(50):
            if r["run_id"] == run["run_id"] and r["last_cycle"] is not None:
                return int(r["last_cycle"]) - int(r["first_cycle"]) + 1
        return 0

    def close(self) -> None:
        try:
            self.restore()
        finally:
            self.client.close()
