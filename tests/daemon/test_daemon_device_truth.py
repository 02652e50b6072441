"""Issue 34, through the daemon process: `usmswitchd --driver serial` on a fake MCU (tests/faultmcu.py)
over a pty, the emulator's own log as the truth. The device's STROKE report, its sensor levels and
the instant the host commanded are checks on every stroke; a clock jump is a new handshake at any
session age; a refused clock rate stays refused; a watchdog reset is latched whenever it comes; a
stall is declared only once what is in hand and on the line is read, and its cause is named."""

from __future__ import annotations

import dataclasses
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import faultmcu
import pytest
from mcudaemon import (
    DAEMON_LOG,
    FAULT,
    MISMATCH,
    MS,
    NOISE,
    STALL,
    daemon,
    not_clean,
    rows,
    run,
    truth_of,
    untrue_clean,
)

from usmswitch.client import Client
from usmswitch.drivers.mcu_protocol import U32_MOD, Ack, Message, MsgType, Start, Stroke

pytestmark = pytest.mark.realtime

T_NS = 12 * MS


def _on_start(k: int, action: object) -> faultmcu.Tamper:
    """A tamper that calls `action(start)` (in a thread of its own) when the k-th START is sent."""
    return faultmcu.start_of_stroke(
        k, lambda s: (threading.Thread(target=action, args=(s,), daemon=True).start(), [s])[1]
    )


def _wait_resynced(c: Client, timeout_s: float = 20.0) -> None:
    """Until the driver has handshaken a jumped clock away (a new handshake on the open link) and
    the session is back: `resyncs` counts the handshake as it begins (loaded run 27: a reset_fault
    during it was refused, "serial is not connected")."""
    end = time.monotonic() + timeout_s
    while (st := c.status())["driver_counters"]["resyncs"] < 1 or not st["driver_ok"]:
        assert time.monotonic() < end, f"the jump was never handshaken away: {st['driver_counters']}"
        time.sleep(0.05)


def test_destination_chatter_mid_stroke_is_never_a_clean_record(tmp_path: Path) -> None:
    """Item 1: edges on the destination sensor from 2 ms after a start were recorded as a clean
    stroke of 2.7-5.1 ms (true ~8 ms) and the predictor learned it: the next stroke that way came
    5.36 ms late. Now the wire's arrival is held against the device's report: the stroke is kept
    flagged MISMATCH (and NOISE), never learned, the chatter counted per sensor in status, and the
    strokes after it are on time."""
    with faultmcu.plugged(tmp_path, seed=21) as (emu, port):
        rung: list[int] = []

        def ring(s: Start) -> list[Message]:
            dest = 1 if s.direction == 0 else 0
            emu.ring(dest, 2 * MS, 300_000, 30 * MS)
            rung.append(dest)
            return [s]

        with daemon(tmp_path, port) as (c, _):
            assert run(c, 100 * MS, 6)["state"] == "idle"  # the predictors warm
            emu.tamper = faultmcu.start_of_stroke(2, ring)  # the 8th stroke of the daemon's life
            st = run(c, 100 * MS, 10)
    got = rows(tmp_path)
    assert st["state"] == "idle", st["fault"]
    assert rung, "the chatter never started"
    hit = got[7]
    assert hit.flags & MISMATCH and hit.flags & NOISE, hit
    assert not untrue_clean(got, emu.log), untrue_clean(got, emu.log)
    assert sum(st_noise for st_noise in st["noise"].values()) > 0, st["noise"]
    assert st["mismatched_strokes"] >= 1
    # The strokes after it, both ways, are on time: nothing of the chatter was learned. A start
    # late by the host's scheduling (the LATE flag, its lateness: 2.87 ms of a 2.92 ms error beside
    # make test and two CPU hogs) is the loop's, not the prediction's, and is taken out.
    for r in got[8:12]:
        assert r.clean and abs(r.error_ns - (r.lateness_ns or 0)) <= T_NS // 20, (r, got[7])


def test_a_clock_jump_is_a_new_handshake_at_any_session_age(tmp_path: Path) -> None:
    """Item 2: a jump of +70 ms 3 s into a session read as a rate error ("+1.066 %") and the rig was
    locked out; a clock started again without BOOT read "-117 %". Now three PONGs that agree with
    each other and not with the clock are a jump: the host handshakes again, and strokes go on."""
    with faultmcu.plugged(tmp_path, seed=22) as (emu, port), daemon(tmp_path, port) as (c, _):
        time.sleep(1.0)
        emu.jump_clock(70_000)
        time.sleep(1.0)
        st1 = run(c, 60 * MS, 6)
        emu.restart_clock()  # back to 0, in session, no BOOT
        time.sleep(1.0)
        st2 = run(c, 60 * MS, 6)
    got = rows(tmp_path)
    for st in (st1, st2):
        assert st["state"] == "idle", st["fault"]
    counters = st2["driver_counters"]
    assert counters["resyncs"] >= 2 and counters["handshake_failures"] == 0, counters
    assert len(got) == 12 and not not_clean(got), not_clean(got) or got
    assert not untrue_clean(got, emu.log)


def _fault_then_clean_again(c: Any, emu: Any, tamper: Callable[[Start], list[Message]]) -> tuple[Any, Any]:
    """6 strokes with `tamper` on the 3rd's START, then (the link resynced, the fault reset) 4 clean
    ones: the status after each run."""
    emu.tamper = faultmcu.start_of_stroke(3, tamper)
    st = run(c, 100 * MS, 6)
    emu.tamper = None
    _wait_resynced(c)
    c.reset_fault()
    return st, run(c, 100 * MS, 4)


def test_a_clock_jump_mid_stroke_is_named_the_links_not_a_stall(tmp_path: Path) -> None:
    """Item 2: a stroke during which the device clock jumped was recorded STALL though the device
    arrived. Its stamps cannot be believed: the stroke ends with FAULT WIRE, never STALL, and after
    reset_fault the strokes are clean again."""
    with faultmcu.plugged(tmp_path, seed=23) as (emu, port), daemon(tmp_path, port) as (c, _):

        def jump_after(s: Start) -> list[Message]:
            # In the firmware's thread as its START goes out, so its edges are stamped after the
            # jump whatever the load (a thread of its own, descheduled, once jumped after the stroke).
            emu.jump_clock(70_000)
            return [s]

        st, after = _fault_then_clean_again(c, emu, jump_after)
    got = rows(tmp_path)
    assert st["state"] == "fault" and st["fault"].startswith("wire"), st["fault"]
    hit = got[2]
    assert hit.flags & FAULT and not hit.flags & STALL, hit
    # Once in make test at stop 50 (not again in 14 runs alone, 8 of them beside two CPU hogs), a
    # stroke after the reset read "the device reports an arrival whose stamps did not reach the
    # host": said with the link's counters and the daemon's log, to find out why when it comes again.
    log = (tmp_path / DAEMON_LOG).read_text(errors="replace")[-3000:]
    why = (after["fault"], after["driver_counters"], log)
    assert after["state"] == "idle", why
    assert all(r.clean for r in got[3:]) and len(got) == 7, got
    assert not untrue_clean(got, emu.log)


def test_a_clock_jump_just_before_a_start_is_named_the_links_not_the_edge_order(tmp_path: Path) -> None:
    """Issue 37: a device clock that jumped between two strokes (after one's report, before the
    next one's START) made that START's stamp unbelievable, and its STROKE report's too: the stroke
    ended 'edge order: stroke N has no START of its own', as if the device had sent a START of
    another stroke. The order was right; the clock was not: FAULT WIRE, never STALL, and after
    reset_fault the strokes are clean again."""
    with faultmcu.plugged(tmp_path, seed=23) as (emu, port), daemon(tmp_path, port) as (c, _):

        def jump_before(s: Start) -> list[Message]:
            emu.jump_clock(70_000)  # as the firmware fires: the START is stamped on the new clock
            return [dataclasses.replace(s, t_us=(s.t_us + 70_000) % U32_MOD)]

        st, after = _fault_then_clean_again(c, emu, jump_before)
    got = rows(tmp_path)
    assert st["state"] == "fault" and st["fault"].startswith("wire"), st["fault"]
    assert "has no START of its own" in st["fault"] and "ahead of the device clock" in st["fault"]
    hit = got[2]
    assert hit.flags & FAULT and not hit.flags & STALL and hit.t_start_ns is None, hit
    assert after["state"] == "idle", after["fault"]
    assert all(r.clean for r in got[3:]) and len(got) == 7, got
    assert not untrue_clean(got, emu.log)


@pytest.mark.parametrize("drift_ppm", [10_000, -10_000])
def test_a_refused_clock_rate_stays_refused(tmp_path: Path, drift_ppm: int) -> None:
    """Item 3: a device clock 1 % off was refused, then taken again at the next reconnect (the
    restart check read the drift as a restart): 8-20 reconnects a minute. Now the refusal stands
    until the device really restarts."""
    with (
        faultmcu.plugged(tmp_path, seed=24, drift_ppm=drift_ppm) as (_, port),
        daemon(tmp_path, port) as (c, _),
    ):
        end = time.monotonic() + 10
        while c.status()["driver_ok"] and time.monotonic() < end:
            time.sleep(0.1)
        assert not c.status()["driver_ok"], "the rate was never refused"
        first = c.status()["driver_counters"]
        time.sleep(6.0)
        later = c.status()
    assert not later["driver_ok"]
    counters = later["driver_counters"]
    assert counters["reconnects"] == first["reconnects"], (first, counters)
    assert counters["handshake_failures"] > first["handshake_failures"], counters


def test_the_clock_rate_is_judged_through_a_slow_link(tmp_path: Path) -> None:
    """Item 4: with a round trip over 10 ms (a USB-serial adapter's 16 ms latency timer) the rate
    was never judged: +1 % ran on, +5 % made 68 resyncs in 45 s. Now it is judged past both round
    trips whatever they are: refused within seconds; an exact clock behind the same link is not."""
    with faultmcu.plugged(tmp_path, seed=25, drift_ppm=10_000) as (emu, port):
        emu.latency_ns = 16 * MS
        with daemon(tmp_path, port) as (c, _):
            end = time.monotonic() + 15
            while c.status()["driver_ok"] and time.monotonic() < end:
                time.sleep(0.2)
            refused = c.status()
    (tmp_path / "good").mkdir()
    with faultmcu.plugged(tmp_path / "good", seed=26) as (good, gport):
        good.latency_ns = 16 * MS
        with daemon(tmp_path / "good", gport) as (g, _):
            time.sleep(4.0)
            fine = g.status()
            st = run(g, 100 * MS, 4)
    assert not refused["driver_ok"], refused["driver_counters"]
    assert fine["driver_ok"] and fine["driver_counters"]["handshake_failures"] == 0, fine
    assert fine["driver_counters"]["max_rtt_ns"] > 15 * MS
    assert st["state"] == "idle", st["fault"]


def test_a_watchdog_reset_between_strokes_of_a_run_is_latched(tmp_path: Path) -> None:
    """Item 5: a watchdog reset of the MCU between two strokes of a run gave warnings only (the loop
    dropped the fault as stamped before its command): 20 of 20 strokes clean. Now it is latched
    whenever it comes, as it is while idle."""
    with faultmcu.plugged(tmp_path, seed=27) as (emu, port):

        def reset_after_fifth() -> None:
            while emu.strokes_arrived < 5:
                time.sleep(0.001)
            time.sleep(0.03)  # between strokes: the 5th is over, the 6th not yet commanded
            with emu._lock:
                emu._watchdog_reset(time.monotonic_ns())

        with daemon(tmp_path, port) as (c, _):
            t = threading.Thread(target=reset_after_fifth, daemon=True)
            t.start()
            st = run(c, 100 * MS, 20)
            t.join(5)
    assert st["state"] == "fault", "the reset was not latched"
    assert "watchdog" in st["fault"], st["fault"]
    assert len(rows(tmp_path)) < 20


@pytest.mark.parametrize(
    ("name", "rewrite", "stamp_shift_ns"),
    [
        ("late, says on time", None, 0),
        ("early", lambda s: dataclasses.replace(s, t_us=(s.t_us - 3000) % U32_MOD), -3 * MS),
        ("on time, says 5 s late", lambda s: dataclasses.replace(s, late_us=5_000_000), 0),
    ],
)
def test_a_devices_claim_about_its_start_is_checked(
    tmp_path: Path, name: str, rewrite: object, stamp_shift_ns: int
) -> None:
    """Item 6: a START fired 3 ms late that said late_us 0, one 3 ms early, and one on time that
    said 5 s late were believed (clean records 3 ms off; LATE by 5 s). Now the start is held
    against the instant the host commanded: the stroke is flagged MISMATCH, its lateness is the
    host's measure, and the next strokes are clean."""
    with faultmcu.plugged(tmp_path, seed=28) as (emu, port), daemon(tmp_path, port) as (c, _):
        assert run(c, 100 * MS, 4)["state"] == "idle"
        if rewrite is None:
            emu.fire_late_ns = 3 * MS
        else:
            emu.tamper = faultmcu.start_of_stroke(1, lambda s: [rewrite(s)])  # type: ignore[operator]
        st = run(c, 100 * MS, 6)
    got = rows(tmp_path)
    assert st["state"] == "idle", st["fault"]
    hit = got[4]
    assert hit.flags & MISMATCH, (name, hit)
    # Its lateness is the host's measure against its own instant, not the device's claim: what the
    # emulator's start really was against that instant (3 ms for the timer fired late, plus any
    # lateness of a COMMAND a busy host sent after its instant: 1.15 ms beside make test), as
    # its START's stamp says it (3 ms early for the rewritten one). No drift: device us are host us.
    true = emu.log[4]
    true_late_ns = true.t_start_ns - (true.t_cmd_ns + true.delay_us * 1000)
    expected_late_ns = max(0, true_late_ns + stamp_shift_ns)
    assert hit.lateness_ns is not None and abs(hit.lateness_ns - expected_late_ns) < 100_000, (hit, true)
    assert st["driver_counters"]["start_mismatches"] >= 1
    assert not untrue_clean(got, emu.log)
    # The next strokes clean and on time (less a start late by the host's scheduling: its lateness).
    off = [r for r in got[5:] if not (r.clean and abs(r.error_ns - (r.lateness_ns or 0)) <= T_NS // 20)]
    assert not off, (not_clean(got), off)


def test_a_host_pause_after_the_start_is_not_a_stall(tmp_path: Path) -> None:
    """Item 7: a 70 ms pause of the daemon 2 ms after a START (the default stroke timeout is 50 ms)
    was a STALL although the device arrived at ~8 ms: the loop gave up at its deadline without
    reading what had come. Now it reads what is in hand: the stroke is clean and exact."""
    with faultmcu.plugged(tmp_path, seed=29) as (emu, port):
        pid = [0]

        def pause(_s: Start) -> None:
            time.sleep(0.002)
            os.kill(pid[0], signal.SIGSTOP)
            time.sleep(0.07)
            os.kill(pid[0], signal.SIGCONT)

        with daemon(tmp_path, port) as (c, proc):
            pid[0] = proc.pid  # type: ignore[attr-defined]
            emu.tamper = _on_start(3, pause)
            st = run(c, 200 * MS, 5)
    got = rows(tmp_path)
    assert st["state"] == "idle", st["fault"]
    assert len(got) == 5 and not not_clean(got), not_clean(got) or got
    assert not untrue_clean(got, emu.log)


def test_a_slow_frame_is_waited_for_and_lost_ones_are_the_wires_fault(tmp_path: Path) -> None:
    """Item 7: a stroke whose frames trickled in a byte per 10 ms, and one whose arrival and report
    were lost, were both STALL. Now the trickled stroke is read when it comes (clean, exact), and
    the lost one ends with FAULT WIRE (the link), never STALL (the mover)."""
    with faultmcu.plugged(tmp_path, seed=30) as (emu, port), daemon(tmp_path, port) as (c, _):
        emu.tamper = _on_start(2, lambda s: emu.trickle(1, 10 * MS))  # its departure, and all behind it
        st = run(c, 300 * MS, 4)
        assert st["state"] == "idle", st["fault"]

        def lose(msg: Message) -> list[Message]:
            return [] if isinstance(msg, Stroke) or (lose.armed and msg.TYPE is MsgType.EDGE) else [msg]

        lose.armed = False  # type: ignore[attr-defined]

        def arm_loss(s: Start) -> list[Message]:
            lose.armed = True  # type: ignore[attr-defined]
            return [s]

        emu.tamper = lambda m: arm_loss(m) if isinstance(m, Start) else lose(m)
        lost = run(c, 300 * MS, 1)
    got = rows(tmp_path)
    assert len(got) == 5 and all(r.clean for r in got[:4]), got
    assert not untrue_clean(got, emu.log)
    assert lost["state"] == "fault" and lost["fault"].startswith("wire"), lost["fault"]
    assert got[4].flags & FAULT and not got[4].flags & STALL, got[4]


def test_a_command_whose_acks_are_all_lost_is_followed_to_its_end(tmp_path: Path) -> None:
    """Item 7: all three ACKs of a COMMAND lost: the record had no start and a 'command failed'
    fault, though the device started and arrived. Now the stroke's own frames are followed: the
    record is the device's stroke, clean and exact."""
    with faultmcu.plugged(tmp_path, seed=31) as (emu, port):
        drop = [False]
        victim: list[int] = []

        def no_command_acks(msg: Message) -> list[Message]:
            if isinstance(msg, Ack) and msg.acked_type == MsgType.COMMAND:
                if drop[0] and not victim:
                    victim.append(msg.stroke)
                if msg.stroke in victim:
                    return []  # every try's ACK of this one stroke
            return [msg]

        with daemon(tmp_path, port) as (c, _):
            assert run(c, 200 * MS, 2)["state"] == "idle"
            drop[0] = True
            emu.tamper = no_command_acks
            st = run(c, 200 * MS, 3)
    got = rows(tmp_path)
    assert st["state"] == "idle", st["fault"]
    assert st["driver_counters"]["unacked_commands"] == 1
    assert got[2].t_start_ns is not None and got[2].clean, got[2]
    assert not untrue_clean(got, emu.log)
    assert truth_of(got[2], emu.log) is not None


def test_a_device_without_stroke_reports_is_refused(tmp_path: Path) -> None:
    """Item 7: a device without STROKE reports (caps 0x1B) was accepted, and any lost frame was a
    false STALL: nothing could rebuild or check its strokes. The report is now a check on every
    stroke: such a device is refused at the handshake, naming what it lacks."""
    import daemonproc

    from usmswitch.drivers.mcu_protocol import Caps
    from usmswitch.sim.mcu_firmware import ALL_CAPS

    with faultmcu.plugged(tmp_path, seed=32, caps=ALL_CAPS & ~Caps.STROKE_REPORT) as (emu, port):
        args = ["--driver", "serial", "--port", str(port), "--target", "12ms"]
        proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args, sim=False))
        _, err = proc.communicate(timeout=30)
    assert proc.returncode != 0
    assert "STROKE_REPORT" in err.decode(), err.decode()[-2000:]


def test_limits_the_device_states_are_checked_at_the_call(tmp_path: Path) -> None:
    """Item 8: `stroke_timeout` had no upper bound (11 s and 3600 s accepted, then every stroke
    NOT_ARMED, the ARM's ACK never checked; 7200 s an internal ValueError with a traceback), and
    "1h" was an unknown unit. Now the config refuses a stall limit past the device's 10 s, naming
    it (h and min are units), and an ARM the device refuses is a fault that says so."""
    import daemonproc

    with faultmcu.plugged(tmp_path, seed=33) as (emu, port):
        for value in ("11s", "1h", "7200s"):
            cfg = tmp_path / f"c{value}.toml"
            cfg.write_text(f'[control]\nstroke_timeout = "{value}"\n')
            args = ["--driver", "serial", "--port", str(port), "--config", str(cfg)]
            proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args, sim=False))
            _, err = proc.communicate(timeout=30)
            text = err.decode()
            assert proc.returncode == 2, text[-2000:]
            assert "control.stroke_timeout" in text and "longest stall limit, 10.000000 s" in text, text
            assert "Traceback" not in text

        def refuse_after_two(msg: Message) -> list[Message]:
            if isinstance(msg, Stroke) and emu.strokes_started >= 2:
                emu.refuse_arms = 4  # BAD_ARG: a field out of its range, as the device judges
            return [msg]

        with daemon(tmp_path, port, "--target", "12ms") as (c, _):
            emu.tamper = refuse_after_two
            st = run(c, 100 * MS, 5)
    assert st["state"] == "fault"
    assert "device refused ARM stroke" in st["fault"] and "BAD_ARG" in st["fault"], st["fault"]
    assert "stall limit 50.000 ms" in st["fault"], st["fault"]


def test_no_fault_of_the_device_makes_a_clean_record_untrue(tmp_path: Path) -> None:
    """Property-based, over what a device and its line do wrong (chatter on a sensor, a clock jump,
    a watchdog reset, lost and delayed frames, a start fired late), each followed by a few strokes,
    one daemon through every example: no record is ever clean unless its operating time is within
    50 us of the emulator's truth, and once the device behaves the daemon recovers (after a
    reset_fault where one was latched) to strokes that are clean and within 5 % of T.

    A program of faults is drawn whole, then run (hypothesis's stateful engine draws as it runs,
    and a run in real time is never the same twice: it calls that a flaky strategy)."""
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import strategies as st

    then = st.integers(0, 3)
    fault = st.one_of(
        st.tuples(
            st.just("chatter"), st.booleans(), st.integers(50, 2000), st.integers(5, 60), st.integers(1, 3)
        ),
        st.tuples(st.just("jump"), st.sampled_from([-500, -70, 30, 70, 1000]), then),
        st.tuples(st.just("watchdog_reset"), then),
        st.tuples(
            st.just("lose"), st.integers(1, 3), st.sampled_from([None, MsgType.EDGE, MsgType.STROKE]), then
        ),
        # Up to 20 ms: a delayed HELLO_ACK anchors the driver's timeline up to half of it off the
        # host's clock (kept: it never goes back); the truth's pairing follows steps under 15 ms.
        st.tuples(st.just("delay"), st.integers(5, 20), then),
        st.tuples(st.just("fire_late"), st.integers(1, 3)),
    )
    with faultmcu.plugged(tmp_path, seed=34) as (emu, port):
        log: list[str] = []

        def check() -> None:
            bad = untrue_clean(rows(tmp_path), emu.log)
            if bad:
                start = max(i for i, x in enumerate(log) if x.startswith("-- a program"))
                t0 = bad[0][0].t_start_ns
                recs = [
                    (r.cycle, r.flags, (r.t_start_ns - t0) / 1e6, r.operating_ns)
                    for r in rows(tmp_path)[-12:]
                ]
                devs = [(d.stroke, (d.t_start_ns - t0) / 1e6, d.t_arrive_ns) for d in emu.log[-14:]]
                program = "\n".join(log[start:])
                # Once beside make run and two CPU hogs (stop 50's loaded run 51), two records clean
                # of faults 156 ms before the device's own strokes: the link's counters (resyncs,
                # round trips, bad stamps) say whether a handshake anchored the timeline that far off.
                counters = c.status()["driver_counters"]
                raise AssertionError(
                    f"{bad}\nrecords {recs}\ndevice {devs}\nthe link {counters}\nthe program: {program}"
                )

        with daemon(tmp_path, port) as (c, _):
            assert run(c, 100 * MS, 10)["state"] == "idle"  # warm predictors: the 5 % bar is theirs

            def ready() -> dict:
                end = time.monotonic() + 10
                while not (st_ := c.status())["driver_ok"] and time.monotonic() < end:
                    time.sleep(0.05)
                if st_["state"] == "fault":
                    c.reset_fault()
                return c.status()

            def strokes(n: int) -> None:
                if n:
                    try:
                        ready()
                        run(c, 100 * MS, n)
                    except Exception as exc:
                        log.append(f"  refused: {exc}")
                log.append(f"  -> {[(r.cycle, r.flags) for r in rows(tmp_path)[-n:]] if n else ''}")

            def do(step: tuple) -> None:
                log.append(repr(step))
                kind, *args = step
                if kind == "chatter":
                    dest, spacing_us, ms, n = args

                    def ring(s: Start) -> list[Message]:
                        ch = (1 if s.direction == 0 else 0) if dest else s.direction
                        emu.ring(ch, 2 * MS, spacing_us * 1000, ms * MS)
                        return [s]

                    emu.tamper = faultmcu.start_of_stroke(1, ring)
                elif kind == "jump":
                    emu.jump_clock(args[0] * 1000)
                elif kind == "watchdog_reset":
                    with emu._lock:
                        emu._watchdog_reset(time.monotonic_ns())
                elif kind == "lose":
                    emu.inject_drop(args[0], only=args[1])
                elif kind == "delay":
                    emu.inject_delay(args[0] * MS, frames=2)
                elif kind == "fire_late":
                    emu.fire_late_ns = 2 * MS
                strokes(args[-1])
                check()

            @settings(
                max_examples=10,
                deadline=None,
                derandomize=True,
                database=None,
                phases=[Phase.explicit, Phase.generate],  # one daemon in real time: nothing to shrink
                suppress_health_check=list(HealthCheck),
            )
            @given(st.lists(fault, min_size=1, max_size=6))
            def program(steps: list[tuple]) -> None:
                log.append("-- a program")
                for step in steps:
                    do(step)
                log.append("-- the device behaves")
                emu.behave()
                time.sleep(0.5)  # what was injected has passed
                assert ready()["driver_ok"], ("the link never came back", log[-12:])
                before = len(rows(tmp_path))
                st_ = run(c, 100 * MS, 4)
                assert st_["state"] == "idle", (st_["fault"], log[-12:])
                after = rows(tmp_path)[before:]
                assert len(after) == 4 and all(r.clean for r in after), (after, log[-12:])
                # The prediction's error: a start the host's own hiccup made late is LATE, apart.
                assert all(abs(r.error_ns - (r.lateness_ns or 0)) <= T_NS // 20 for r in after[1:]), after
                check()

            program()
