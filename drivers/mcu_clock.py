"""The device's clock as the host keeps it: stamps mapped and checked, heartbeats, rate and jumps.

The driver's clock is the device's timeline mapped onto the host: device stamps (32-bit us,
unwrapped) become `base_ns + (us - base_us) * 1000`, where the base is fixed at each handshake so
the timeline starts near `time.monotonic_ns()` and never goes back across reconnects (a reconnect to
a device whose clock kept counting, where the timeline puts it, keeps the base); `now_ns()` is
`time.monotonic_ns() + offset_ns`, the offset re-estimated from each heartbeat round trip (the
sample with the smallest round trip of the last eight), which tracks the crystals' drift.

Three things can be wrong with a device's clock, and each is told apart from the others:

- a **jump** (the clock restarted, or was set): a PONG far from where the clock should be, and the
  next ones agreeing with it, not with the old clock: the session is handshaken again, at any age;
- a **rate error** (a wrong prescaler, a ceramic resonator far off): PONGs that drift steadily away,
  judged between samples that are not jumps, against the session's best early sample, past both
  round trips, whatever the round trip is: the session is refused, and stays refused until the
  device really restarts (its BOOT, its clock started again, or another firmware);
- a **bad stamp** on one frame: rejected, counted, and it leaves nothing behind.
"""

from __future__ import annotations

import logging
import time

from .mcu_link import DeviceClock, LinkStats
from .mcu_protocol import U32_MOD, HelloAck

log = logging.getLogger(__name__)

#: A device stamp is believed only inside this band around the device clock as the heartbeat tracks
#: it (plus the clock's uncertainty, half the round trip of its best sample): a frame is stamped
#: before it is sent, so never much ahead; and it arrives within the link timeout, so never much
#: behind (a STROKE report's stamps may be as old as the stroke timeout besides).
STAMP_AHEAD_NS = 5_000_000
#: How far the device's clock may run from 1 us per us (a crystal is within 0.01 %, a ceramic
#: resonator 0.5 %); judged over heartbeats, past their round trips.
MAX_CLOCK_RATE_ERROR_PPM = 5_000
#: The rate is judged against the best sample (smallest round trip) of the session's first seconds.
RATE_REF_WINDOW_NS = 2_000_000_000
#: A PONG after a stroke may be this far off (past both round trips and the tolerated drift).
CLOCK_CHECK_NS = 200_000
#: PONGs in a row off the clock before it is judged (a jump, or a rate the tracking cannot follow).
JUMP_SAMPLES = 3
_OFFSET_WINDOW = 8
# A device whose clock at a new handshake is this far from where the last session's clock would
# be now (plus twice the worst round trip seen, and 1000 ppm of the time between) is not the same
# run of the device.
_CLOCK_CONTINUITY_NS = 10_000_000


class DeviceTimeline:
    """One device's clock on the host: the mapping of its stamps and the checks of its PONGs."""

    def __init__(
        self, clock: DeviceClock, stats: LinkStats, *, name: str, heartbeat_ns: int, link_timeout_ns: int
    ) -> None:
        self.clock = clock
        self.stats = stats
        self.name = name
        self.heartbeat_ns = heartbeat_ns
        self.link_timeout_ns = link_timeout_ns
        self.base_us = 0
        self.base_ns = 0
        self.session_wraps = 0
        self.wraps_total = 0
        self._basis = (0, 0)  # (round trip, host instant) of the sample the clock stands on
        self._offsets: list[tuple[int, int, int]] = []
        self._anchor_mid = 0
        self._rate_ref: tuple[int, int, int] | None = None  # (host mid, device ns, round trip)
        self._rate_off = 0
        self._last_good: tuple[int, int, int] | None = (
            None  # (host mid, device ns, rtt) of the last sample taken
        )
        self._off_run: list[tuple[int, int, int]] = []  # (host mid, device ns, rtt) of PONGs not taken
        self._bad_said_ns = -1_000_000_000
        #: Why the device's clock rate was refused ("" if it was not): its handshakes are refused too,
        #: until the device restarts.
        self.rate_refusal = ""
        # The device clock as last heard (raw us, host monotonic ns), to tell a restart at handshake.
        self.heard: tuple[int, int] | None = None

    # -- mapping ------------------------------------------------------------------------------
    def dev_us(self, raw_us: int) -> int:
        """The unwrapped count of a raw 32-bit stamp: the one nearest the device clock now, as the
        heartbeat tracks it. Stateless: no frame moves a reference that later frames are read by."""
        now_us = self.base_us + (self.clock.now_ns() - self.base_ns) // 1000
        d = (raw_us - now_us) % U32_MOD
        if d >= U32_MOD // 2:
            d -= U32_MOD
        return now_us + d

    def dev_ns(self, raw_us: int) -> int:
        """A raw stamp on the driver's clock, unchecked."""
        return self.base_ns + (self.dev_us(raw_us) - self.base_us) * 1000

    def to_raw_us(self, t_ns: int) -> int:
        """An instant of the driver's clock as the device's raw 32-bit microseconds."""
        return (self.base_us + (t_ns - self.base_ns) // 1000) % U32_MOD

    def err_ns(self, now_ns: int) -> int:
        """How far the driver's clock may be from the device's: half the round trip of the sample
        it stands on, and what the worst tolerated crystal drifts since."""
        rtt, t_ns = self._basis
        return rtt // 2 + max(0, now_ns - t_ns) * MAX_CLOCK_RATE_ERROR_PPM // 1_000_000

    def off_text(self, raw_us: int) -> str:
        """Where a stamp lies against the device clock, for messages."""
        off = self.dev_ns(raw_us) - self.clock.now_ns()
        return f"{fmt_ns(abs(off))} {'ahead of' if off > 0 else 'behind'} the device clock"

    def stamp(self, raw_us: int, what: str, behind_ns: int | None = None) -> int | None:
        """A device stamp on the driver's clock, or None when it is not believable: further ahead of
        the device clock than its uncertainty and STAMP_AHEAD_NS, or further behind than the link
        timeout (`behind_ns`). A rejected stamp is counted and logged (once a second), and leaves
        nothing behind."""
        host_now = time.monotonic_ns()
        now = host_now + self.clock.offset_ns
        t = self.dev_ns(raw_us)
        err = self.err_ns(host_now)
        behind = self.link_timeout_ns if behind_ns is None else behind_ns
        if now - behind - err <= t <= now + err + STAMP_AHEAD_NS:
            u = self.dev_us(raw_us)
            if u // U32_MOD > self.session_wraps:
                self.session_wraps = u // U32_MOD
            return t
        self.stats.bad_stamps += 1
        off = t - now
        if host_now - self._bad_said_ns >= 1_000_000_000:
            self._bad_said_ns = host_now
            log.warning(
                "%s: %s stamped %s %s the device clock rejected (%d so far)",
                self.name,
                what,
                fmt_ns(abs(off)),
                "ahead of" if off > 0 else "behind",
                self.stats.bad_stamps,
            )
        return None

    # -- sessions -----------------------------------------------------------------------------
    def resumes(self, raw_us: int, host_mid_ns: int, rtt_ns: int) -> bool:
        """At a reconnect to the same run of the device: is its clock where this timeline puts it,
        within the handshake's own round trip? Then the timeline goes on as it was (True): a
        handshake's midpoint is only as good as its round trip (beside two CPU hogs one took 312 ms,
        and an anchor on it moved the timeline 156 ms), where the mapping the heartbeats refined
        holds for a clock that kept counting. The next PONGs re-estimate the offset afresh."""
        if not self.base_ns:
            return False  # no session before this one
        jump = self.dev_ns(raw_us) - (host_mid_ns + self.clock.offset_ns)
        if abs(jump) > self.err_ns(host_mid_ns) + rtt_ns // 2 + CLOCK_CHECK_NS:
            return False
        self._offsets = []
        self._off_run = []
        return True

    def anchor(self, raw_us: int, host_mid_ns: int, rtt_ns: int, floor_ns: int) -> None:
        """Start a device session's timeline at `host_mid_ns` on the driver clock, never before
        `floor_ns` (the last stamp delivered)."""
        self.wraps_total += self.session_wraps
        self.session_wraps = 0
        self.base_us = raw_us
        self.base_ns = max(host_mid_ns + self.clock.offset_ns, floor_ns)
        self.clock.offset_ns = self.base_ns - host_mid_ns
        self._basis = (rtt_ns, host_mid_ns)
        self._offsets = []
        self._off_run = []
        self._rate_off = 0
        self._anchor_mid = host_mid_ns
        self._rate_ref = (host_mid_ns, self.base_ns, rtt_ns)
        self._last_good = (host_mid_ns, self.base_ns, rtt_ns)

    def restarted(
        self, msg: HelloAck, t_send: int, t_recv: int, *, booted: bool, fw_before: int | None
    ) -> bool:
        """At a handshake: is this another run of the device than the last session's (or the first)?

        Its BOOT said so (`booted`), its firmware is another, or its clock started again: the count
        now is below the time since it was last heard and off where the old run's would be at some
        instant of the round trip (its stamp was taken between the HELLO and the answer's arrival,
        wherever the line or a busy host held either). A clock that merely runs at a wrong rate is
        the same run, whatever its offset has grown to."""
        heard = self.heard
        if booted or heard is None or (fw_before is not None and fw_before != msg.fw_version):
            return True
        elapsed_ns = t_recv - heard[1]
        lo = (heard[0] + (t_send - heard[1]) // 1000) % U32_MOD
        span_us = (t_recv - t_send) // 1000
        past_lo = (msg.t_us - lo + U32_MOD // 2) % U32_MOD - U32_MOD // 2
        off_ns = 1000 * (-past_lo if past_lo < 0 else max(0, past_lo - span_us))
        slack_ns = _CLOCK_CONTINUITY_NS + 2 * self.stats.max_rtt_ns + elapsed_ns // 1000
        if off_ns <= slack_ns:
            return False  # the same run of the device (a reconnect)
        if self.rate_refusal:
            # Refused for its rate: only a count that started again (younger than the silence) is a
            # restart; a drifting clock's offset grows with every reconnect and proves nothing.
            return msg.t_us * 1000 <= elapsed_ns + slack_ns
        return True

    # -- heartbeats -----------------------------------------------------------------------------
    def sample(self, raw_us: int, t_send_ns: int, t_recv_ns: int) -> tuple[str, str]:
        """A PONG: the device clock at the round trip's middle. Returns ("", "") when all is well,
        ("refuse", why) for a clock rate the host cannot time strokes on, ("resync", why) for a clock
        that jumped.

        A sample that agrees with the clock (within its uncertainty, both round trips and
        STAMP_AHEAD_NS) is taken. One that does not is held: three in a row that agree with each
        other at 1 us per us are a jump; three that drift apart are a rate the tracking cannot
        follow. The rate is judged on the samples taken, against the best sample of the session's
        first seconds, past both round trips."""
        rtt = t_recv_ns - t_send_ns
        mid = (t_send_ns + t_recv_ns) // 2
        dev = self.dev_ns(raw_us)
        off = dev - mid
        jump = off - self.clock.offset_ns
        if abs(jump) > self.err_ns(t_recv_ns) + rtt // 2 + STAMP_AHEAD_NS:
            return self._off_clock(mid, dev, rtt, jump)
        self._off_run = []
        verdict = self._judge_rate(mid, dev, rtt)
        if verdict:
            return "refuse", verdict
        self.stats.last_rtt_ns = rtt
        self.stats.max_rtt_ns = max(self.stats.max_rtt_ns, rtt)
        ref = self._rate_ref
        if ref is not None and rtt < ref[2] and mid - self._anchor_mid <= RATE_REF_WINDOW_NS:
            self._rate_ref = (mid, dev, rtt)  # a better reference while the session is young
        u = self.dev_us(raw_us)
        self.session_wraps = max(self.session_wraps, u // U32_MOD)
        self._offsets.append((rtt, off, mid))
        if len(self._offsets) > _OFFSET_WINDOW:
            del self._offsets[0]
        best = min(self._offsets)
        self.clock.offset_ns = best[1]
        self._basis = (best[0], best[2])
        self._last_good = (mid, dev, rtt)
        return "", ""

    def check(self, raw_us: int, t_send_ns: int, t_recv_ns: int) -> str:
        """A PONG asked for at a stroke's end: is the device clock where the last sample taken puts
        it (within both round trips and the worst tolerated drift since)? A device clock that
        jumped just before a stroke makes all its stamps agree with each other and with the
        commanded instant, while the stroke really ran that much off: only the clock tells.
        Returns "" or what is wrong."""
        last = self._last_good
        if last is None:
            return ""
        rtt = t_recv_ns - t_send_ns
        mid = (t_send_ns + t_recv_ns) // 2
        off = self.dev_ns(raw_us) - (last[1] + (mid - last[0]))
        tol = (rtt + last[2]) // 2 + (mid - last[0]) * MAX_CLOCK_RATE_ERROR_PPM // 1_000_000 + CLOCK_CHECK_NS
        if abs(off) <= tol:
            return ""
        return f"the device clock was {fmt_ns(off)} off the host's at the stroke's end (within {fmt_ns(tol)})"

    def _judge_rate(self, mid: int, dev: int, rtt: int) -> str:
        """Three samples in a row off 1 us per us by more than MAX_CLOCK_RATE_ERROR_PPM past both
        round trips: the refusal's text (kept: the next handshakes are refused with it)."""
        ref = self._rate_ref
        if ref is None or mid - ref[0] < self.heartbeat_ns // 2:
            return ""
        span = mid - ref[0]
        ppm = ((dev - ref[1]) - span) * 1_000_000 // span
        slack_ppm = (ref[2] + rtt) * 1_000_000 // span
        if abs(ppm) <= MAX_CLOCK_RATE_ERROR_PPM + slack_ppm:
            self._rate_off = 0
            return ""
        self._rate_off += 1
        if self._rate_off < JUMP_SAMPLES:
            return ""
        self.rate_refusal = _rate_text(dev - ref[1], span)
        return self.rate_refusal

    def _off_clock(self, mid: int, dev: int, rtt: int, jump: int) -> tuple[str, str]:
        self.stats.bad_stamps += 1
        log.warning("%s: PONG stamped %s off the device clock not taken", self.name, fmt_ns(jump))
        run = self._off_run
        run.append((mid, dev, rtt))
        if len(run) < JUMP_SAMPLES:
            return "", ""
        self._off_run = []
        # A rate the heartbeat cannot follow drifts at one steady slope through the held samples
        # (and off 1 us per us past MAX_CLOCK_RATE_ERROR_PPM); anything else (one step, or two
        # jumps in a row) is a clock that jumped: handshaken again, and judged afresh.
        (m0, d0, r0), (m1, d1, r1), (m2, d2, r2) = run[0], run[len(run) // 2], run[-1]
        slack = r0 + r1 + r2 + STAMP_AHEAD_NS // 5
        drift01 = (d1 - d0) - (m1 - m0)
        drift12 = (d2 - d1) - (m2 - m1)
        steady = abs(drift12 * (m1 - m0) - drift01 * (m2 - m1)) <= slack * max(m2 - m1, m1 - m0)
        fast = abs(drift01 + drift12) > (m2 - m0) * MAX_CLOCK_RATE_ERROR_PPM // 1_000_000 + slack
        if steady and fast:
            self.rate_refusal = _rate_text(d2 - d0, m2 - m0)
            return "refuse", self.rate_refusal
        return "resync", f"its clock jumped by {fmt_ns(jump)}"


def _rate_text(dev_span_ns: int, host_span_ns: int) -> str:
    ppm = (dev_span_ns - host_span_ns) * 1_000_000 // host_span_ns
    return (
        f"the device clock runs at {dev_span_ns / host_span_ns:.6f} us per us ({ppm / 10_000:+.3f} %),"
        f" more than {MAX_CLOCK_RATE_ERROR_PPM / 10_000:.1f} % off: the host cannot time strokes on it"
        " (a wrong timer prescaler or clock source?)"
    )


def fmt_ns(ns: int) -> str:
    """Nanoseconds for people, as usmswitch.protocol.units.format_ns writes them: "12.000 ms", "95.3 us"."""
    sign = "-" if ns < 0 else ""
    mag = abs(ns)
    if mag < 1_000:
        return f"{sign}{mag} ns"
    if mag < 999_950:
        return f"{sign}{mag / 1e3:.1f} us"
    if mag < 999_999_500:
        return f"{sign}{mag / 1e6:.3f} ms"
    return f"{sign}{mag / 1e9:.6f} s"
