"""The simulated rig's DAQ face: a software-timed `Daq` whose edges come from `UsmSwitchModel`.

The rig as simulated:
- The mover rests at sensor A (x = 0, switch off) or B (x = stroke_mm, switch on). A stroke is
  commanded by `Daq.command`; `_drive` switches the drive on and schedules the stroke's edges:
  the source sensor releases (depart, level 0) once the mover has moved `release_mm`, and the
  destination sensor activates (arrive, level 1) at drive-on + operating time.
- Limit cut: the destination sensor's activation cuts the drive in the rig's wiring (not via the
  DAQ), so the drive is off from the arrival instant and heating stops there. No event marks the
  cut; a `stop()` after arrival is harmless. The cut is edge-triggered: it fires on activation.
- Wrong direction: a stroke toward the sensor the mover already rests on pushes against the end
  stop. Nothing moves and no edge comes: to the controller it looks like a stall, and the drive
  stays on (heating) until `stop()`.
- Stall (injected): the mover departs, then jams part-way (`stall_fraction_*`); no arrival. The
  drive stays on until `stop()`. The USM is self-locking, so after a stop (or any cut mid-stroke)
  the mover stays where it was, between the sensors, both released. The next stroke in either
  direction runs from there: no depart edge (no sensor to release), and it arrives after the
  remaining distance only.
- Disconnect (injected): the device goes away. The drive is off from that instant, a FAULT
  DISCONNECT event is delivered, and then every use (command, recv, conditions, set_drive)
  raises `DaqDisconnected` until `open()` reconnects. `stop()` and `close()` stay harmless:
  a device that is gone has its drive off. The mover keeps its position across a reconnect.

Time: `realtime=False` runs on a `VirtualClock`: `recv` jumps the clock to the next event, or to
its deadline when none is due before it. `realtime=True` runs on a `MonotonicClock` and delivers
each event at its wall-clock instant. The wait is a `threading.Event` wait (no spinning) so that
a `stop()` or `inject()` from another thread wakes a waiting `recv` at once.
"""

from __future__ import annotations

import heapq
import random
import threading

from usmswitch.drivers.clock import Clock, MonotonicClock, VirtualClock
from usmswitch.drivers.daq import DEFAULT_DEBOUNCE_NS, Daq, DaqDisconnected, DaqError
from usmswitch.drivers.events import Channel, Conditions, Direction, Event, FaultCode

from .faults import FAULT_KINDS, FaultPlan, check_kind
from .model import Stroke, UsmSwitchModel

_DISCONNECT = object()  # heap marker: the device goes away at this instant
_MISSABLE = ("depart", "arrive")


class _Motion:
    """The stroke under way: when its edges physically happen and when the drive cuts itself."""

    __slots__ = ("arrive_t", "depart_t", "direction", "off_t", "sign", "stroke", "t_start", "x0")

    def __init__(
        self,
        direction: Direction,
        t_start: int,
        x0: float,
        stroke: Stroke | None,
        depart_t: int | None,
        arrive_t: int | None,
    ) -> None:
        self.direction = direction
        self.t_start = t_start
        self.x0 = x0
        self.sign = 1.0 if direction is Direction.ON else -1.0
        self.stroke = stroke  # None: pushing against the end stop, no motion
        self.depart_t = depart_t  # None: the mover was not on the source sensor
        self.arrive_t = arrive_t  # None: no arrival (stall, end stop)
        self.off_t = arrive_t  # the limit cut; None: the drive stays on until stop()


class _Injection:
    """A run-time fault waiting for its strokes."""

    __slots__ = ("edge", "kind", "left")

    def __init__(self, kind: str, left: int, edge: str | None) -> None:
        self.kind = kind
        self.left = left  # strokes still to suffer it
        self.edge = edge  # "missed" only: which edge, or None for either


class SimDaq(Daq):
    """The simulated rig behind the `Daq` interface: software-timed, virtual or real time."""

    hardware_timed = False
    name = "sim"

    def __init__(
        self,
        model: UsmSwitchModel | None = None,
        *,
        realtime: bool = False,
        seed: int = 0,
        faults: FaultPlan | dict[str, object] | None = None,
        debounce_ns: int = DEFAULT_DEBOUNCE_NS,
        clock: Clock | None = None,
    ) -> None:
        if clock is None:
            clock = MonotonicClock() if realtime else VirtualClock()
        elif clock.virtual == bool(realtime):
            raise ValueError(f"realtime={realtime!r} does not match the given clock {type(clock).__name__}")
        super().__init__(clock=clock, debounce_ns=debounce_ns)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"seed must be an integer, got {seed!r}")
        if model is None:
            model = UsmSwitchModel(seed=seed)
        elif not isinstance(model, UsmSwitchModel):
            raise TypeError(f"model must be a UsmSwitchModel, got {type(model).__name__}")
        self.model = model
        self.realtime = bool(realtime)
        self.seed = seed
        # Faults draw from their own generator, so injecting them never shifts the physics.
        self._frng = random.Random(f"usmswitch.sim.faults:{seed}")
        plan = FaultPlan.from_config(faults)
        self._prob: dict[str, float] = dict(plan.probability)
        self._schedule: dict[int, tuple[str, ...]] = dict(plan.schedule)
        self._injected: list[_Injection] = []
        #: Strokes each fault was applied to.
        self.fault_counts: dict[str, int] = dict.fromkeys(FAULT_KINDS, 0)
        #: The faults applied to the most recent stroke.
        self.last_faults: tuple[str, ...] = ()
        #: Strokes started (the next stroke's number for the fault schedule).
        self.strokes = 0
        self._heap: list[tuple[int, int, object]] = []
        self._seq = 0
        p = model.params
        self._stroke_mm = p.stroke_mm
        self._release_mm = p.release_mm
        self._x = 0.0  # mover position: 0 at sensor A (switch off), stroke_mm at sensor B
        self._levels = [1, 0]  # sensor levels A, B: the mover starts at rest on A
        self._motion: _Motion | None = None
        self._connected = False
        self._wake = threading.Event()

    # -- lifecycle -------------------------------------------------------------------------------
    def open(self) -> None:
        """Connect, or reconnect after a disconnect (the mover keeps its position)."""
        with self._lock:
            if self.is_open and not self._connected:
                self.is_open = False
            super().open()

    def _open(self) -> None:
        self._heap.clear()
        self._connected = True

    def _close(self) -> None:
        self._heap.clear()
        self._connected = False
        self._wake.set()

    def ping(self) -> bool:
        """True while open and connected."""
        return self.is_open and self._connected

    # -- drive settings and conditions -----------------------------------------------------------
    def counters(self) -> dict[str, int]:
        return {**super().counters(), **{f"injected_{k}": n for k, n in self.fault_counts.items()}}

    def conditions(self) -> Conditions:
        """Motor temperature now and the drive's frequency and voltage."""
        with self._lock:
            self._check_usable()
            m = self.model
            return Conditions(m.temperature_c(self.clock.now_ns()), m.frequency_hz, m.voltage_vpp)

    def expected_stroke_ns(self, direction: Direction) -> int:
        """The model's expected next stroke (drive, temperature and friction as they are now)."""
        with self._lock:
            return self.model.expected_operating_ns(direction)

    def set_drive(self, *, frequency_hz: float | None = None, voltage_vpp: float | None = None) -> None:
        """Set excitation frequency and/or voltage, as the daemon would over Modbus; next stroke on."""
        with self._lock:
            self._check_usable()
            self.model.set_drive(frequency_hz=frequency_hz, voltage_vpp=voltage_vpp)

    def levels(self) -> tuple[int, int]:
        """The two sensors' levels now (A, B): where the mover is, for recovery after a fault."""
        with self._lock:
            return self._levels_at(self.clock.now_ns())

    def position_mm(self) -> float:
        """The mover's position now, 0 at sensor A and stroke_mm at sensor B (diagnostics)."""
        with self._lock:
            m = self._motion
            if m is None or m.stroke is None:
                return self._x
            t = self.clock.now_ns()
            if m.arrive_t is not None and t >= m.arrive_t:
                return 0.0 if m.direction is Direction.OFF else self._stroke_mm
            return m.x0 + m.sign * m.stroke.displacement_mm(t - m.t_start)

    def _check_usable(self) -> None:
        if not self.is_open:
            raise DaqError(f"{self.name}: the driver is closed")
        if not self._connected:
            raise DaqDisconnected(f"{self.name}: the device is disconnected; open() reconnects")

    # -- faults ------------------------------------------------------------------------------------
    def inject(self, fault: str, *, count: int = 1, edge: str | None = None) -> None:
        """Make the next `count` strokes suffer `fault`; "disconnect" happens now."""
        fault = check_kind(fault)
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ValueError(f"count must be a positive integer, got {count!r}")
        if edge is not None and (fault != "missed" or edge not in _MISSABLE):
            raise ValueError(f"edge={edge!r} applies only to 'missed' and must be one of {_MISSABLE}")
        with self._lock:
            if fault != "disconnect":
                self._injected.append(_Injection(fault, count, edge))
                return
            self._check_usable()
            now = self.clock.now_ns()
            self._flush_due(now)
            if self._connected:
                self.fault_counts["disconnect"] += 1
                self._pending.append(self._disconnect_at(now, "disconnect injected"))

    def set_fault_probability(self, fault: str, probability: float) -> None:
        """Set a fault's per-stroke probability from the next stroke on (0 disables it)."""
        fault = check_kind(fault)
        FaultPlan.from_config({"probability": {fault: probability}})  # validates the number
        with self._lock:
            self._prob[fault] = float(probability)

    def clear_faults(self) -> None:
        """Drop every pending injection, the schedule and all probabilities (does not reconnect)."""
        with self._lock:
            self._injected.clear()
            self._schedule.clear()
            self._prob.clear()

    def _faults_for(self, n: int) -> dict[str, str | None]:
        kinds: dict[str, str | None] = {}
        for kind in self._schedule.pop(n, ()):
            kinds[kind] = None
        for entry in self._injected:
            if kinds.get(entry.kind) is None:
                kinds[entry.kind] = entry.edge
            entry.left -= 1
        if self._injected:
            self._injected = [e for e in self._injected if e.left > 0]
        rnd = self._frng.random
        for kind, p in self._prob.items():
            if p > 0.0 and rnd() < p and kind not in kinds:
                kinds[kind] = None
        return kinds

    # -- the mechanism -----------------------------------------------------------------------------
    def _push_at(self, t: int, item: object) -> None:
        self._seq += 1
        heapq.heappush(self._heap, (t, self._seq, item))

    def _drive(self, direction: Direction) -> int:
        now = self.clock.now_ns()
        self._check_usable()
        self._flush_due(now)
        if not self._connected:
            raise DaqDisconnected(f"{self.name}: the device disconnected before the start")
        m = self._motion
        if m is not None:
            if m.off_t is None:
                raise DaqError(
                    f"{self.name}: the drive is still on since {m.t_start} ns (stall or end stop): "
                    "stop() first"
                )
            if now < m.off_t:
                raise DaqError(f"{self.name}: a stroke is in motion until {m.off_t} ns; wait for its arrival")
            self._finish(now)
        n = self.strokes
        self.strokes = n + 1
        faults = self._faults_for(n) if (self._prob or self._schedule or self._injected) else {}
        for kind in faults:
            self.fault_counts[kind] += 1
        self.last_faults = tuple(faults)
        src = direction.source
        dst = direction.dest
        src_x = 0.0 if src is Channel.A else self._stroke_mm
        dst_x = self._stroke_mm - src_x
        x = self._x
        frng = self._frng
        if self._levels[dst] or x == dst_x:
            # Already at the destination: the drive pushes against the end stop, nothing moves.
            self.model.drive_on(now, None)
            self._motion = _Motion(direction, now, x, None, None, None)
            end_t = now + self.model.dead_time_ns(direction) + 1_000_000
        else:
            p = self.model.params
            jam = frng.uniform(p.stall_fraction_min, p.stall_fraction_max) if "stall" in faults else None
            st = self.model.next_stroke(direction, now, distance_mm=abs(dst_x - x), jam_fraction=jam)
            depart_t = None
            if self._levels[src]:
                rel = self._release_mm - abs(x - src_x)
                if rel <= 0.0:
                    depart_t = now + st.dead_ns
                elif rel < st.end_mm:
                    depart_t = now + st.time_at_ns(rel)
            arrive_t = now + st.operating_ns if st.operating_ns is not None else None
            self._motion = _Motion(direction, now, x, st, depart_t, arrive_t)
            end_t = now + st.end_offset_ns
            missed = None
            if "missed" in faults:
                have = [e for e, t in zip(_MISSABLE, (depart_t, arrive_t), strict=True) if t is not None]
                want = faults["missed"]
                missed = want if want in have else (frng.choice(have) if have else None)
            if depart_t is not None and missed != "depart":
                self._push_at(depart_t, Event.edge(depart_t, src, 0))
            if arrive_t is not None and missed != "arrive":
                self._push_at(arrive_t, Event.edge(arrive_t, dst, 1))
                if "bounce" in faults:
                    t = arrive_t
                    for _ in range(frng.randint(1, p.bounce_pairs_max)):
                        t += frng.randint(p.bounce_gap_min_ns, p.bounce_gap_max_ns)
                        self._push_at(t, Event.edge(t, dst, 0))
                        t += frng.randint(p.bounce_gap_min_ns, p.bounce_gap_max_ns)
                        self._push_at(t, Event.edge(t, dst, 1))
        if "spurious" in faults:
            p = self.model.params
            tg = frng.randint(now + 1, max(end_t, now + 2))
            ch = frng.choice((Channel.A, Channel.B))
            level = self._planned_level(ch, tg)
            width = frng.randint(p.glitch_width_min_ns, p.glitch_width_max_ns)
            self._push_at(tg, Event.edge(tg, ch, 1 - level))
            # The pulse ends at the line's true level then: when the real edge came during the
            # pulse (an arrival inside it), the line stays where the mover put it.
            if self._planned_level(ch, tg + width) == level:
                self._push_at(tg + width, Event.edge(tg + width, ch, level))
        if "disconnect" in faults:
            self._push_at(frng.randint(now + 1, max(end_t, now + 2)), _DISCONNECT)
        if self.realtime:
            self._wake.set()  # a recv waiting in another thread must see the new edges
        return now

    def _planned_level(self, ch: Channel, t: int) -> int:
        """A sensor's level at `t` as the stroke under way will leave it (ignoring glitches)."""
        m = self._motion
        level = self._levels[ch]
        if m is None:
            return level
        if ch is m.direction.source and m.depart_t is not None and t >= m.depart_t:
            return 0
        if ch is m.direction.dest and m.arrive_t is not None and t >= m.arrive_t:
            return 1
        return level

    def _levels_at(self, t: int) -> tuple[int, int]:
        return (self._planned_level(Channel.A, t), self._planned_level(Channel.B, t))

    def _finish(self, t: int) -> None:
        """Settle the stroke under way at `t`: position, sensor levels, and the drive cut."""
        m = self._motion
        if m is None:
            return
        self._levels[0], self._levels[1] = self._levels_at(t)
        self._motion = None
        st = m.stroke
        if st is not None:
            if m.arrive_t is not None and t >= m.arrive_t:
                self._x = 0.0 if m.direction is Direction.OFF else self._stroke_mm
            else:
                x = m.x0 + m.sign * st.displacement_mm(t - m.t_start)
                self._x = min(max(x, 0.0), self._stroke_mm)
        if m.off_t is None or t < m.off_t:
            self.model.drive_off(t)

    def _disconnect_at(self, t: int, detail: str) -> Event:
        """The device goes away at `t`: the drive is off, nothing after `t` is reported."""
        self._connected = False
        self._finish(t)
        self._heap.clear()
        self._wake.set()
        return Event.fault_event(t, FaultCode.DISCONNECT, f"{self.name}: {detail}")

    def _pop(self) -> Event:
        t, _, item = heapq.heappop(self._heap)
        if item is _DISCONNECT:
            return self._disconnect_at(t, "disconnected mid-stroke (injected)")
        return item  # an Event: only _DISCONNECT is not

    def _flush_due(self, now: int) -> None:
        """Queue events already past (so a START or STOP stamped `now` cannot overtake them)."""
        heap = self._heap
        while heap and heap[0][0] <= now:
            self._pending.append(self._pop())

    def _stop(self) -> None:
        if not self._connected:
            self._wake.set()
            return
        now = self.clock.now_ns()
        self._flush_due(now)
        if self._connected:
            self._finish(now)
            self._heap.clear()
        self._wake.set()

    def _recv_internal(self, deadline_ns: int | None) -> Event | None:
        if self.realtime:
            return self._recv_realtime(deadline_ns)
        with self._lock:
            if self._pending:
                return self._pending.popleft()
            self._check_usable()
            heap = self._heap
            if heap:
                t = heap[0][0]
                if deadline_ns is None or t <= deadline_ns:
                    self.clock.sleep_until(t)
                    return self._pop()
            if deadline_ns is not None:
                self.clock.sleep_until(deadline_ns)
            return None

    def _recv_realtime(self, deadline_ns: int | None) -> Event | None:
        clock = self.clock
        while True:
            with self._lock:
                if self._pending:  # pushed by stop() or inject() from another thread
                    return self._pending.popleft()
                self._check_usable()
                now = clock.now_ns()
                heap = self._heap
                if heap and heap[0][0] <= now:
                    return self._pop()
                t_next = heap[0][0] if heap else None
                held = self._motion is not None and self._motion.off_t is None
                self._wake.clear()
            if deadline_ns is not None and now >= deadline_ns:
                return None
            if t_next is None and deadline_ns is None:
                if not held:
                    return None
                self._wake.wait()  # a stalled drive: only a stop() or inject() can end this
                continue
            if t_next is None or (deadline_ns is not None and deadline_ns < t_next):
                target = deadline_ns
            else:
                target = t_next
            self._wake.wait((target - now) / 1e9)
