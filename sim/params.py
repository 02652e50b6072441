"""Every physical parameter of the simulated rig, each with where its value comes from.

Sources: "Table 1", "Fig. N" and "Sec. N" refer to Li, Yao, Zhou, Zhou, JVE 2017 (the paper);
"assumption" marks a value the paper does not give, with the reasoning for the number chosen.
Relative quantities (friction, white noise) are fractions of the stroke's motion time.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, fields

# Table 1 (identification result of Eq. 1), rows sorted by ascending excitation frequency.
TABLE1_FREQUENCY_HZ: tuple[float, ...] = (39_500.0, 40_000.0, 40_500.0, 41_000.0, 41_500.0)
TABLE1_WN2: tuple[float, ...] = (298.0, 296.7, 295.0, 324.0, 321.5)
TABLE1_2XI_WN: tuple[float, ...] = (23.35, 23.74, 24.02, 25.33, 25.44)
TABLE1_K_WN: tuple[float, ...] = (647.4, 642.9, 587.5, 578.7, 558.1)


@dataclass(frozen=True)
class RigParams:
    """The rig's physical parameters; the field comments give each one's source."""

    # -- geometry --------------------------------------------------------------------------
    #: Sec. 3 / Fig. 3: the mover reciprocates over 5 mm between the two limit sensors.
    stroke_mm: float = 5.0
    #: assumption: a limit sensor releases once the mover is 50 um away from its rest point
    #: (optical-fork hysteresis); the depart edge is stamped there.
    release_mm: float = 0.05

    # -- Eq. 1 and Table 1 ---------------------------------------------------------------------
    #: Table 1: excitation frequencies (Hz), ascending.
    table_frequency_hz: tuple[float, ...] = TABLE1_FREQUENCY_HZ
    #: Table 1: w_n^2 per row (the table's units).
    table_wn2: tuple[float, ...] = TABLE1_WN2
    #: Table 1: 2 xi w_n per row.
    table_2xi_wn: tuple[float, ...] = TABLE1_2XI_WN
    #: Table 1: K w_n per row.
    table_k_wn: tuple[float, ...] = TABLE1_K_WN
    #: assumption: Table 1 does not state its time unit. One unit = 10 ms makes the speed's
    #: 10-90 % rise (~0.12 units at xi ~ 0.69) about 1.2 ms, early in a ~10 ms stroke, the
    #: shape of the speed responses in Fig. 7-8 (fast rise, then a plateau).
    table_time_unit_ns: int = 10_000_000

    # -- reference operating point and calibration ---------------------------------------------
    #: Fig. 12 / Sec. 6: the paper's control runs at 40 kHz and 500 Vpp.
    reference_frequency_hz: float = 40_000.0
    #: Fig. 6-8, 12-13: 500 Vpp drive.
    reference_voltage_vpp: float = 500.0
    #: Fig. 9: the coolest curve, 25 C, taken as the reference temperature.
    reference_temperature_c: float = 25.0
    #: Sec. 6 (Fig. 15-16): at a fixed 10.5 ms every one of 100,000 cycles "has enough time to
    #: delay the start", so no stroke may take 10.5 ms; and T = 12 ms leaves room too. An "on"
    #: stroke from rest at the reference point, cold, friction at its mean, takes 8.0 ms from
    #: drive-on to the far sensor; warm-up and the slower "off" put a run's mean near 8.3 ms and
    #: its slowest stroke in 100,000 near 9.9-10.0 ms (docs/sim.md, the calibration's evidence).
    #: The displacement gain of Eq. 1 (mm per table unit) is solved from this number.
    nominal_operating_ns: int = 8_000_000

    # -- on / off asymmetry and dead time ------------------------------------------------------
    #: assumption: the stator needs ~0.3 ms to build its elliptical motion before the mover
    #: moves ("on/off time in a millisecond", Sec. 3; the dead zone of [15]).
    dead_time_on_ns: int = 300_000
    #: assumption: the reverse phase (90 deg the other way, Sec. 2) builds up a little slower.
    dead_time_off_ns: int = 350_000
    #: assumption: "off" runs 3.5 % slower than "on" (the two mode couplings of the V-shape
    #: stator are not perfectly symmetric, Fig. 2), so the two directions differ as on a real rig.
    off_speed_ratio: float = 0.965

    # -- drive voltage -------------------------------------------------------------------------
    #: assumption: speed grows linearly with the drive voltage above a dead zone (the dead-zone
    #: model of Senjyu [15]); below 100 Vpp the stator does not overcome the preload.
    voltage_deadzone_vpp: float = 100.0
    #: assumption: the drive board's limits; a setting outside them is refused.
    voltage_min_vpp: float = 150.0
    voltage_max_vpp: float = 700.0

    # -- temperature (Fig. 9) and the thermal state ----------------------------------------------
    #: Fig. 9: speed differs between 25, 27.5 and 30 C. The stator's resonance falls as it warms
    #: (its elastic moduli soften), by this much per C: a drive above resonance, as Table 1 shows
    #: this rig's is, is then further from it, and the motor moves as the cold motor would at
    #: frequency + 10 Hz per C over reference (Table 1: slower). Size: an electro-thermal USM model
    #: validated on a motor retunes its drive about 10 Hz per C (J. Intell. Mater. Syst. Struct.,
    #: 2025, doi 10.1177/1045389X251327239); docs/sim.md.
    resonance_hz_per_c: float = -10.0
    #: assumption: the lab's ambient equals the reference temperature.
    ambient_c: float = 25.0
    #: assumption: the stator (a few grams of piezo ceramic and metal) heats and cools with a
    #: 6 s time constant, so Fig. 6-style open-loop runs show their warm-up within ~500 strokes.
    thermal_tau_ns: int = 6_000_000_000
    #: assumption: driven continuously (100 % duty) the motor settles 5 C above ambient: the
    #: 25-30 C span of Fig. 9. Heat input is proportional to drive-on time (duty).
    thermal_rise_full_duty_c: float = 5.0

    # -- friction and noise (Fig. 6) -----------------------------------------------------------
    #: assumption: friction is an AR(1) process per direction (each direction loads its own
    #: flank of the V-shape drive foot's elliptical path), indexed by that direction's strokes;
    #: lag-one correlation 0.975, the wandering of Fig. 6 and an AR(1) fit that wins AIC
    #: (Table 2).
    friction_phi: float = 0.975
    #: assumption: stationary std of the friction's effect on motion time, 4 %, so open loop
    #: is "highly dispersed" (Fig. 6): ~0.33 ms at 8.3 ms, 6.9-10.0 ms over 100,000 strokes.
    friction_std: float = 0.04
    #: assumption: per-stroke white noise on the motion time (contact micro-slip, piezo
    #: nonlinearity), 0.55 %: with the friction innovation it puts the paper's AR(1) closed-loop
    #: error std at ~94 us (T = 12 ms, 40 kHz) and ~102 us (24 ms, 40.5 kHz), beside the paper's
    #: 95.3 and 102.7 us (Sec. 6).
    white_std: float = 0.0055

    # -- fault shapes (for injected faults) -------------------------------------------------------
    #: assumption: a stalled mover jams between 20 % and 80 % of its way.
    stall_fraction_min: float = 0.2
    stall_fraction_max: float = 0.8
    #: assumption: a bouncing sensor chatters 1 to 3 extra on/off pairs after arriving ...
    bounce_pairs_max: int = 3
    #: ... with 2-20 us between transitions (a contact or fork edge, well inside 100 us debounce).
    bounce_gap_min_ns: int = 2_000
    bounce_gap_max_ns: int = 20_000
    #: assumption: a spurious pulse (EMI on the sensor line, a reflection in the fork) lasts
    #: 1-200 us: the shorter half is filtered by a 100 us settle debounce, the longer half gets
    #: through as a pair of edges a controller must reject.
    glitch_width_min_ns: int = 1_000
    glitch_width_max_ns: int = 200_000

    def __post_init__(self) -> None:
        n = len(self.table_frequency_hz)
        if n < 2:
            raise ValueError(f"table_frequency_hz needs >= 2 rows, got {self.table_frequency_hz!r}")
        for name in ("table_wn2", "table_2xi_wn", "table_k_wn"):
            col = getattr(self, name)
            if len(col) != n:
                raise ValueError(f"{name} has {len(col)} rows, table_frequency_hz has {n}")
            if any(not (v > 0 and math.isfinite(v)) for v in col):
                raise ValueError(f"{name} must be positive and finite, got {col!r}")
        f = self.table_frequency_hz
        if any(b <= a for a, b in itertools.pairwise(f)):
            raise ValueError(f"table_frequency_hz must be strictly ascending, got {f!r}")
        for wn2, b in zip(self.table_wn2, self.table_2xi_wn, strict=True):
            if b * b >= 4.0 * wn2:
                raise ValueError(f"Table row with w_n^2={wn2}, 2 xi w_n={b} is not underdamped (xi >= 1)")
        positive = (
            "stroke_mm",
            "release_mm",
            "table_time_unit_ns",
            "reference_voltage_vpp",
            "nominal_operating_ns",
            "off_speed_ratio",
            "thermal_tau_ns",
            "friction_std",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        nonneg = (
            "dead_time_on_ns",
            "dead_time_off_ns",
            "voltage_deadzone_vpp",
            "thermal_rise_full_duty_c",
            "white_std",
            "bounce_gap_min_ns",
            "glitch_width_min_ns",
        )
        for name in nonneg:
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        for fld in fields(self):
            value = getattr(self, fld.name)
            if fld.name.endswith("_ns") and (isinstance(value, bool) or not isinstance(value, int)):
                raise ValueError(f"{fld.name} must be an integer of nanoseconds, got {value!r}")
        if self.release_mm >= self.stroke_mm / 2:
            raise ValueError(f"release_mm must be < stroke_mm / 2, got {self.release_mm!r}")
        if not f[0] <= self.reference_frequency_hz <= f[-1]:
            raise ValueError(f"reference_frequency_hz {self.reference_frequency_hz!r} is outside Table 1")
        volts = (
            self.voltage_deadzone_vpp,
            self.voltage_min_vpp,
            self.reference_voltage_vpp,
            self.voltage_max_vpp,
        )
        if not volts[0] < volts[1] <= volts[2] <= volts[3]:
            raise ValueError(
                "need voltage_deadzone_vpp < voltage_min_vpp <= reference_voltage_vpp <= voltage_max_vpp, "
                f"got {volts!r}"
            )
        if not -1.0 < self.friction_phi < 1.0:
            raise ValueError(f"friction_phi must be in (-1, 1), got {self.friction_phi!r}")
        if self.nominal_operating_ns <= self.dead_time_on_ns:
            raise ValueError(
                f"nominal_operating_ns {self.nominal_operating_ns!r} must exceed "
                f"dead_time_on_ns {self.dead_time_on_ns!r}"
            )
        if not 0.0 < self.stall_fraction_min <= self.stall_fraction_max < 1.0:
            raise ValueError(
                f"need 0 < stall_fraction_min <= stall_fraction_max < 1, got "
                f"{self.stall_fraction_min!r}, {self.stall_fraction_max!r}"
            )
        if self.bounce_pairs_max < 1:
            raise ValueError(f"bounce_pairs_max must be >= 1, got {self.bounce_pairs_max!r}")
        if self.bounce_gap_max_ns < self.bounce_gap_min_ns or (
            self.glitch_width_max_ns < self.glitch_width_min_ns
        ):
            raise ValueError("bounce gap and glitch width ranges must have min <= max")
        # Within Table 1's span (2 kHz) over 50 C: beyond it the table is extrapolated.
        if not -40.0 <= self.resonance_hz_per_c <= 40.0:
            raise ValueError(
                f"resonance_hz_per_c {self.resonance_hz_per_c!r} is outside -40..40 Hz per C "
                "(a stator's resonance moves tens of Hz per C at most)"
            )
