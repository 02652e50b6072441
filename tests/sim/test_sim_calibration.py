"""Issue 3's calibration: the simulated rig behaves like the paper's (Fig. 6, Sec. 6)."""

from __future__ import annotations

import numpy as np

from usmswitch.drivers import Direction
from usmswitch.predictor import ARPredictor
from usmswitch.sim import SimDaq


def one_step_errors(series: np.ndarray, predictor: ARPredictor) -> np.ndarray:
    """t - t_hat for every stroke after the predictor's window has filled (the closed-loop error)."""
    errs = []
    for k, t in enumerate(series):
        if k >= predictor.window:
            errs.append(t - predictor.predict())
        predictor.update(int(t))
    return np.array(errs)


def test_open_loop_500_strokes_like_fig6(strokes, per_direction):
    daq = SimDaq(seed=0)
    daq.open()
    t_cold = daq.conditions().temperature_c
    run = strokes(daq, 500)
    ops = np.array(run[1], dtype=float)
    by_dir = per_direction(run)
    floor = max(daq.model.innovation_floor_ns(d) for d in Direction)
    # Mean stroke 8-8.8 ms at 40 kHz / 500 Vpp / 25 C ambient: below the paper's fixed 10.5 ms
    # (its reliability run left time to delay every start, Sec. 6), with room for the drift.
    assert 8e6 <= ops.mean() <= 8.8e6, ops.mean()
    # Highly dispersed: the whole series' std is at least 3x what no predictor can remove.
    assert ops.std() >= 3 * floor, (ops.std(), floor)
    # Visible drift: the motor warms, and each direction wanders slowly rather than scattering:
    # 25-stroke block means spread almost as much as single strokes (white noise: 1/5 as much).
    assert daq.conditions().temperature_c - t_cold > 1.5
    for d, y in by_dir.items():
        blocks = y[: len(y) // 25 * 25].reshape(-1, 25).mean(axis=1)
        assert blocks.std() > 0.5 * y.std(), (d, blocks.std(), y.std())
        r1 = np.corrcoef(y[:-1], y[1:])[0, 1]
        assert r1 > 0.6, (d, r1)


def test_paper_ar1_error_in_the_papers_range(strokes, per_direction):
    daq = SimDaq(seed=1)
    daq.open()
    run = strokes(daq, 2000)
    ops = np.array(run[1], dtype=float)
    for d, y in per_direction(run).items():
        err = one_step_errors(y, ARPredictor(order=1, window=100, model="paper"))
        # Paper: 95.3 and 102.7 us; the issue asks for 50-200 us and >= 3x below open loop.
        assert 50e3 <= err.std() <= 200e3, (d, err.std())
        assert err.std() * 3 <= ops.std(), (d, err.std(), ops.std())
        assert err.std() * 3 <= y.std(), (d, err.std(), y.std())


def test_best_linear_ar_reaches_the_floor(strokes, per_direction):
    """A centred AR(2)/AR(3) per direction (window 100) gets within 1.3x of the innovation floor,
    and never meaningfully below it: the floor is the limit and it is within a linear AR's reach."""
    daq = SimDaq(seed=2)
    daq.open()
    by_dir = per_direction(strokes(daq, 2000))
    for d, y in by_dir.items():
        floor = daq.model.innovation_floor_ns(d)
        for order in (2, 3):
            err = one_step_errors(y, ARPredictor(order=order, window=100, model="centered"))
            assert 0.9 * floor <= err.std() <= 1.3 * floor, (d, order, err.std(), floor)
