"""The rig's physics: Eq. 1 / Table 1, the crossing solve, voltage, temperature, thermal state,
friction, the innovation floor, profiles, and parameter validation."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from usmswitch.drivers import Direction
from usmswitch.sim import RigParams, UsmSwitchModel
from usmswitch.sim.params import TABLE1_FREQUENCY_HZ

ON, OFF = Direction.ON, Direction.OFF


def quiet(**changes: object) -> RigParams:
    """The rig with friction and noise (almost) removed, to see the deterministic physics."""
    return dataclasses.replace(RigParams(), friction_std=1e-12, white_std=0.0, **changes)


def test_closed_form_displacement_integrates_the_speed():
    m = UsmSwitchModel()
    for f in TABLE1_FREQUENCY_HZ:
        dyn = m._dynamics(f)
        assert dyn.x(0.0) == 0.0 and dyn.v(0.0) == 0.0
        taus = np.linspace(0.0, 1.5, 3001)
        v = np.array([dyn.v(t) for t in taus])
        x = np.array([dyn.x(t) for t in taus])
        # Trapezoidal integral of the step response equals the closed-form displacement.
        integral = np.concatenate([[0.0], np.cumsum((v[1:] + v[:-1]) / 2 * np.diff(taus))])
        assert np.max(np.abs(integral - x)) < 1e-6
        assert np.all(np.diff(x) > 0)  # strictly increasing: one crossing
        assert v.max() > 1.0  # underdamped (xi ~ 0.7): a small overshoot, as in Fig. 7-8
        assert abs(v[-1] - 1.0) < 1e-3


@pytest.mark.parametrize("r", [1e-6, 1e-3, 0.0094, 0.05, 0.3, 0.9, 1.2])
def test_crossing_matches_bisection(r):
    dyn = UsmSwitchModel()._dynamics(40_000.0)
    lo, hi = 0.0, 5.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if dyn.x(mid) < r else (lo, mid)
    assert dyn.crossing(r) == pytest.approx(0.5 * (lo + hi), rel=1e-11, abs=1e-14)


def test_reference_stroke_and_its_edge_instants():
    p = RigParams()
    m = UsmSwitchModel(quiet())
    assert m.nominal_operating_ns(ON, temperature_c=25.0) == p.nominal_operating_ns
    st = m.next_stroke(ON, 0)
    # The arrival is where the displacement crosses 5 mm, to within the 1 ns rounding.
    op = st.operating_ns
    assert st.displacement_mm(op - 1) < p.stroke_mm
    assert p.stroke_mm - st.displacement_mm(op - 1) < st.speed_mm_s(op - 1) * 2e-9
    assert st.displacement_mm(op) == p.stroke_mm
    # No motion during the dead time; the depart edge is where release_mm is reached.
    assert st.displacement_mm(p.dead_time_on_ns) == 0.0
    t_rel = st.time_at_ns(p.release_mm)
    assert st.displacement_mm(t_rel - 1) < p.release_mm <= st.displacement_mm(t_rel + 1)
    with pytest.raises(ValueError, match="travel_mm"):
        st.time_at_ns(6.0)


def test_lower_frequency_is_faster_across_table1():
    nominal = [
        UsmSwitchModel().nominal_operating_ns(ON, frequency_hz=f, temperature_c=25.0)
        for f in TABLE1_FREQUENCY_HZ
    ]
    assert all(a < b for a, b in itertools.pairwise(nominal)), nominal
    # The same with friction and heating, same seed: mean of 200 strokes at each frequency.
    means = []
    for f in TABLE1_FREQUENCY_HZ:
        m = UsmSwitchModel(seed=5)
        m.set_drive(frequency_hz=f)
        t = 0
        ops = []
        for k in range(200):
            st = m.next_stroke(Direction(k % 2), t)
            ops.append(st.operating_ns)
            t += st.operating_ns + 5_000_000
        means.append(np.mean(ops))
    assert all(a < b for a, b in itertools.pairwise(means)), means
    # Between 39.5 and 40.5 kHz the speed difference is Table 1's K w_n / w_n^2 ratio (~8 %).
    assert means[2] / means[0] > 1.06


def test_voltage_scales_speed():
    m = UsmSwitchModel()
    p = m.params
    motion = {v: m.motion_ns(ON, voltage_vpp=v, temperature_c=25.0) for v in (300.0, 400.0, 500.0, 600.0)}
    assert motion[300.0] > motion[400.0] > motion[500.0] > motion[600.0]
    # Past the speed's rise, motion time ~ 1 / speed, and speed ~ (V - dead zone).
    ratio = (500.0 - p.voltage_deadzone_vpp) / (300.0 - p.voltage_deadzone_vpp)
    lag_ns = m._dynamics(40_000.0).lag * p.table_time_unit_ns
    assert (motion[300.0] - lag_ns) / (motion[500.0] - lag_ns) == pytest.approx(ratio, rel=1e-3)
    for bad in (100.0, 900.0, "500", True):
        with pytest.raises(ValueError, match="voltage_vpp"):
            m.set_drive(voltage_vpp=bad)
    for bad in (39_000.0, 42_000.0, None.__class__):
        with pytest.raises(ValueError, match="frequency_hz"):
            m.set_drive(frequency_hz=bad)


def test_warmer_is_slower_as_in_fig9():
    means = {}
    for ambient in (25.0, 27.5, 30.0):
        m = UsmSwitchModel(dataclasses.replace(RigParams(), ambient_c=ambient), seed=3)
        t = 0
        ops = []
        for k in range(100):
            st = m.next_stroke(Direction(k % 2), t)
            ops.append(st.operating_ns)
            t += st.operating_ns + 20_000_000
        means[ambient] = np.mean(ops)
    # The resonance falls 10 Hz per C: 2.5 C is ~0.35 % of the operating time at 40 kHz (same seed,
    # same friction, so nothing else differs).
    assert 1.002 < means[27.5] / means[25.0] < 1.006
    assert 1.002 < means[30.0] / means[27.5] < 1.006


def test_warming_is_driving_further_above_the_resonance_that_it_lowered():
    # 10 C warmer at 40 kHz moves as the cold motor does at 40.1 kHz (the resonance 100 Hz lower).
    m = UsmSwitchModel(RigParams(), seed=1)
    warm = m.motion_ns(Direction.ON, frequency_hz=40_000.0, temperature_c=35.0)
    assert warm == pytest.approx(m.motion_ns(Direction.ON, frequency_hz=40_100.0, temperature_c=25.0))
    assert warm > m.motion_ns(Direction.ON, frequency_hz=40_000.0, temperature_c=25.0)


def test_on_and_off_differ():
    m = UsmSwitchModel(quiet())
    p = m.params
    assert m.dead_time_ns(ON) != m.dead_time_ns(OFF)
    on = m.nominal_operating_ns(ON, temperature_c=25.0)
    off = m.nominal_operating_ns(OFF, temperature_c=25.0)
    assert off - on > 300_000  # 3.5 % slower and 50 us more dead time
    # In a stroke stream the two directions keep their separate friction processes.
    m = UsmSwitchModel(seed=4)
    t = 0
    for k in range(400):
        st = m.next_stroke(Direction(k % 2), t)
        t += st.operating_ns + 10_000_000
    assert m.strokes == [200, 200]
    assert m.friction(ON) != m.friction(OFF)
    assert p.off_speed_ratio < 1.0


def test_thermal_state_heats_with_duty_and_cools_to_ambient():
    p = RigParams()
    temps = {}
    models = {}
    for gap_ns in (1_000_000, 30_000_000):
        m = UsmSwitchModel(quiet())
        t = k = 0
        while t < 5 * p.thermal_tau_ns:  # long enough to settle
            st = m.next_stroke(Direction(k % 2), t)
            t += st.operating_ns + gap_ns
            k += 1
        temps[gap_ns] = m.temperature_c(t)
        models[gap_ns] = (m, t)
    # Steady state ~ duty x the full-duty rise: back-to-back (duty ~0.9) vs 30 ms pauses (~0.25).
    rise = p.thermal_rise_full_duty_c
    assert temps[1_000_000] - p.ambient_c == pytest.approx(0.91 * rise, abs=0.3)
    assert temps[30_000_000] - p.ambient_c == pytest.approx(0.25 * rise, abs=0.3)
    # Idle for five time constants: the excess decays exponentially.
    m_hot = temps[1_000_000] - p.ambient_c
    m, t = models[1_000_000]
    later = t + 5 * p.thermal_tau_ns
    assert m.temperature_c(later) - p.ambient_c == pytest.approx(m_hot * math.exp(-5), rel=0.05)
    # Held drive (stall) keeps heating until drive_off; time never goes back.
    m.next_stroke(ON, later, jam_fraction=0.5)
    m.drive_off(later + 2 * p.thermal_tau_ns)
    assert m.temperature_c() > p.ambient_c + 0.8 * p.thermal_rise_full_duty_c
    with pytest.raises(ValueError, match="went back"):
        m.drive_off(later)


def test_jammed_stroke_never_arrives():
    m = UsmSwitchModel()
    st = m.next_stroke(ON, 0, jam_fraction=0.4)
    assert st.operating_ns is None and not st.arrives
    assert st.displacement_mm(10**12) == pytest.approx(0.4 * m.params.stroke_mm)
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="jam_fraction"):
            m.next_stroke(ON, 1, jam_fraction=bad)
    with pytest.raises(ValueError, match="distance_mm"):
        m.next_stroke(ON, 2, distance_mm=7.0)


def test_innovation_floor_holds_by_simulation():
    """The oracle (the model's own Kalman filter on each direction's past strokes, knowing the
    deterministic part) reaches the reported floor, so nothing can beat it: the floor is honest."""
    m = UsmSwitchModel(seed=11)
    p = m.params
    phi, gain = p.friction_phi, m.kalman_gain
    state = {ON: 0.0, OFF: 0.0}
    innov = {ON: [], OFF: []}
    t = 0
    for k in range(6000):
        d = Direction(k % 2)
        st = m.next_stroke(d, t)
        t += st.operating_ns + 2_000_000
        z = (st.operating_ns - st.dead_ns) / st.motion_nominal_ns - 1.0  # = friction + white noise
        pred = phi * state[d]
        nu = z - pred
        state[d] = pred + gain * nu
        if k >= 200:
            innov[d].append(nu * st.motion_nominal_ns)
    for d in Direction:
        floor = m.innovation_floor_ns(d)
        assert np.std(innov[d]) == pytest.approx(floor, rel=0.06), d
        assert abs(np.mean(innov[d])) < 0.15 * floor  # unbiased
    # The floor exceeds the white noise alone and is below the friction's full spread.
    assert p.white_std < m.innovation_floor_relative < p.friction_std


def test_profile_samples_displacement_and_speed():
    m = UsmSwitchModel(seed=2)
    st = m.next_stroke(ON, 0)
    prof = m.profile(st, step_ns=10_000)
    assert prof.t_ns[0] == 0 and prof.t_ns.dtype == np.int64
    assert np.all(np.diff(prof.displacement_mm) >= 0)
    assert prof.displacement_mm[prof.t_ns < st.dead_ns].max() == 0.0
    assert prof.displacement_mm[-1] <= m.params.stroke_mm
    # Speed is the derivative of displacement (mm/s), and holds near its plateau (~0.5 m/s).
    mid = (prof.t_ns > 3_000_000) & (prof.t_ns < st.operating_ns - 100_000)
    fd = np.gradient(prof.displacement_mm, prof.t_ns / 1e9)
    assert np.allclose(fd[mid], prof.speed_mm_s[mid], rtol=1e-3)
    assert 300 < np.median(prof.speed_mm_s[mid]) < 800
    # Past the arrival: held at 5 mm, speed 0 (the limit cut).
    long = m.profile(st, step_ns=100_000, until_ns=st.operating_ns + 1_000_000)
    assert long.displacement_mm[-1] == m.params.stroke_mm and long.speed_mm_s[-1] == 0.0
    with pytest.raises(ValueError, match="step_ns"):
        m.profile(st, step_ns=0)
    with pytest.raises(ValueError, match="until_ns"):
        m.profile(st, until_ns=-5)


def test_same_seed_same_strokes_and_bad_seeds():
    def series(seed: int) -> list[int]:
        m = UsmSwitchModel(seed=seed)
        return [m.next_stroke(Direction(k % 2), k * 25_000_000).operating_ns for k in range(50)]

    assert series(9) == series(9)
    assert series(9) != series(10)
    with pytest.raises(ValueError, match="seed"):
        UsmSwitchModel(seed=1.5)
    with pytest.raises(TypeError, match="RigParams"):
        UsmSwitchModel(params={"stroke_mm": 5})


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"table_wn2": (1.0, 2.0)}, "table_wn2"),
        ({"table_frequency_hz": (39_500.0, 39_000.0, 40_500.0, 41_000.0, 41_500.0)}, "ascending"),
        ({"table_2xi_wn": (50.0, 23.74, 24.02, 25.33, 25.44)}, "underdamped"),
        ({"stroke_mm": 0.0}, "stroke_mm"),
        ({"dead_time_on_ns": 0.3}, "dead_time_on_ns"),
        ({"friction_phi": 1.0}, "friction_phi"),
        ({"reference_frequency_hz": 45_000.0}, "reference_frequency_hz"),
        ({"voltage_min_vpp": 50.0}, "voltage_deadzone_vpp"),
        ({"nominal_operating_ns": 100_000}, "nominal_operating_ns"),
        ({"stall_fraction_max": 1.0}, "stall_fraction"),
        ({"white_std": -0.1}, "white_std"),
        ({"release_mm": 3.0}, "release_mm"),
        ({"resonance_hz_per_c": -50.0}, "resonance_hz_per_c"),
    ],
)
def test_bad_params_name_the_field(changes, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(RigParams(), **changes)
