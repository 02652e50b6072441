"""A fault-injecting fake MCU: the firmware emulator with a hand on its transmit side.

It speaks docs/mcu-protocol.md as `McuEmulator` does, over a pty (`PtyLink`), and every frame it
sends is valid (COBS, CRC, the firmware's own sequence numbers): what it injects is what a confused
device or a noisy line that happens to pass the CRC would say. `tamper` rewrites each frame the
firmware sends into any list of frames; `say` sends one more now; `flood` sends EDGE frames in a
window as fast as the host reads them; `chatter` sends a sensor's edges at a given spacing for a
while (a line ringing); `later` sends a frame at a later instant of the device; `latency_ns` delays
every frame on the line (a USB-serial adapter's latency timer) and `trickle` sends the next frames a
byte at a time, both in order; `jump_clock` moves the device
clock without a restart. Importable from any test (tests/conftest.py puts this folder on sys.path).
"""

from __future__ import annotations

import array
import contextlib
import fcntl
import termios
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from usmswitch.drivers.mcu_protocol import Edge, Message, Start, Stroke
from usmswitch.sim.mcu_emulator import McuEmulator, PtyLink

Tamper = Callable[[Message], list[Message]]

#: A flood writes its next chunk only when the host has fewer bytes than this left unread.
_MAX_UNREAD = 1024


class FaultyMcu(McuEmulator):
    """`McuEmulator` whose outgoing frames pass through `tamper` (None: sent as the firmware says)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.tamper: Tamper | None = None
        #: Frames `tamper` replaced, and frames sent by say/flood.
        self.tampered = 0
        self.said = 0
        #: Every frame reaches the host this much later (in order).
        self.latency_ns = 0
        self._trickle_frames = 0
        self._trickle_byte_ns = 0
        self._line_busy_ns = 0
        #: The next stroke's start fires this much after its instant, and says it was on time.
        self.fire_late_ns = 0
        #: Every ARM is refused with this status (None: the firmware decides).
        self.refuse_arms: int | None = None
        #: The device instant the firmware thread is handling (None: between two), which a busy
        #: host lets fall behind the wall clock.
        self._instant_ns: int | None = None
        #: The pty this device is behind (set by plug), whose unread bytes pace a flood.
        self.link: PtyLink | None = None

    def _send(self, msg: Message) -> None:
        tamper = self.tamper
        if tamper is None:
            super()._send(msg)
            return
        out = tamper(msg)
        if out != [msg]:
            self.tampered += 1
        for m in out:
            super()._send(m)

    def _put_raw(self, data: bytes) -> None:
        now = time.monotonic_ns()
        if not self.latency_ns and not self._trickle_frames and self._line_busy_ns <= now:
            super()._put_raw(data)
            return
        # The line's model: frames leave in order, each after the one before it is out.
        if self._trickle_frames:
            self._trickle_frames -= 1
            for i in range(len(data)):
                due = max(now + self.latency_ns, self._line_busy_ns) + self._trickle_byte_ns
                self._line_busy_ns = due
                self._at(due, lambda b=data[i : i + 1]: McuEmulator._put_raw(self, b))
            return
        due = max(now + self.latency_ns, self._line_busy_ns)
        self._line_busy_ns = due
        self._at(due, lambda: McuEmulator._put_raw(self, data))

    def _at(self, t_ns: int, fn: Callable[[], None]) -> None:
        def at_instant() -> None:
            before, self._instant_ns = self._instant_ns, t_ns
            try:
                fn()
            finally:
                self._instant_ns = before

        super()._at(t_ns, at_instant)

    def _take(self, data: bytes, t_ns: int) -> None:
        before, self._instant_ns = self._instant_ns, t_ns
        try:
            super()._take(data, t_ns)
        finally:
            self._instant_ns = before

    def instant_ns(self) -> int:
        """The device's present instant: in the firmware's thread (a tamper), the instant it is
        handling, however late that thread runs; elsewhere, now."""
        return time.monotonic_ns() if self._instant_ns is None else self._instant_ns

    def _fire(self, st: object, due_ns: int, gen: int) -> None:
        off, self.fire_late_ns = self.fire_late_ns, 0
        if off > 0:  # the timer fires late, and the firmware believes it on time
            self._at(due_ns + off, lambda: McuEmulator._fire(self, st, due_ns + off, gen))  # type: ignore[arg-type]
            return
        super()._fire(st, due_ns, gen)  # type: ignore[arg-type]

    def _on_arm(self, seq: int, msg: object, now: int) -> None:
        status = self.refuse_arms
        if status is None:
            super()._on_arm(seq, msg, now)  # type: ignore[arg-type]
            return
        self._ack(msg, seq, status, msg.stroke, now)  # type: ignore[arg-type, attr-defined]

    def behave(self) -> None:
        """From now on the device and its line behave: every pending injection is cleared."""
        with self._lock:
            self.tamper = None
            self.fire_late_ns = 0
            self.refuse_arms = None
            self.latency_ns = 0
            self._trickle_frames = 0
            self._drop_next = self._corrupt_next = self._delay_next = self._rx_drop_next = 0
            self._drop_only = self._corrupt_only = None

    def trickle(self, frames: int, byte_ns: int) -> None:
        """Send the next `frames` frames one byte every `byte_ns` (and what follows after them)."""
        with self._lock:
            self._trickle_frames = frames
            self._trickle_byte_ns = byte_ns

    def jump_clock(self, by_us: int) -> None:
        """Move the device clock by `by_us` at once, in session, without a restart or a BOOT."""
        with self._lock:
            self.clock_start_us = (self.clock_start_us + by_us) % (1 << 32)

    def restart_clock(self) -> None:
        """The device clock starts again from clock_start_us, in session, without a BOOT."""
        with self._lock:
            self._t_boot_ns = time.monotonic_ns()

    def ring(self, channel: int, after_ns: int, spacing_ns: int, duration_ns: int) -> None:
        """Edges of `channel` from `after_ns` after the device's present instant, every `spacing_ns`
        for `duration_ns`, on the firmware's own timers, alternating from the level the sensor will
        not have then, each stamped and ordered at the instant it falls due. Called from a tamper,
        the present instant is the one the firmware is handling (a START's), not the wall clock:
        the emulator's thread, late on a busy host, is not the chip (woken 10 ms late, the ringing
        meant to start 2 ms into a stroke started after its arrival, and no NOISE was seen)."""
        with self._lock:
            t0 = self.instant_ns() + after_ns
            for i in range(max(1, duration_ns // spacing_ns)):
                t = t0 + i * spacing_ns

                def edge(i: int = i, t: int = t) -> None:
                    level = int(self.rig.sensors(t)[channel])
                    self.said += 1
                    McuEmulator._send(
                        self, Edge(channel, 1 - level if i % 2 == 0 else level, self.device_us(t))
                    )

                self._at(t, edge)

    def later(self, after_ns: int, msg: Callable[[int], Message]) -> None:
        """Send `msg(stamp_us)` `after_ns` after the device's present instant (a tamper's: the one
        the firmware is handling), on the firmware's own timers, stamped and numbered then, as a
        device sends a frame at its instant and never ahead of it. Sent at once, a frame stamped
        6 ms ahead fell outside the band the host believes when its clock was behind the device by
        its whole uncertainty (loaded run 26: an edge dropped as ahead of the device clock)."""
        with self._lock:
            t = self.instant_ns() + after_ns

            def send() -> None:
                self.said += 1
                McuEmulator._send(self, msg(self.device_us(t)))

            self._at(t, send)

    def chatter(self, channel: int, spacing_ns: int, duration_ns: int) -> threading.Thread:
        """Edges of `channel`, alternating from the level it does not have now, every `spacing_ns`
        for `duration_ns`, each stamped when sent (a line ringing): returns the sending thread."""

        def run() -> None:
            end = time.monotonic_ns() + duration_ns
            level = 1 - int(self.rig.sensors()[channel])
            while time.monotonic_ns() < end:
                with self._lock:
                    self.said += 1
                    McuEmulator._send(self, Edge(channel, level, self.device_us()))
                level ^= 1
                time.sleep(spacing_ns / 1e9)

        t = threading.Thread(target=run, daemon=True)
        t.start()
        return t

    def say(self, msg: Message) -> None:
        """Send `msg` now, numbered in the firmware's sequence."""
        with self._lock:
            self.said += 1
            super()._send(msg)

    def flood(
        self, duration_s: float, channel: int = 0, frames: int | None = None, *, at_ns: int | None = None
    ) -> int:
        """EDGE frames of `channel`, each repeating its present level (a chattering report), stamped
        as sent, as fast as the host reads them for `duration_s` from `at_ns` (a host monotonic
        instant, now if None; waited for if ahead), or until `frames` are sent; returns how many were
        sent. The window is the device's: a thread that starts late floods less, never later, and no
        more than a chunk waits on the line unread, so the last frame reaches the host about the
        window's end (a pty holds tens of kB: a host reading slower than the flood writes would
        otherwise get the last frames after the window)."""
        start = time.monotonic_ns() if at_ns is None else at_ns
        end = start + int(duration_s * 1e9)
        while (now := time.monotonic_ns()) < start:
            time.sleep(min(0.01, (start - now) / 1e9))
        n = 0
        while time.monotonic_ns() < end and (frames is None or n < frames):
            if self._unread() > _MAX_UNREAD:
                time.sleep(0.0005)
                continue
            with self._lock:
                level = None
                for _ in range(200 if frames is None else min(200, frames - n)):
                    now = time.monotonic_ns()
                    if now >= end:
                        break
                    if level is None or self._rx or (self._timers and self._timers[0][0] <= now):
                        # The bytes received by now and what they and the timers make due (a START,
                        # a FAULT, a STOP) leave before this edge: a COMMAND the firmware's thread
                        # had not yet taken, starved beside a busy host's work, once started its
                        # stroke after 77 ms of edges and its FAULT went out stamped before them.
                        self._catch_up()
                        now = time.monotonic_ns()
                        level = self.rig.sensors(now)[channel]
                    super()._send(Edge(channel, int(level), self.device_us(now)))
                    n += 1
        self.said += n
        return n

    def _unread(self) -> int:
        """Bytes on the line the host has not read yet (0 when no pty is known)."""
        link = self.link
        fd = -1 if link is None else link._slave
        if fd < 0:
            return 0
        buf = array.array("i", [0])
        try:
            fcntl.ioctl(fd, termios.FIONREAD, buf)
        except OSError:
            return 0
        return buf[0]


def start_of_stroke(k: int, make: Callable[[Start], list[Message]]) -> Tamper:
    """A tamper that rewrites the k-th START the firmware sends (1-based) with `make`."""
    seen = [0]
    lock = threading.Lock()

    def tamper(msg: Message) -> list[Message]:
        if isinstance(msg, Start):
            with lock:
                seen[0] += 1
                if seen[0] == k:
                    return make(msg)
        return [msg]

    return tamper


def drop_report_of(stroke_ids: set[int], inner: Tamper | None = None) -> Tamper:
    """A tamper that drops the STROKE report of the given stroke ids (after `inner`)."""

    def tamper(msg: Message) -> list[Message]:
        out = inner(msg) if inner is not None else [msg]
        return [m for m in out if not (isinstance(m, Stroke) and m.stroke in stroke_ids)]

    return tamper


def plug(tmp_path: Path, **kwargs: object) -> tuple[FaultyMcu, PtyLink, Path]:
    """A started FaultyMcu behind a pty whose stable path is tmp_path/usmswitch."""
    emu = FaultyMcu(**kwargs).start()
    path = tmp_path / "usmswitch"
    link = PtyLink(emu, path).plug()
    emu.link = link
    return emu, link, path


@contextlib.contextmanager
def plugged(tmp_path: Path, **kwargs: object) -> Iterator[tuple[FaultyMcu, Path]]:
    """plug(), then the pty closed and the emulator stopped on the way out (its log stays readable)."""
    emu, link, path = plug(tmp_path, **kwargs)
    try:
        yield emu, path
    finally:
        link.close()
        emu.stop()
