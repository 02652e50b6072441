"""Simulated rig: virtual-time strokes per second, and the rig's calibration figures.

Rows: 100,000 strokes through SimDaq (arm, command, recv: the daemon's path; target <= 5 s, the
paper's 100,000-cycle reliability run), the bare model (the physics alone, no Daq path), and a
fixed-dt stepping integrator of Eq. 1 for contrast (measured on fewer strokes, scaled to 100,000),
with its timing error against the closed-form crossing; and SimDaq on the wall clock: how late it
hands over each event, beside how late this machine wakes any sleeper (tests/sim/test_sim_realtime.py
checks only that no event comes early and that waiting does not spin).
"""

from __future__ import annotations

import math
import time

import numpy as np

from benchmarks.table import print_table
from usmswitch.drivers import Direction, EventKind
from usmswitch.predictor import ARPredictor
from usmswitch.sim import SimDaq, UsmSwitchModel

N_STROKES = 100_000
TARGET_S = 5.0
STEP_STROKES = 200
STEP_DT_NS = 1_000
WALL_STROKES = 40
#: SimDaq on the wall clock: p90 of its events' lateness within this of the machine's own p90
#: (a plain sleep's wake-up, measured beside it: a busy machine makes everyone's late).
WALL_P90_OVER_MACHINE_NS = 1_000_000


def daq_strokes(n: int, seed: int = 0) -> tuple[float, list[int], SimDaq]:
    """Seconds for `n` strokes through SimDaq, their operating times (ns), and the driver."""
    daq = SimDaq(seed=seed)
    daq.open()
    ops = []
    direction = Direction.ON
    t0 = time.perf_counter()
    for _ in range(n):
        daq.arm(direction, 1_000_000)
        cmd = daq.command()
        while True:
            ev = daq.recv(40_000_000)
            if ev is None:
                raise RuntimeError(f"stroke {len(ops)} did not arrive")
            if ev.kind is EventKind.EDGE and ev.level == 1:
                break
        ops.append(ev.t_ns - cmd.t_start_ns)
        direction = direction.opposite
    return time.perf_counter() - t0, ops, daq


def wall_clock_lateness(n: int = WALL_STROKES, seed: int = 4) -> list[int]:
    """How late (ns) SimDaq on the wall clock hands over each event of `n` strokes, sorted."""
    daq = SimDaq(realtime=True, seed=seed)
    daq.open()
    late = []
    direction = Direction.ON
    try:
        for _ in range(n):
            daq.arm(direction, 500_000)
            daq.command()
            while True:
                ev = daq.recv(50_000_000)
                got = time.monotonic_ns()
                if ev is None:
                    raise RuntimeError(f"stroke {len(late)} did not arrive")
                late.append(got - ev.t_ns)
                if ev.kind is EventKind.EDGE and ev.level == 1:
                    break
            direction = direction.opposite
    finally:
        daq.close()
    return sorted(late)


def sleep_lateness(n: int = 40) -> list[int]:
    """How late (ns) a plain 2 ms sleep of this process wakes, sorted: the machine's own share."""
    out = []
    for _ in range(n):
        t0 = time.monotonic_ns()
        time.sleep(0.002)
        out.append(time.monotonic_ns() - t0 - 2_000_000)
    return sorted(out)


def _pct(xs: list[int], q: float) -> int:
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def model_strokes(n: int, seed: int = 0) -> float:
    """Seconds for `n` strokes of the bare model (crossing and depart instant, no Daq)."""
    m = UsmSwitchModel(seed=seed)
    release = m.params.release_mm
    t = 0
    t0 = time.perf_counter()
    for k in range(n):
        st = m.next_stroke(Direction(k & 1), t)
        st.time_at_ns(release)
        t += st.operating_ns + 1_000_000
    return time.perf_counter() - t0


def stepped_strokes(n: int, dt_ns: int, seed: int = 0) -> tuple[float, float]:
    """Seconds for `n` strokes found by stepping Eq. 1 at a fixed dt, and the worst timing error (ns)."""
    m = UsmSwitchModel(seed=seed)
    t = 0
    worst = 0.0
    elapsed = 0.0
    for k in range(n):
        st = m.next_stroke(Direction(k & 1), t)
        t += st.operating_ns + 1_000_000
        dyn = st._dyn
        unit = st._unit
        target = st.distance_mm / st._reach  # the crossing, in Eq. 1's units
        h = dt_ns / unit
        a, b, kw = dyn.a, dyn.b, dyn.a  # unit steady speed: input gain = w_n^2
        t0 = time.perf_counter()
        x = v = dv = 0.0
        steps = 0
        while x < target:  # semi-implicit Euler on v'' + b v' + a v = a
            dv += h * (kw - b * dv - a * v)
            v += h * dv
            x += h * v
            steps += 1
        elapsed += time.perf_counter() - t0
        worst = max(worst, abs(st.dead_ns + steps * dt_ns - st.operating_ns))
    return elapsed, worst


def one_step_std(y: list[int], predictor: ARPredictor) -> float:
    errs = []
    for k, t in enumerate(y):
        if k >= predictor.window:
            errs.append(t - predictor.predict())
        predictor.update(t)
    return float(np.std(errs))


def calibration_rows() -> list[list[object]]:
    """The issue's calibration figures on a 2,000-stroke run (floors at the run's end temperature)."""
    _, ops, daq = daq_strokes(2000)
    rows: list[list[object]] = []
    first = np.array(ops[:500], dtype=float)
    floor = {d: daq.model.innovation_floor_ns(d) for d in Direction}
    rows.append(
        ["open loop, 500 strokes: mean / std (ms)", f"{first.mean() / 1e6:.3f} / {first.std() / 1e6:.3f}"]
    )
    rows.append(["  std / innovation floor", f"{first.std() / max(floor.values()):.2f}"])
    for d in Direction:
        y = ops[int(d) :: 2]
        ar1 = one_step_std(y, ARPredictor(order=1, window=100, model="paper"))
        ar2 = one_step_std(y, ARPredictor(order=2, window=100, model="centered"))
        ar3 = one_step_std(y, ARPredictor(order=3, window=100, model="centered"))
        rows.append([f"{d.name}: innovation floor (us)", f"{floor[d] / 1e3:.1f}"])
        rows.append([f"{d.name}: paper AR(1) one-step error std (us)", f"{ar1 / 1e3:.1f}"])
        rows.append([f"{d.name}: open-loop std (2000) / AR(1) error", f"{np.std(ops) / ar1:.2f}"])
        rows.append(
            [f"{d.name}: centred AR(2), AR(3) error / floor", f"{ar2 / floor[d]:.3f}, {ar3 / floor[d]:.3f}"]
        )
    return rows


def main() -> int:
    """Time 100,000 virtual-time strokes against the bare model and a fixed-dt integrator."""
    daq_s, _, _ = daq_strokes(N_STROKES)
    model_s = model_strokes(N_STROKES)
    step_s, step_err = stepped_strokes(STEP_STROKES, STEP_DT_NS)
    step_full = step_s * N_STROKES / STEP_STROKES
    rows = [
        [
            "SimDaq arm/command/recv (virtual time)",
            N_STROKES,
            f"{daq_s:.2f}",
            f"{N_STROKES / daq_s:,.0f}",
            f"{daq_s / N_STROKES * 1e6:.1f}",
            "0 (closed form)",
        ],
        [
            "bare model: next_stroke + depart instant",
            N_STROKES,
            f"{model_s:.2f}",
            f"{N_STROKES / model_s:,.0f}",
            f"{model_s / N_STROKES * 1e6:.1f}",
            "0 (closed form)",
        ],
        [
            f"peer: Eq. 1 stepped at dt = {STEP_DT_NS / 1000:g} us",
            f"{STEP_STROKES} (x{N_STROKES // STEP_STROKES})",
            f"{step_full:.1f} (scaled)",
            f"{STEP_STROKES / step_s:,.0f}",
            f"{step_s / STEP_STROKES * 1e6:.0f}",
            f"{step_err:.0f} ns worst",
        ],
    ]
    print_table(
        ["path", "strokes", "seconds", "strokes/s", "us/stroke", "arrival error"],
        rows,
        title=f"Simulated rig, {N_STROKES:,} strokes (target <= {TARGET_S:g} s through SimDaq)",
    )
    print()
    print_table(
        ["calibration (seed 0, 40 kHz / 500 Vpp / 25 C, back-to-back strokes)", "value"], calibration_rows()
    )
    late, machine = wall_clock_lateness(), sleep_lateness()
    print()
    print_table(
        ["wall clock: how late an event is handed over", "p50 (us)", "p90 (us)", "max (us)"],
        [
            [
                f"SimDaq(realtime=True), {WALL_STROKES} strokes",
                *(f"{_pct(late, q) / 1e3:.1f}" for q in (0.5, 0.9, 1)),
            ],
            [
                "this machine: a plain 2 ms sleep, 40 times",
                *(f"{_pct(machine, q) / 1e3:.1f}" for q in (0.5, 0.9, 1)),
            ],
        ],
    )
    wall_ok = late[0] >= -1_000 and _pct(late, 0.9) < WALL_P90_OVER_MACHINE_NS + _pct(machine, 0.9)
    ok = daq_s <= TARGET_S and math.isfinite(daq_s)
    print(
        f"\nSimDaq: {daq_s:.2f} s for {N_STROKES:,} strokes: {'OK' if ok else 'TARGET MISSED'} "
        f"(<= {TARGET_S:g} s); "
        f"{step_full / daq_s:.0f}x faster than stepping Eq. 1 at {STEP_DT_NS / 1000:g} us"
    )
    print(
        f"SimDaq on the wall clock: p90 {_pct(late, 0.9) / 1e3:.1f} us late:"
        f" {'OK' if wall_ok else 'TARGET MISSED'} (never early, p90 within"
        f" {WALL_P90_OVER_MACHINE_NS / 1e3:.0f} us of the machine's own {_pct(machine, 0.9) / 1e3:.1f} us)"
    )
    return 0 if ok and wall_ok else 1
