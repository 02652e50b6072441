"""Issue 29, the driver side, through the daemon process: `usmswitchd --driver serial` on a fake MCU
(tests/faultmcu.py) that speaks docs/mcu-protocol.md with valid CRCs and says what a confused device
or a noisy line would: stamps off its clock, STARTs of other strokes, a longest delay it cannot
honour, floods of edges."""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from pathlib import Path

import daemonproc
import faultmcu
import mcudaemon
import pytest
from mcudaemon import daemon, run

from usmswitch.drivers.mcu import MAX_QUEUED_EVENTS
from usmswitch.drivers.mcu_protocol import U32_MOD, Edge, Message, Start, Stopped, Stroke

MS = 1_000_000
FAULT = 16  # Flag.FAULT
STALL = 2  # Flag.STALL

pytestmark = pytest.mark.realtime


def rows(tmp_path: Path) -> list[tuple[int, int, int | None, int | None, int | None]]:
    return [(r.cycle, r.flags, r.t_start_ns, r.t_arrive_ns, r.operating_ns) for r in mcudaemon.rows(tmp_path)]


def test_stamps_off_the_device_clock_are_rejected_and_outlive_nothing(tmp_path: Path) -> None:
    """Item 1: two edges each 2^31 - 1 us ahead of the one before had moved the 32-bit unwrap's
    reference a whole wrap (71.6 min) ahead, so every later stamp was 'from the future' and every
    stroke stalled; an edge stamped 1 s behind during a stroke ended it as 'edge order'. Now each is
    rejected against the device clock, counted, and the 20 strokes after them are clean."""
    with faultmcu.plugged(tmp_path, seed=7) as (emu, port), daemon(tmp_path, port) as (c, _):
        now = emu.device_us()
        for ahead in (2**31 - 1, 2**32 - 2, 10_000_000):  # while idle
            emu.say(Edge(1, 0, (now + ahead) % U32_MOD))
        time.sleep(0.2)

        def behind(s: Start) -> list[Message]:
            return [s, Edge(0, 1, (s.t_us - 1_000_000) % U32_MOD)]

        emu.tamper = faultmcu.start_of_stroke(5, behind)  # during the 5th stroke
        st = run(c, 60 * MS, 20)
    got = rows(tmp_path)
    assert st["state"] == "idle", st["fault"]
    assert len(got) == 20 and not [r for r in got if r[1] & (FAULT | STALL)], got
    # The driver's timeline starts at the host's monotonic clock and stays there: two frames each
    # 2^31 - 1 us ahead had moved it a whole wrap (71.6 min) ahead, the heartbeat following them.
    assert abs(got[-1][3] - time.monotonic_ns()) < 60_000 * MS, got[-1]
    # 2^32 - 2 us ahead is 2 us behind the device clock: believable, and read as such.
    assert st["driver_counters"]["bad_stamps"] == 3


def test_a_start_naming_another_stroke_is_not_this_strokes_start(tmp_path: Path) -> None:
    """Item 2: a START naming another stroke's id was taken as this stroke's start (its stamp 3 ms
    early made the operating time 3 ms long). Now it is rejected and counted: the stroke's own START
    is used; a stroke that gets none ends with FAULT 'edge order' saying so, and after reset_fault the
    strokes go on."""
    with faultmcu.plugged(tmp_path, seed=8) as (emu, port), daemon(tmp_path, port) as (c, _):

        def early_foreign(s: Start) -> list[Message]:
            other = dataclasses.replace(s, stroke=(s.stroke + 7) % 65536, t_us=(s.t_us - 3000) % U32_MOD)
            return [other, s]

        emu.tamper = faultmcu.start_of_stroke(3, early_foreign)
        st = run(c, 60 * MS, 6)
        assert st["state"] == "idle", st["fault"]
        clean = rows(tmp_path)
        true_ns = [s.t_arrive_ns - s.t_start_ns for s in emu.log]

        replaced: set[int] = set()
        starts = [0]

        def foreign_only(msg: Message) -> list[Message]:
            if isinstance(msg, Start):
                starts[0] += 1
                if starts[0] == 2:
                    replaced.add(msg.stroke)
                    return [dataclasses.replace(msg, stroke=(msg.stroke + 7) % 65536)]
            if isinstance(msg, Stroke) and msg.stroke in replaced:
                return []  # and no report to rebuild its start from
            return [msg]

        emu.tamper = foreign_only
        st = run(c, 60 * MS, 4)
        emu.tamper = None
        assert st["state"] == "fault"
        fault = st["fault"]
        c.reset_fault()
        after = run(c, 60 * MS, 4)
    assert len(clean) == 6 and not [r for r in clean if r[1] & FAULT], clean
    assert abs(clean[2][4] - true_ns[2]) < 50_000, (clean[2], true_ns[2])  # its own start, not 3 ms early
    assert fault.startswith("edge order: stroke ") and "has no START of its own" in fault, fault
    assert "a START naming stroke" in fault
    got = rows(tmp_path)
    assert got[7][1] & FAULT and got[7][2] is None  # the second stroke of the run
    assert after["state"] == "idle", (
        after["fault"],
        got[6:],
        [(s.stroke, s.direction, s.t_start_ns, s.t_arrive_ns, s.t_depart_ns) for s in emu.log[6:]],
    )
    assert len(got) == 12 and not [r for r in got[8:] if r[1] & FAULT]
    assert after["driver_counters"]["foreign_starts"] == 2


def test_a_device_that_cannot_delay_as_long_as_the_targets_is_refused(tmp_path: Path) -> None:
    """Item 3: a device whose HELLO_ACK said max_delay_us 100 passed the handshake and then every
    stroke raised ValueError inside the loop ('internal error'). Now the daemon refuses to start,
    naming the device's value and the host's need."""
    with faultmcu.plugged(tmp_path, seed=9, max_delay_us=100) as (emu, port):
        sock = tmp_path / "d.sock"
        args = ["--driver", "serial", "--port", str(port), "--target", "12ms"]
        proc = daemonproc.spawn(daemonproc.daemon_args(tmp_path, *args, sim=False, socket=sock))
        _, err = proc.communicate(timeout=30)
    assert proc.returncode != 0
    text = err.decode()
    assert "delays a start by at most 100.0 us (HELLO_ACK max_delay_us 100)" in text, text[-2000:]
    assert "up to 12.000 ms" in text


def test_a_target_beyond_the_devices_longest_delay_is_refused_at_the_call(tmp_path: Path) -> None:
    """Item 3 (and issue 34 item 8): a target raised past what the device can delay made arm()
    raise ValueError inside the loop ('internal error'); then a fault at the next stroke. Now the
    call itself is refused, naming the device's longest delay, and the rig runs on."""
    from usmswitch.client import TargetUnreachable
    from usmswitch.protocol.wire import InvalidParams

    with (
        faultmcu.plugged(tmp_path, seed=10, max_delay_us=15_000) as (_, port),
        daemon(tmp_path, port) as (c, _),
    ):
        assert run(c, 100 * MS, 2)["state"] == "idle"
        with pytest.raises(TargetUnreachable, match=r"longer than the device.s longest, 15\.000 ms"):
            c.set_target(40 * MS)
        with pytest.raises(InvalidParams, match=r"device.s longest start delay, 15\.000 ms"):
            c.set_mode("open", "20ms")
        st = run(c, 100 * MS, 2)
    assert st["state"] == "idle", st["fault"]
    got = rows(tmp_path)
    assert len(got) == 4 and not [r for r in got if r[1] & FAULT], got


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def test_a_flood_of_valid_edges_is_bounded_between_device_and_loop(tmp_path: Path) -> None:
    """Item 4: between two strokes of a run nothing reads the driver, and its queue grew with every
    valid EDGE frame at line speed (tens of MB a second). Now it holds at most MAX_QUEUED_EVENTS:
    the oldest are dropped and counted, the daemon's memory stays flat and the strokes stay clean."""
    with faultmcu.plugged(tmp_path, seed=11) as (emu, port), daemon(tmp_path, port) as (c, proc):
        run(c, 60 * MS, 2)
        rss0 = _rss_kb(proc.pid)  # type: ignore[attr-defined]
        sent, most = [0], [0]
        peak = [rss0]

        floods: list[threading.Thread] = []

        def flood(t_arrive: int) -> None:
            channel = 1 - int(emu.rig.sensors()[0] == 0)
            gap = emu.flood(1.2, channel=channel, frames=2 * MAX_QUEUED_EVENTS, at_ns=t_arrive + 30 * MS)
            sent[0] += gap
            most[0] = max(most[0], gap)
            peak[0] = max(peak[0], _rss_kb(proc.pid))  # type: ignore[attr-defined]

        def flood_after_each_arrival(msg: Message) -> list[Message]:
            # In the firmware's thread, at the arrival's instant: the flood's window, 30 ms to 1.23 s
            # after it (the next COMMAND goes ~1.5 s after it), is the device's, however late a
            # thread wakes to send it (30 ms after the arrival on the wall clock, a thread woken
            # late flooded into the next stroke: "events lost ... during stroke 4").
            if isinstance(msg, Stopped) and len(floods) < 3:
                floods.append(threading.Thread(target=flood, args=(emu.instant_ns(),), daemon=True))
                floods[-1].start()
            return [msg]

        emu.tamper = flood_after_each_arrival
        st = run(c, 1_500 * MS, 4)
        for t in floods:
            t.join(10)
    got = rows(tmp_path)
    dropped = st["driver_counters"].get("events_dropped")
    print(f"\nflood: {sent[0]} frames, RSS {rss0} kB -> peak {peak[0]} kB, {dropped} dropped")
    assert st["state"] == "idle", st["fault"]
    assert len(got) == 6 and not [r for r in got if r[1] & (FAULT | STALL)], got
    assert peak[0] - rss0 < 20_000, (rss0, peak[0])
    if not dropped and most[0] <= MAX_QUEUED_EVENTS:
        # Between two strokes the flood must outrun the queue for the bound to be seen at all.
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        pytest.xfail(
            f"at most {most[0]} frames between two strokes (load {load}): too few to fill the"
            f" driver's queue of {MAX_QUEUED_EVENTS}"
        )
    assert dropped > 0
