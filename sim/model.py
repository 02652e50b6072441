"""The USM switch's physics: Eq. 1 motion, thermal state, friction process, innovation floor.

A stroke's motion follows the step response of Eq. 1, G(s) = K w_n / (s^2 + 2 xi w_n s + w_n^2),
read as drive -> mover speed, with Table 1's coefficients interpolated at the drive frequency.
The displacement is the integral of that speed in closed form; the far sensor is reached where it
crosses the stroke distance, found by a bracketed Newton iteration on the analytic expression.

Stroke-to-stroke variation: a deterministic part (frequency, voltage, temperature, direction) and
a random time scale `1 + F_k + w_k` on the motion, where F is an AR(1) friction process per
direction and w white noise. The motion time is linear in that scale, so the unpredictable part of
the next stroke is exactly the one-step innovation of "AR(1) + white noise", which the model
derives in closed form (the steady-state Kalman innovation variance) and reports as its floor.

Pure Python `math` in the per-stroke path: numpy's per-scalar calls would cost more than the model.
"""

from __future__ import annotations

import math
import random
from bisect import bisect_right
from dataclasses import dataclass

import numpy as np

from usmswitch.drivers.events import Direction

from .params import RigParams

_MIN_SCALE = 0.25  # a stroke never runs faster than 4x nominal, whatever the noise draws


class _Dynamics:
    """Eq. 1 at one drive frequency, in Table 1's units (time in table units, unit step input)."""

    __slots__ = ("a", "b", "bracket_pad", "ca", "cb", "k", "lag", "sig", "sig_wd", "v_ss", "wd")

    def __init__(self, wn2: float, two_xi_wn: float, k_wn: float) -> None:
        self.a = wn2
        self.b = two_xi_wn
        self.k = k_wn
        self.sig = two_xi_wn / 2.0  # xi * w_n, the decay rate
        self.wd = math.sqrt(wn2 - self.sig * self.sig)  # damped natural frequency
        self.lag = two_xi_wn / wn2  # 2 xi / w_n: the ramp's lag behind a unit speed
        # X(tau) = tau - lag + exp(-sig tau) * (ca cos(wd tau) + cb sin(wd tau)), X(0) = 0
        self.ca = self.lag
        self.cb = (2.0 * self.sig * self.sig / wn2 - 1.0) / self.wd
        self.sig_wd = self.sig / self.wd
        self.v_ss = k_wn / wn2  # steady speed of Eq. 1 for a unit step, in table units
        self.bracket_pad = self.lag + abs(self.ca) + abs(self.cb)

    def x(self, tau: float) -> float:
        """Displacement per unit steady speed after `tau` table units of motion."""
        if tau <= 0.0:
            return 0.0
        e = math.exp(-self.sig * tau)
        w = self.wd * tau
        return tau - self.lag + e * (self.ca * math.cos(w) + self.cb * math.sin(w))

    def v(self, tau: float) -> float:
        """Speed per unit steady speed (the unit step response of Eq. 1)."""
        if tau <= 0.0:
            return 0.0
        w = self.wd * tau
        return 1.0 - math.exp(-self.sig * tau) * (math.cos(w) + self.sig_wd * math.sin(w))

    def crossing(self, r: float) -> float:
        """The tau where x(tau) = r: bracketed Newton on the closed form (x is increasing)."""
        if r <= 0.0:
            return 0.0
        # x(tau) >= tau - lag - (|ca| + |cb|), so x(r + pad) >= r: a guaranteed bracket.
        lo, hi = 0.0, r + self.bracket_pad
        # Past the transient x is the ramp tau - lag; near the start it grows like a tau^3 / 6.
        t = r + self.lag if r > self.lag else (6.0 * r / self.a) ** (1.0 / 3.0)
        sig, wd, ca, cb, lag, sw = self.sig, self.wd, self.ca, self.cb, self.lag, self.sig_wd
        exp, cos, sin = math.exp, math.cos, math.sin
        for _ in range(100):
            e = exp(-sig * t)
            w = wd * t
            c = cos(w)
            s = sin(w)
            f = t - lag + e * (ca * c + cb * s) - r
            if f > 0.0:
                hi = t
            elif f < 0.0:
                lo = t
            else:
                return t
            d = 1.0 - e * (c + sw * s)
            tn = t - f / d if d > 0.0 else -1.0
            if not lo <= tn <= hi:
                tn = 0.5 * (lo + hi)
            if abs(tn - t) <= 1e-13 * (1.0 + t):
                return tn
            t = tn
        return t  # the bracket has shrunk below float resolution


@dataclass(frozen=True, slots=True)
class Profile:
    """Sampled motion of one stroke: offsets from drive-on, displacement and speed."""

    t_ns: np.ndarray  # int64, offsets from the stroke's drive-on instant
    displacement_mm: np.ndarray
    speed_mm_s: np.ndarray


class Stroke:
    """One stroke as the model resolved it. Offsets are from the drive-on instant `t_start_ns`."""

    __slots__ = (
        "_dyn",
        "_reach",
        "_unit",
        "arrives",
        "dead_ns",
        "direction",
        "distance_mm",
        "end_mm",
        "end_offset_ns",
        "frequency_hz",
        "motion_nominal_ns",
        "operating_ns",
        "scale",
        "t_start_ns",
        "temperature_c",
        "voltage_vpp",
    )

    def __init__(
        self,
        direction: Direction,
        t_start_ns: int,
        dyn: _Dynamics,
        reach: float,
        unit_ns: float,
        dead_ns: int,
        distance_mm: float,
        end_mm: float,
        scale: float,
        temperature_c: float,
        frequency_hz: float,
        voltage_vpp: float,
    ) -> None:
        self.direction = direction
        self.t_start_ns = t_start_ns
        self._dyn = dyn
        self._reach = reach  # mm per table time unit at steady speed
        self._unit = unit_ns * scale  # ns per table time unit, stretched by this stroke's scale
        self.dead_ns = dead_ns
        self.distance_mm = distance_mm
        self.end_mm = end_mm  # where the motion ends: the far sensor, or where it jammed
        self.arrives = end_mm >= distance_mm
        self.scale = scale  # 1 + friction + white noise
        self.temperature_c = temperature_c
        self.frequency_hz = frequency_hz
        self.voltage_vpp = voltage_vpp
        tau = dyn.crossing(end_mm / reach)
        self.end_offset_ns = dead_ns + round(tau * self._unit)
        #: Drive-on to far-sensor edge (None when the mover jams and never arrives).
        self.operating_ns: int | None = self.end_offset_ns if self.arrives else None
        #: The motion time this stroke would take with friction at its mean and no noise.
        full = tau if self.arrives else dyn.crossing(distance_mm / reach)
        self.motion_nominal_ns = full * unit_ns

    def time_at_ns(self, travel_mm: float) -> int:
        """Offset at which the mover has covered `travel_mm` (an edge's instant)."""
        if not 0.0 <= travel_mm <= self.end_mm:
            raise ValueError(f"travel_mm must be in [0, {self.end_mm}], got {travel_mm!r}")
        return self.dead_ns + round(self._dyn.crossing(travel_mm / self._reach) * self._unit)

    def displacement_mm(self, offset_ns: int) -> float:
        """Distance covered `offset_ns` after drive-on (held at the end of the motion)."""
        if offset_ns >= self.end_offset_ns:
            return self.end_mm
        tau = (offset_ns - self.dead_ns) / self._unit
        return min(self._reach * self._dyn.x(tau), self.end_mm)

    def speed_mm_s(self, offset_ns: int) -> float:
        """Mover speed `offset_ns` after drive-on (zero once the motion has ended)."""
        if offset_ns >= self.end_offset_ns:
            return 0.0
        tau = (offset_ns - self.dead_ns) / self._unit
        return self._reach * self._dyn.v(tau) / self._unit * 1e9


class UsmSwitchModel:
    """The rig's physics: stroke times at given conditions, thermal state, friction process."""

    def __init__(self, params: RigParams | None = None, seed: int = 0) -> None:
        if params is None:
            params = RigParams()
        if not isinstance(params, RigParams):
            raise TypeError(f"params must be a RigParams, got {type(params).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"seed must be an integer, got {seed!r}")
        self.params = p = params
        self.seed = seed
        self._rng = random.Random(seed)
        self._dyn_cache: dict[float, _Dynamics] = {}
        self._unit = float(p.table_time_unit_ns)
        # Calibrate Eq. 1's displacement gain: an "on" stroke at the reference point takes
        # nominal_operating_ns, so reach (mm per table unit at steady speed) = stroke / x(tau).
        ref = self._dynamics(p.reference_frequency_hz)
        tau_ref = (p.nominal_operating_ns - p.dead_time_on_ns) / self._unit
        self._reach_ref = p.stroke_mm / ref.x(tau_ref)
        self._gain_per_kwn = self._reach_ref / ref.v_ss  # mm per unit of Table 1's K w_n / w_n^2
        self._innov_sd = p.friction_std * math.sqrt(1.0 - p.friction_phi**2)
        # Start both friction processes in their stationary distribution.
        self._friction = [self._rng.gauss(0.0, p.friction_std), self._rng.gauss(0.0, p.friction_std)]
        self.strokes = [0, 0]  # strokes drawn per direction
        self.frequency_hz = p.reference_frequency_hz
        self.voltage_vpp = p.reference_voltage_vpp
        # Thermal state: excess over ambient at _t_theta; the drive is on from _on_from to
        # _on_until (None: until drive_off), or off when _on_from is None.
        self._theta = 0.0
        self._t_theta = 0
        self._on_from: int | None = None
        self._on_until: int | None = None
        self._theta_full = p.thermal_rise_full_duty_c
        self._tau_th = float(p.thermal_tau_ns)
        self.last_stroke: Stroke | None = None

    @property
    def gain_mm_per_kwn(self) -> float:
        """The displacement gain calibrated at the reference point: steady speed (mm per Table 1
        time unit) per unit of Eq. 1's steady output K w_n / w_n^2 (what identification needs)."""
        return self._gain_per_kwn

    # -- drive settings ------------------------------------------------------------------------
    def set_drive(self, *, frequency_hz: float | None = None, voltage_vpp: float | None = None) -> None:
        """Set the excitation like the drive board would; applies from the next stroke."""
        if frequency_hz is not None:
            self.frequency_hz = self._check_frequency(frequency_hz)
        if voltage_vpp is not None:
            self.voltage_vpp = self._check_voltage(voltage_vpp)

    def _check_frequency(self, frequency_hz: float) -> float:
        f = self.params.table_frequency_hz
        if isinstance(frequency_hz, bool) or not isinstance(frequency_hz, int | float):
            raise ValueError(f"frequency_hz must be a number, got {frequency_hz!r}")
        if not f[0] <= frequency_hz <= f[-1]:
            raise ValueError(f"frequency_hz {frequency_hz!r} is outside Table 1's {f[0]:.0f}-{f[-1]:.0f} Hz")
        return float(frequency_hz)

    def _check_voltage(self, voltage_vpp: float) -> float:
        p = self.params
        if isinstance(voltage_vpp, bool) or not isinstance(voltage_vpp, int | float):
            raise ValueError(f"voltage_vpp must be a number, got {voltage_vpp!r}")
        if not p.voltage_min_vpp <= voltage_vpp <= p.voltage_max_vpp:
            raise ValueError(
                f"voltage_vpp {voltage_vpp!r} is outside the drive's "
                f"{p.voltage_min_vpp:.0f}-{p.voltage_max_vpp:.0f} Vpp"
            )
        return float(voltage_vpp)

    def _dynamics(self, frequency_hz: float) -> _Dynamics:
        """Table 1 at a drive frequency, cold (at the reference temperature); cached per frequency."""
        dyn = self._dyn_cache.get(frequency_hz)
        if dyn is None:
            dyn = self._dyn_cache[frequency_hz] = self._table(frequency_hz)
        return dyn

    def _table(self, frequency_hz: float) -> _Dynamics:
        """Table 1 interpolated (extrapolated along its end rows beyond its span)."""
        p = self.params
        f = p.table_frequency_hz
        i = min(max(bisect_right(f, frequency_hz) - 1, 0), len(f) - 2)
        w = (frequency_hz - f[i]) / (f[i + 1] - f[i])

        def lerp(col: tuple[float, ...]) -> float:
            return col[i] + w * (col[i + 1] - col[i])

        return _Dynamics(lerp(p.table_wn2), lerp(p.table_2xi_wn), lerp(p.table_k_wn))

    def _dynamics_at(self, frequency_hz: float, temperature_c: float) -> _Dynamics:
        """The motor's dynamics driven at `frequency_hz` at `temperature_c`: the cold motor's at the
        drive's distance from the resonance that warming moved (`resonance_hz_per_c`). Not cached
        off the reference temperature: the temperature is continuous."""
        p = self.params
        shift = p.resonance_hz_per_c * (temperature_c - p.reference_temperature_c)
        return self._dynamics(frequency_hz) if shift == 0.0 else self._table(frequency_hz - shift)

    def _reach(self, direction: Direction, dyn: _Dynamics, voltage_vpp: float) -> float:
        """Steady-speed reach (mm per table unit) at these conditions."""
        p = self.params
        volt = (voltage_vpp - p.voltage_deadzone_vpp) / (p.reference_voltage_vpp - p.voltage_deadzone_vpp)
        side = 1.0 if direction is Direction.ON else p.off_speed_ratio
        return self._gain_per_kwn * dyn.v_ss * volt * side

    def dead_time_ns(self, direction: Direction) -> int:
        """Drive-on to first motion for a direction (the stator's build-up)."""
        p = self.params
        return p.dead_time_on_ns if Direction(direction) is Direction.ON else p.dead_time_off_ns

    # -- deterministic physics -----------------------------------------------------------------
    def motion_ns(
        self,
        direction: Direction,
        *,
        frequency_hz: float | None = None,
        voltage_vpp: float | None = None,
        temperature_c: float | None = None,
        distance_mm: float | None = None,
    ) -> float:
        """Motion time (after the dead time) with friction at its mean: the predictable part."""
        direction = Direction(direction)
        f = self.frequency_hz if frequency_hz is None else self._check_frequency(frequency_hz)
        v = self.voltage_vpp if voltage_vpp is None else self._check_voltage(voltage_vpp)
        t_c = self.temperature_c() if temperature_c is None else float(temperature_c)
        d = self.params.stroke_mm if distance_mm is None else float(distance_mm)
        if d <= 0.0:
            raise ValueError(f"distance_mm must be > 0, got {distance_mm!r}")
        dyn = self._dynamics_at(f, t_c)
        return dyn.crossing(d / self._reach(direction, dyn, v)) * self._unit

    def nominal_operating_ns(self, direction: Direction, **conditions: float) -> int:
        """Dead time plus `motion_ns`: a full stroke's operating time with no friction or noise."""
        return self.dead_time_ns(direction) + round(self.motion_ns(direction, **conditions))

    # -- the innovation floor ------------------------------------------------------------------
    @property
    def innovation_floor_relative(self) -> float:
        """Std of the one-step innovation of the motion-time scale given all past strokes.

        The scale is F + w with F AR(1) (phi, innovation q) and w white (r): its best one-step
        predictor is the steady-state Kalman filter, whose innovation variance P + r solves
        P = phi^2 P r / (P + r) + q.
        """
        p = self.params
        q = self._innov_sd**2
        r = p.white_std**2
        phi2 = p.friction_phi**2
        c = r * (1.0 - phi2) - q
        big_p = 0.5 * (-c + math.sqrt(c * c + 4.0 * q * r))
        return math.sqrt(big_p + r)

    @property
    def kalman_gain(self) -> float:
        """Steady-state Kalman gain of the friction filter (for oracle predictors in tests)."""
        r = self.params.white_std**2
        s2 = self.innovation_floor_relative**2
        return (s2 - r) / s2

    def innovation_floor_ns(self, direction: Direction, **conditions: float) -> float:
        """Std (ns) of the part of the next stroke time no predictor can know from the past."""
        return self.motion_ns(direction, **conditions) * self.innovation_floor_relative

    # -- thermal state -------------------------------------------------------------------------
    def _theta_at(self, t_ns: int) -> float:
        th, t0 = self._theta, self._t_theta
        tau = self._tau_th
        a = self._on_from
        if a is None:
            return th * math.exp((t0 - t_ns) / tau) if t_ns > t0 else th
        if a > t0:
            th *= math.exp((t0 - a) / tau)
            t0 = a
        b = self._on_until
        end = t_ns if b is None or b > t_ns else b
        if end > t0:
            full = self._theta_full
            th = full + (th - full) * math.exp((t0 - end) / tau)
            t0 = end
        if t_ns > t0:
            th *= math.exp((t0 - t_ns) / tau)
        return th

    def _settle(self, t_ns: int) -> None:
        if t_ns < self._t_theta:
            raise ValueError(f"thermal time went back: t_ns={t_ns} before {self._t_theta}")
        self._theta = self._theta_at(t_ns)
        self._t_theta = t_ns
        if self._on_from is not None:
            if self._on_until is not None and self._on_until <= t_ns:
                self._on_from = None
            else:
                self._on_from = t_ns

    # -- what the rig remembers between runs of the daemon ----------------------------------------
    STATE_FORMAT = 1

    def state(self, t_ns: int) -> dict[str, object]:
        """The rig's slow state at `t_ns`, plain data for a JSON file: friction per direction, how
        much warmer than ambient the motor is, strokes made, the drive's setting. A new model
        given it (`restore`) faces the rig this one left, not a fresh one."""
        theta = self._theta_at(max(t_ns, self._t_theta))
        return {
            "format": self.STATE_FORMAT,
            "friction": list(self._friction),
            "theta_c": theta,
            "strokes": list(self.strokes),
            "frequency_hz": self.frequency_hz,
            "voltage_vpp": self.voltage_vpp,
        }

    def restore(self, state: dict[str, object], t_ns: int, idle_ns: int = 0) -> None:
        """Take up `state` at `t_ns`, the motor having cooled (drive off) for `idle_ns` since it was
        saved. ValueError names what does not fit (the caller then starts from a fresh rig)."""
        if state.get("format") != self.STATE_FORMAT:
            raise ValueError(
                f"rig state format {state.get('format')!r}, this model reads {self.STATE_FORMAT}"
            )
        friction = state["friction"]
        strokes = state["strokes"]
        theta = state["theta_c"]
        if not (
            isinstance(friction, list) and len(friction) == 2 and all(isinstance(f, float) for f in friction)
        ):
            raise ValueError(f"rig state friction {friction!r} is not two numbers")
        if not (isinstance(strokes, list) and len(strokes) == 2 and all(isinstance(n, int) for n in strokes)):
            raise ValueError(f"rig state strokes {strokes!r} is not two counts")
        if not isinstance(theta, float) or not 0.0 <= theta <= 100.0:
            raise ValueError(f"rig state theta_c {theta!r} is not a temperature rise")
        if idle_ns < 0:
            raise ValueError(f"idle_ns must be >= 0, got {idle_ns}")
        self.set_drive(frequency_hz=state["frequency_hz"], voltage_vpp=state["voltage_vpp"])  # type: ignore[arg-type]
        self._friction = [float(f) for f in friction]
        self.strokes = [int(n) for n in strokes]
        self._theta = theta * math.exp(-idle_ns / self._tau_th)
        self._t_theta = t_ns
        self._on_from = self._on_until = None

    def temperature_c(self, t_ns: int | None = None) -> float:
        """Motor temperature at `t_ns` (None: at the last instant the model was told about)."""
        if t_ns is None or t_ns < self._t_theta:
            t_ns = self._t_theta
        return self.params.ambient_c + self._theta_at(t_ns)

    def drive_on(self, t_ns: int, until_ns: int | None = None) -> None:
        """The drive heats the motor from `t_ns` until `until_ns` (None: until drive_off)."""
        self._settle(t_ns)
        if until_ns is not None and until_ns < t_ns:
            raise ValueError(f"until_ns {until_ns} is before t_ns {t_ns}")
        self._on_from = t_ns
        self._on_until = until_ns

    def drive_off(self, t_ns: int) -> None:
        """The drive was cut at `t_ns` (stop, stall timeout, disconnect): heating ends there."""
        self._settle(t_ns)
        self._on_from = None
        self._on_until = None

    # -- strokes -------------------------------------------------------------------------------
    def next_stroke(
        self,
        direction: Direction,
        t_start_ns: int,
        *,
        distance_mm: float | None = None,
        jam_fraction: float | None = None,
    ) -> Stroke:
        """Draw the next stroke of `direction` started at `t_start_ns`, and heat the motor for it.

        The drive is taken as on until the far sensor cuts it (the rig's limit cut); a jammed
        stroke (`jam_fraction` of the way, a stall) keeps it on until `drive_off`.
        """
        direction = Direction(direction)
        p = self.params
        d = p.stroke_mm if distance_mm is None else float(distance_mm)
        if not 0.0 < d <= p.stroke_mm:
            raise ValueError(f"distance_mm must be in (0, {p.stroke_mm}], got {distance_mm!r}")
        self._settle(t_start_ns)
        temp_c = p.ambient_c + self._theta
        i = int(direction)
        fr = p.friction_phi * self._friction[i] + self._innov_sd * self._rng.gauss(0.0, 1.0)
        self._friction[i] = fr
        scale = 1.0 + fr + p.white_std * self._rng.gauss(0.0, 1.0)
        if scale < _MIN_SCALE:
            scale = _MIN_SCALE
        self.strokes[i] += 1
        f = self.frequency_hz
        v = self.voltage_vpp
        dyn = self._dynamics_at(f, temp_c)
        reach = self._reach(direction, dyn, v)
        dead = p.dead_time_on_ns if i == 0 else p.dead_time_off_ns
        if jam_fraction is None:
            end = d
        elif 0.0 < jam_fraction < 1.0:
            end = d * jam_fraction
        else:
            raise ValueError(f"jam_fraction must be in (0, 1), got {jam_fraction!r}")
        st = Stroke(direction, t_start_ns, dyn, reach, self._unit, dead, d, end, scale, temp_c, f, v)
        self._on_from = t_start_ns
        self._on_until = st.operating_ns + t_start_ns if st.arrives else None
        self.last_stroke = st
        return st

    def expected_operating_ns(self, direction: Direction) -> int:
        """The next stroke's operating time as the model expects it now: the drive and temperature
        now, friction where its AR(1) goes next from its current level, no noise. What the simulated
        rig tells the daemon for a direction's first stroke (a real rig has nothing like it)."""
        i = int(Direction(direction))
        scale = 1.0 + self.params.friction_phi * self._friction[i]
        return self.dead_time_ns(direction) + round(self.motion_ns(direction) * scale)

    def noise_state(self) -> tuple[list[float], object]:
        """The friction and the noise stream as they are now. `rewind` to it and the rig makes the
        same strokes again, so an experiment can vary one condition and nothing else (common random
        numbers: Fig. 9's temperatures each meet the same friction, not three stretches of its drift)."""
        return (list(self._friction), self._rng.getstate())

    def rewind(self, state: tuple[list[float], object]) -> None:
        """Back to a `noise_state()`: the same friction and noise from here (the drive, the thermal
        state and the stroke counts are left as they are)."""
        friction, rng = state
        self._friction = [float(f) for f in friction]
        self._rng.setstate(rng)  # type: ignore[arg-type]

    def friction(self, direction: Direction) -> float:
        """The friction state of a direction (relative motion-time offset), for diagnostics."""
        return self._friction[int(Direction(direction))]

    def profile(self, stroke: Stroke, *, step_ns: int = 10_000, until_ns: int | None = None) -> Profile:
        """Sample a stroke's displacement and speed every `step_ns` from drive-on (Fig. 7-8)."""
        if isinstance(step_ns, bool) or not isinstance(step_ns, int) or step_ns <= 0:
            raise ValueError(f"step_ns must be a positive integer of nanoseconds, got {step_ns!r}")
        end = stroke.end_offset_ns if until_ns is None else until_ns
        if isinstance(end, bool) or not isinstance(end, int) or end < 0:
            raise ValueError(f"until_ns must be a non-negative integer of nanoseconds, got {until_ns!r}")
        t = np.arange(0, end + 1, step_ns, dtype=np.int64)
        dyn = stroke._dyn
        unit = stroke._unit
        tau = np.clip((t - stroke.dead_ns) / unit, 0.0, None)
        e = np.exp(-dyn.sig * tau)
        w = dyn.wd * tau
        x = np.where(tau > 0.0, tau - dyn.lag + e * (dyn.ca * np.cos(w) + dyn.cb * np.sin(w)), 0.0)
        v = np.where(tau > 0.0, 1.0 - e * (np.cos(w) + dyn.sig_wd * np.sin(w)), 0.0)
        moving = t < stroke.end_offset_ns
        disp = np.where(moving, np.minimum(stroke._reach * x, stroke.end_mm), stroke.end_mm)
        speed = np.where(moving, stroke._reach * v / unit * 1e9, 0.0)
        return Profile(t, disp, speed)
