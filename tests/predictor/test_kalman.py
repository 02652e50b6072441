"""The "kalman" model: condition steps, noise, mean reversion, cold start and its state."""

from __future__ import annotations

import math
import random

import msgpack
import pytest

from usmswitch.predictor import SOUND_FIT, ARPredictor, make_predictor, make_predictors
from usmswitch.predictor.kalman import GRID, KalmanPredictor


def series(
    n: int, seed: int, phi: float = 0.975, friction: float = 0.04, white: float = 0.0055
) -> list[float]:
    """Relative stroke scales 1 + F + w: F AR(1) (phi, stationary std `friction`), w white."""
    rng = random.Random(seed)
    q = friction * math.sqrt(1 - phi * phi)
    f = rng.gauss(0, friction)
    out = []
    for _ in range(n):
        f = phi * f + rng.gauss(0, q)
        out.append(1 + f + rng.gauss(0, white))
    return out


def rms_error(p, strokes: list[int], conds: list[dict] | None = None, skip: int = 200) -> float:
    acc = []
    for i, t in enumerate(strokes):
        c = None if conds is None else conds[i]
        if i >= skip:
            acc.append((t - p.predict(c)) ** 2)
        p.update(t, c)
    return math.sqrt(sum(acc) / len(acc))


def test_a_learned_drive_step_is_predicted_the_next_time() -> None:
    # ln t moves by 10 % per kHz; the drive steps 40 <-> 40.5 kHz every 300 strokes.
    scale = series(3000, seed=2)
    conds = [{"frequency_hz": 40_000.0 + 500.0 * ((i // 300) % 2)} for i in range(3000)]
    t = [
        round(8e6 * s * math.exp(0.1 * (c["frequency_hz"] - 40_000.0) / 1000))
        for s, c in zip(scale, conds, strict=True)
    ]
    p = KalmanPredictor(nominal_ns=8_000_000)
    errors = []
    for v, c in zip(t, conds, strict=True):
        errors.append(abs(v - p.predict(c)))
        p.update(v, c)
    assert errors[300] > 300_000  # the first step is news: nothing said how the frequency acts
    assert p.sensitivities[0] == pytest.approx(0.1, abs=0.02)
    later = [errors[i] for i in range(900, 3000, 300)]
    assert max(later) < 250_000  # the later steps are known: about a stroke's scatter (~90 us)
    # Without conditions the steps stay news for ever.
    blind = KalmanPredictor(nominal_ns=8_000_000)
    blind_err = []
    for v in t:
        blind_err.append(abs(v - blind.predict()))
        blind.update(v)
    blind_later = [blind_err[i] for i in range(900, 3000, 300)]
    assert sum(blind_later) / len(blind_later) > 2 * sum(later) / len(later)


@pytest.mark.parametrize(
    ("phi", "white", "gain_at_most", "phi_at_most"),
    [(0.975, 0.044, 0.5, 1.0), (0.8, 0.0055, 1.0, 0.95)],  # noise x8; mean-reverting friction
)
def test_the_filter_chosen_follows_the_process_and_beats_the_papers_ar1(
    phi, white, gain_at_most, phi_at_most
):
    t = [round(8e6 * s) for s in series(4000, seed=5, phi=phi, white=white)]
    k = KalmanPredictor(nominal_ns=8_000_000)
    ours = rms_error(k, t)
    paper = rms_error(ARPredictor(order=1, window=100, nominal_ns=8_000_000), t)
    assert ours < 0.97 * paper
    chosen_phi, chosen_gain = k.coefficients
    assert chosen_gain <= gain_at_most and chosen_phi <= phi_at_most


def test_cold_start_is_the_papers_ar1_until_a_sound_fit() -> None:
    t = [round(8e6 * s) for s in series(SOUND_FIT + 5, seed=1)]
    k = KalmanPredictor(nominal_ns=8_100_000)
    ref = ARPredictor(order=1, window=SOUND_FIT, nominal_ns=8_100_000)
    for v in t[:SOUND_FIT]:
        assert not k.ready and k.coefficients == ref.coefficients
        assert k.predict() == ref.predict()
        k.update(v)
        ref.update(v)
    assert k.ready and k.coefficients in GRID


def test_state_round_trips_through_msgpack_cold_and_warm_and_a_bad_one_is_named() -> None:
    t = [round(8e6 * s) for s in series(300, seed=3)]
    conds = [{"temperature_c": 25.0 + i / 100, "frequency_hz": 40_000.0} for i in range(300)]
    for n in (10, 300):
        k = KalmanPredictor(nominal_ns=8_000_000)
        for v, c in zip(t[:n], conds[:n], strict=True):
            k.update(v, c)
        q = KalmanPredictor.from_state(msgpack.unpackb(msgpack.packb(k.state())))
        for v, c in zip(t[:50], conds[:50], strict=True):
            assert q.predict(c) == k.predict(c)
            q.update(v, c)
            k.update(v, c)
    state = k.state()
    with pytest.raises(ValueError, match="level"):
        KalmanPredictor.from_state({**state, "level": [0.0]})
    with pytest.raises(ValueError, match="format"):
        KalmanPredictor.from_state({**state, "format": "x"})
    with pytest.raises(ValueError, match="got 0"):
        KalmanPredictor(nominal_ns=8_000_000).update(0)


def test_the_fitted_filter_reports_its_phi_and_round_trips_through_the_state() -> None:
    # A stationary friction at phi 0.6 seen without stroke noise: the filter predicting is the fitted
    # one (K = 1, phi its least-squares estimate), and a predictor rebuilt from the state predicts as
    # the original, its fitted phi included.
    t = [round(8e6 * s) for s in series(1500, seed=6, phi=0.6, friction=0.015, white=0.0)]
    k = KalmanPredictor(nominal_ns=8_000_000)
    for v in t[:1000]:
        k.update(v)
    phi, gain = k.coefficients
    assert gain == 1.0 and 0.45 < phi < 0.75 and (phi, gain) not in GRID
    q = KalmanPredictor.from_state(msgpack.unpackb(msgpack.packb(k.state())))
    for v in t[1000:]:
        assert q.predict() == k.predict() and q.coefficients == k.coefficients
        q.update(v)
        k.update(v)
    with pytest.raises(ValueError, match="fit"):
        KalmanPredictor.from_state({**k.state(), "fit": [0.1, -1.0]})
    with pytest.raises(ValueError, match="fit"):
        KalmanPredictor.from_state({**k.state(), "fit": [0.1]})


def test_the_two_directions_learn_the_drive_together() -> None:
    # The drive steps 40 -> 40.5 kHz once; "on" meets it first. Told by make_predictors, "off" then
    # predicts its own first stroke after the step; on its own it cannot (the step is ~5 %, ~420 us).
    rate = 0.1  # ln t per kHz

    def first_off_error_after_step(shared: bool, seed: int) -> float:
        scale_on, scale_off = series(600, seed=seed), series(600, seed=seed + 100)
        on, off = make_predictors("kalman", [8_000_000, 8_300_000])
        if not shared:
            off = make_predictor("kalman", nominal_ns=8_300_000)
        err = 0.0
        for i in range(600):
            f = 40_000.0 if i < 400 else 40_500.0
            c = {"frequency_hz": f}
            step = math.exp(rate * (f - 40_000.0) / 1000)
            on.update(round(8e6 * scale_on[i] * step), c)
            t_off = round(8.3e6 * scale_off[i] * step)
            if i == 400:
                err = abs(t_off - off.predict(c))
            off.update(t_off, c)
        return err

    shared = [first_off_error_after_step(True, seed) for seed in range(6)]
    alone = [first_off_error_after_step(False, seed) for seed in range(6)]
    assert sum(shared) / 6 < 150_000  # about a stroke's scatter (~90 us)
    assert sum(alone) / 6 > 300_000  # about the whole step


def test_the_written_out_grid_step_is_the_grid() -> None:
    # _grid_step spells GRID's numbers out for speed: it must be the loop over GRID and the fitted
    # filter (phi given, K = 1), bit for bit.
    from usmswitch.predictor.kalman import FORGET, _grid_step, _members

    rng = random.Random(4)
    for _ in range(200):
        phi_fit = rng.uniform(0.0, 1.0)
        members = _members(phi_fit)
        levels = [16.0 + rng.gauss(0, 0.05) for _ in members]
        scores = [abs(rng.gauss(0, 1e-3)) for _ in members]
        z, mu, moved = 16.0 + rng.gauss(0, 0.05), 16.0 + rng.gauss(0, 0.05), rng.gauss(0, 0.02)
        want_levels, want_scores = [], []
        for (phi, k), v, sc in zip(members, levels, scores, strict=True):
            pr = phi * v + (1.0 - phi) * mu + moved
            e = z - pr
            want_levels.append(pr + k * e)
            want_scores.append(FORGET * sc + e * e)
        got_levels, got_scores = _grid_step(levels, scores, z, mu, moved, phi_fit)
        assert got_levels == pytest.approx(want_levels, rel=1e-15, abs=0)
        assert got_scores == pytest.approx(want_scores, rel=1e-12, abs=1e-18)


def _first_step_error(sensitivities: tuple[float, float, float] | None, seed: int) -> float:
    """|error| of the first stroke after a 40 -> 40.5 kHz, 500 -> 450 V step (ln t: +0.1 per kHz,
    -0.2 per 100 V), for a predictor told `sensitivities` beforehand."""
    scale = series(700, seed=seed)
    p = make_predictor("kalman", nominal_ns=8_000_000, sensitivities=sensitivities)
    for i in range(700):
        f, v = (40_000.0, 500.0) if i < 600 else (40_500.0, 450.0)
        c = {"frequency_hz": f, "voltage_v": v, "temperature_c": 25.0}
        t = round(8e6 * scale[i] * math.exp(0.1 * (f - 40_000.0) / 1e3 - 0.2 * (v - 500.0) / 1e2))
        if i == 600:
            return abs(t - p.predict(c))
        p.update(t, c)
    raise AssertionError("no step")


def test_known_sensitivities_predict_the_first_step_ever() -> None:
    # The step moves ln t by 0.15 (~1.3 ms): news to a predictor told nothing; within a stroke's
    # scatter to one told the sensitivities (here 10 % off, as a commissioning would have them).
    blind = [_first_step_error(None, seed) for seed in range(5)]
    known = [_first_step_error((0.11, -0.18, 0.0), seed) for seed in range(5)]
    assert min(blind) > 1_000_000
    assert sum(known) / 5 < 200_000


def test_sensitivities_are_checked_and_kept_through_the_state() -> None:
    k = KalmanPredictor(nominal_ns=8_000_000, sensitivities=(0.1, -0.2, 0.01))
    assert k.sensitivities == (0.1, -0.2, 0.01)
    q = KalmanPredictor.from_state(msgpack.unpackb(msgpack.packb(k.state())))
    assert q.sensitivities == (0.1, -0.2, 0.01)
    for bad in ((0.1, 0.2), (0.1, float("nan"), 0.0), "abc", (True, 0.0, 0.0)):
        with pytest.raises(ValueError, match="sensitivities"):
            make_predictor("kalman", nominal_ns=8_000_000, sensitivities=bad)


def _off_errors(
    told: tuple[float, float, None], true_rate: float, seed: int
) -> tuple[list[float], list[float]]:
    """The drive steps 40 -> 40.5 kHz and back every 200 strokes of each direction, ln t moving
    `true_rate` per kHz; the predictors were told `told`. |error| of "off"'s first stroke after each
    step ("on" meets each step first), and of its stroke 100 strokes later (nothing stepped)."""
    scale_on, scale_off = series(1400, seed=seed), series(1400, seed=seed + 100)
    on, off = make_predictors("kalman", [8_000_000, 8_000_000], sensitivities=told)
    at_step, quiet = [], []
    for i in range(1400):
        f = 40_000.0 + 500.0 * ((i // 200) % 2)
        c = {"frequency_hz": f, "voltage_v": 500.0}
        step = math.exp(true_rate * (f - 40_000.0) / 1000)
        on.update(round(8e6 * scale_on[i] * step), c)
        t_off = round(8e6 * scale_off[i] * step)
        if i % 200 == 0 and i:
            at_step.append(abs(t_off - off.predict(c)))
        if i % 200 == 100 and i > 200:
            quiet.append(abs(t_off - off.predict(c)))
        off.update(t_off, c)
    return at_step, quiet


def _rms(v: list[float]) -> float:
    return math.sqrt(sum(e * e for e in v) / len(v))


def test_a_known_sensitivity_is_not_moved_by_the_first_strokes_scatter() -> None:
    # Told the right sensitivity, "on"'s first stroke after a step is mostly scatter: s must move by
    # little, or "off"'s first stroke inherits "on"'s scatter (rms 1.3x that of a stroke where nothing
    # stepped, with the wide prior and the log-difference learning this replaced).
    runs = [_off_errors((0.15, -0.23, None), 0.15, seed) for seed in range(20)]
    at_step = _rms([e for a, _ in runs for e in a])
    quiet = _rms([e for _, q in runs for e in q])
    assert at_step < 1.08 * quiet, (at_step, quiet)


def test_a_step_that_contradicts_the_known_sensitivity_is_learned_at_once() -> None:
    # Told +0.15 per kHz (the chord of detuning up), the drive acts at -0.1 per kHz: "on"'s first
    # stroke after the first step errs by the whole difference (~1 ms), beyond s's uncertainty, so
    # its variance is reset and "off"'s first stroke after it, and the later steps, are predicted.
    for seed in range(3):
        at_step, _ = _off_errors((0.15, -0.23, None), -0.1, seed)
        assert max(at_step) < 300_000, at_step
