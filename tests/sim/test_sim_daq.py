"""SimDaq: the event stream, determinism, every injected fault, and the drivers.Daq base
behaviour (debounce, order check, arming) exercised through it."""

from __future__ import annotations

import tomllib

import pytest

from usmswitch.drivers import (
    Channel,
    Conditions,
    DaqDisconnected,
    DaqError,
    DaqHalted,
    Direction,
    Event,
    EventKind,
    FaultCode,
    MonotonicClock,
    VirtualClock,
)
from usmswitch.sim import FaultPlan, SimDaq

ON, OFF = Direction.ON, Direction.OFF
A, B = Channel.A, Channel.B


def drain(daq: SimDaq, timeout_ns: int = 30_000_000) -> list[Event]:
    """Every event until none comes within `timeout_ns` (the clock ends past the last event)."""
    out = []
    while (ev := daq.recv(timeout_ns)) is not None:
        out.append(ev)
    return out


def edges(events: list[Event]) -> list[tuple[Channel, int]]:
    return [(ev.channel, ev.level) for ev in events if ev.kind is EventKind.EDGE]


def stroke(daq: SimDaq, direction: Direction, delay_ns: int = 0) -> list[Event]:
    daq.arm(direction, delay_ns)
    daq.command()
    return drain(daq)


@pytest.fixture
def daq():
    d = SimDaq(seed=0)
    d.open()
    yield d
    d.close()


def test_a_stroke_is_start_depart_arrive_on_a_virtual_clock(daq):
    assert isinstance(daq.clock, VirtualClock) and not daq.hardware_timed
    daq.arm(ON, 2_000_000)
    cmd = daq.command()
    assert cmd.t_cmd_ns == 0 and cmd.t_start_ns == 2_000_000 and cmd.lateness_ns == 0
    start = daq.recv(0)
    assert start.kind is EventKind.START and start.direction is ON and start.t_ns == cmd.t_start_ns
    depart = daq.recv(None)
    assert (depart.kind, depart.channel, depart.level) == (EventKind.EDGE, A, 0)
    arrive = daq.recv(None)
    assert (arrive.kind, arrive.channel, arrive.level) == (EventKind.EDGE, B, 1)
    dead = daq.model.dead_time_ns(ON)
    assert cmd.t_start_ns + dead < depart.t_ns < cmd.t_start_ns + dead + 2_000_000
    assert 7_500_000 < arrive.t_ns - cmd.t_start_ns < 10_500_000
    # The clock jumped to each event, then waited out the base's settle debounce, no further.
    settled = arrive.t_ns + daq.debounce_ns
    assert daq.now_ns() == settled
    assert daq.recv(None) is None and daq.now_ns() == settled  # nothing left: at once
    assert daq.recv(5_000_000) is None and daq.now_ns() == settled + 5_000_000
    assert daq.levels() == (0, 1) and daq.position_mm() == 5.0
    # The limit cut turned the drive off: the next stroke starts at once, the other way.
    events = stroke(daq, OFF)
    assert edges(events) == [(B, 0), (A, 1)]
    assert daq.levels() == (1, 0) and daq.position_mm() == 0.0


def test_stroke_in_motion_and_bad_arguments_raise(daq):
    daq.arm(ON, 0)
    daq.command()
    daq.recv(0)  # START; the mover is still on its way
    daq.arm(OFF, 0)
    with pytest.raises(DaqError, match="in motion"):
        daq.command()
    with pytest.raises(ValueError, match="delay_ns"):
        daq.arm(ON, -1)
    with pytest.raises(ValueError, match="delay_ns"):
        daq.arm(ON, 1.5)
    with pytest.raises(ValueError):
        daq.arm(7, 0)
    with pytest.raises(ValueError, match="timeout_ns"):
        daq.recv(-3)


def test_command_without_arm_raises_and_arming_is_one_shot(daq):
    with pytest.raises(DaqError, match="without an armed stroke"):
        daq.command()
    daq.arm(ON, 0)
    assert daq.armed == (ON, 0)
    daq.command()
    assert daq.armed is None
    drain(daq)
    with pytest.raises(DaqError, match="without an armed stroke"):
        daq.command()


def test_closed_driver_refuses_use():
    daq = SimDaq()
    daq.arm(ON, 0)
    with pytest.raises(DaqError, match="closed"):
        daq.command()
    with pytest.raises(DaqError, match="closed"):
        daq.conditions()
    assert not daq.ping()
    with daq:
        assert daq.ping()
    assert not daq.is_open
    daq.close()  # twice is fine


def test_same_seed_same_event_stream_bit_for_bit():
    faults = {"probability": {"bounce": 0.2, "spurious": 0.1, "missed": 0.05}}

    def stream(seed: int) -> list[Event]:
        d = SimDaq(seed=seed, faults=faults, debounce_ns=0)
        d.open()
        out = []
        direction = ON
        for k in range(300):
            d.arm(direction, 1_000_000 + 1000 * (k % 7))
            d.command()
            out.extend(drain(d, 15_000_000))
            d.stop()  # after a missed arrival too
            direction = Direction(int(d.levels()[B]))  # away from where the mover rests
        return out

    a, b = stream(42), stream(42)
    assert a == b
    assert len(a) > 1200
    assert stream(43) != a


def test_conditions_and_drive_settings(daq):
    c = daq.conditions()
    assert isinstance(c, Conditions)
    assert (c.temperature_c, c.frequency_hz, c.voltage_vpp) == (25.0, 40_000.0, 500.0)
    t_fast = stroke(daq, ON)[-1].t_ns
    daq.set_drive(frequency_hz=41_500.0, voltage_vpp=400.0)
    assert daq.conditions().frequency_hz == 41_500.0 and daq.conditions().voltage_vpp == 400.0
    t0 = daq.now_ns()
    events = stroke(daq, OFF)
    start = next(ev.t_ns for ev in events if ev.kind is EventKind.START)
    assert events[-1].t_ns - start > 1.4 * t_fast  # 25 % slower speed, and 20 % less voltage
    assert start == t0
    assert daq.conditions().temperature_c > 25.0  # two strokes of heat
    with pytest.raises(ValueError, match="frequency_hz"):
        daq.set_drive(frequency_hz=50_000.0)


def test_wrong_direction_pushes_against_the_end_stop(daq):
    # The mover rests on A: an "off" stroke has nowhere to go. No edges, like a stall.
    daq.arm(OFF, 0)
    daq.command()
    events = drain(daq, 50_000_000)
    assert [ev.kind for ev in events] == [EventKind.START]
    assert daq.levels() == (1, 0)
    t_hot = daq.conditions().temperature_c
    assert t_hot > 25.0  # the drive is on and heats while it pushes
    daq.arm(ON, 0)
    with pytest.raises(DaqError, match="still on"):
        daq.command()
    daq.stop("timeout")
    stop = daq.recv(0)
    assert stop.kind is EventKind.STOP and stop.detail == "timeout"
    assert edges(stroke(daq, ON)) == [(A, 0), (B, 1)]


def test_stall_then_stop_leaves_the_mover_between_sensors(daq):
    daq.inject("stall")
    daq.arm(ON, 0)
    cmd = daq.command()
    events = drain(daq, 40_000_000)
    assert edges(events) == [(A, 0)]  # departed, never arrived
    assert daq.last_faults == ("stall",) and daq.fault_counts["stall"] == 1
    daq.stop("stall")
    assert daq.recv(0).kind is EventKind.STOP
    assert daq.levels() == (0, 0)
    x = daq.position_mm()
    p = daq.model.params
    assert p.stall_fraction_min * 5.0 <= x <= p.stall_fraction_max * 5.0
    # From mid-way either direction works: no depart edge, a shorter trip.
    daq.arm(OFF, 0)
    cmd = daq.command()
    events = drain(daq)
    assert edges(events) == [(A, 1)]
    assert events[-1].t_ns - cmd.t_start_ns < 0.9 * 10_000_000
    assert daq.position_mm() == 0.0 and daq.levels() == (1, 0)


def test_stop_mid_stroke_cuts_the_motion(daq):
    daq.arm(ON, 0)
    cmd = daq.command()
    assert daq.recv(0).kind is EventKind.START
    assert daq.recv(None).channel == A  # departed
    daq.clock.advance(3_000_000)
    daq.stop()
    assert daq.recv(0).kind is EventKind.STOP
    assert daq.recv(20_000_000) is None  # the arrival was cancelled with the drive
    assert 0.5 < daq.position_mm() < 4.5
    assert cmd.t_start_ns is not None


def test_bounce_is_debounced_by_the_base_and_visible_without_it():
    daq = SimDaq(seed=1, faults={"schedule": {"0": "bounce"}})
    daq.open()
    events = stroke(daq, ON)
    assert edges(events) == [(A, 0), (B, 1)]
    assert daq.bounces == 1 and daq.fault_counts["bounce"] == 1
    clean = SimDaq(seed=1)
    clean.open()
    # The delivered arrival keeps the stamp of the first transition: chatter costs no accuracy.
    assert events[-1].t_ns == stroke(clean, ON)[-1].t_ns

    raw = SimDaq(seed=1, faults={"schedule": {0: ["bounce"]}}, debounce_ns=0)
    raw.open()
    events = [ev for ev in stroke(raw, ON) if ev.kind is EventKind.EDGE]
    chatter = events[1:]
    assert len(chatter) >= 3 and len(chatter) % 2 == 1
    assert all(ev.channel == B for ev in chatter)
    assert [ev.level for ev in chatter] == [1, 0] * (len(chatter) // 2) + [1]  # settles active
    assert chatter[-1].t_ns - chatter[0].t_ns < raw.model.params.bounce_gap_max_ns * len(chatter)
    assert chatter[-1].t_ns - chatter[0].t_ns < 100_000  # inside the default debounce
    assert raw.bounces == 0 and raw.glitches == 0


def test_missed_edges(daq):
    daq.inject("missed", edge="arrive")
    assert edges(stroke(daq, ON)) == [(A, 0)]  # looks like a stall to the controller ...
    assert daq.levels() == (0, 1)  # ... but the mover did arrive and the limit cut the drive
    daq.stop()
    daq.recv(0)
    daq.inject("missed", edge="depart")
    assert edges(stroke(daq, OFF)) == [(A, 1)]
    assert daq.fault_counts["missed"] == 2
    with pytest.raises(ValueError, match="edge"):
        daq.inject("stall", edge="arrive")
    with pytest.raises(ValueError, match="edge"):
        daq.inject("missed", edge="middle")


def test_spurious_glitch():
    raw = SimDaq(seed=5, debounce_ns=0)
    raw.open()
    raw.inject("spurious", count=2)
    twin = SimDaq(seed=5, debounce_ns=0)  # same physics: faults draw from their own generator
    twin.open()
    widths = []
    for direction in (ON, OFF):
        got = [ev for ev in stroke(raw, direction) if ev.kind is EventKind.EDGE]
        real = [ev for ev in stroke(twin, direction) if ev.kind is EventKind.EDGE]
        assert len(real) == 2 and len(got) == 4  # depart, arrive, and a glitch pair
        assert all(ev in got for ev in real)
        g1, g2 = (ev for ev in got if ev not in real)
        assert g1.channel == g2.channel and g1.level == 1 - g2.level
        widths.append(g2.t_ns - g1.t_ns)
    p = raw.model.params
    assert all(p.glitch_width_min_ns <= w <= p.glitch_width_max_ns for w in widths)
    assert raw.fault_counts["spurious"] == 2
    # Through the settle debounce a short pulse is dropped and counted; a long one gets through.
    seen = {"short": 0, "long": 0}
    daq = SimDaq(seed=5)
    daq.open()
    direction = ON
    for _ in range(40):
        daq.inject("spurious")
        n = len(edges(stroke(daq, direction)))
        seen["short" if n == 2 else "long"] += 1
        assert n in (2, 4)
        direction = direction.opposite
    # A pulse that meets a real edge merges with it (chatter, counted as a bounce), not a glitch.
    assert daq.glitches + daq.bounces == seen["short"] > 5 and seen["long"] > 5


def test_scheduled_disconnect_mid_stroke_and_reconnect():
    daq = SimDaq(seed=2, faults={"schedule": {"1": "disconnect"}})
    daq.open()
    stroke(daq, ON)
    daq.arm(OFF, 0)
    cmd = daq.command()
    events = []
    with pytest.raises(DaqDisconnected):
        while True:
            events.append(daq.recv(30_000_000))
    fault = events[-1]
    assert fault.kind is EventKind.FAULT and fault.fault is FaultCode.DISCONNECT
    assert cmd.t_start_ns < fault.t_ns
    assert not any(ev.kind is EventKind.EDGE and ev.t_ns > fault.t_ns for ev in events)
    assert not daq.ping()
    for use in (daq.conditions, lambda: daq.set_drive(voltage_vpp=450.0)):
        with pytest.raises(DaqDisconnected):
            use()
    daq.arm(ON, 0)
    with pytest.raises(DaqDisconnected):
        daq.command()
    daq.stop()  # harmless: the device's drive is already off
    daq.open()  # reconnect
    assert daq.ping()
    # The unplug came before the arrival: wherever it left the mover, "off" brings it to A.
    assert daq.levels()[A] == 0
    events = stroke(daq, OFF)
    assert edges(events)[-1] == (A, 1)
    assert daq.levels() == (1, 0)


def test_runtime_disconnect_and_clear_faults(daq):
    daq.arm(ON, 0)
    daq.command()
    daq.inject("disconnect")
    start = daq.recv(0)
    fault = daq.recv(0)
    assert start.kind is EventKind.START
    assert fault.kind is EventKind.FAULT and fault.fault is FaultCode.DISCONNECT
    with pytest.raises(DaqDisconnected):
        daq.recv(0)
    with pytest.raises(DaqDisconnected):
        daq.inject("disconnect")
    daq.open()
    assert daq.levels() == (1, 0)  # unplugged during the dead time: never moved
    daq.set_fault_probability("stall", 1.0)
    daq.inject("bounce", count=3)
    daq.clear_faults()
    assert edges(stroke(daq, ON)) == [(A, 0), (B, 1)]
    assert daq.last_faults == ()


def test_fault_probabilities_apply_per_stroke():
    daq = SimDaq(seed=3, faults={"probability": {"bounce": 0.5}})
    daq.open()
    direction = ON
    for _ in range(200):
        stroke(daq, direction)
        direction = direction.opposite
    assert 60 <= daq.fault_counts["bounce"] <= 140
    with pytest.raises(ValueError, match="probability"):
        daq.set_fault_probability("bounce", 1.5)
    with pytest.raises(ValueError, match="unknown fault"):
        daq.set_fault_probability("fire", 0.1)


def test_fault_plan_from_toml_and_bad_configs():
    doc = tomllib.loads(
        """
        [faults.probability]
        bounce = 0.01
        spurious = 0
        [faults.schedule]
        12 = ["stall", "bounce"]
        40 = "disconnect"
        """
    )
    plan = FaultPlan.from_config(doc["faults"])
    assert plan.probability == {"bounce": 0.01, "spurious": 0.0}
    assert plan.schedule == {12: ("stall", "bounce"), 40: ("disconnect",)}
    bad = [
        ({"probabilities": {}}, "unknown key"),
        ({"probability": {"stall": 2}}, "faults.probability.stall"),
        ({"probability": {"stall": True}}, "faults.probability.stall"),
        ({"probability": {"fire": 0.1}}, "unknown fault 'fire'"),
        ({"schedule": {"x": "stall"}}, "stroke number"),
        ({"schedule": {-1: "stall"}}, ">= 0"),
        ({"schedule": {"3": []}}, "faults.schedule.3"),
        ({"schedule": {"3": ["melt"]}}, "faults.schedule.3: unknown fault 'melt'"),
        ({"schedule": ["3"]}, "faults.schedule must be a table"),
        ("stall", "must be a table"),
    ]
    for config, match in bad:
        with pytest.raises(ValueError, match=match):
            FaultPlan.from_config(config)
    with pytest.raises(ValueError, match="unknown fault"):
        SimDaq(faults={"schedule": {"1": "melt"}})


def test_base_order_check_reports_a_sequence_fault(daq):
    events = stroke(daq, ON)
    # A driver-pushed event stamped before the last delivered one is dropped and reported.
    daq._push(Event.edge(events[0].t_ns, A, 1))
    ev = daq.recv(0)
    assert ev.kind is EventKind.FAULT and ev.fault is FaultCode.SEQUENCE
    assert daq.out_of_order == 1
    assert edges(stroke(daq, OFF)) == [(B, 0), (A, 1)]


def test_clock_and_realtime_flag_must_agree():
    with pytest.raises(ValueError, match="realtime"):
        SimDaq(realtime=True, clock=VirtualClock())
    with pytest.raises(ValueError, match="realtime"):
        SimDaq(clock=MonotonicClock())
    with pytest.raises(ValueError, match="seed"):
        SimDaq(seed="7")
    with pytest.raises(TypeError, match="UsmSwitchModel"):
        SimDaq(model=object())
    shared = VirtualClock(start_ns=123)
    d = SimDaq(clock=shared)
    assert d.now_ns() == 123


def test_a_command_after_a_halt_is_refused_as_halted_naming_its_reason() -> None:
    """An estop disarms: the loop's command then was refused as unarmed ("command without an armed
    stroke"), and the run ended 'fault: command failed: ...' where the estop had ended it (about one
    estop in 150-300 mid-cycle, `make bench BENCH=abuse`)."""
    daq = SimDaq(seed=1)
    daq.open()
    daq.arm(ON, 1_000_000)
    daq.halt("estop (estop socket)")
    with pytest.raises(DaqHalted, match=r"halted \(estop \(estop socket\)\)"):
        daq.command()
    daq.close()
