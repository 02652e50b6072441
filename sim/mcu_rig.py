"""The mover between the two limit sensors, as a microcontroller on the rig sees it.

`Mover` bridges the rig model (`UsmSwitchModel`) and a firmware, emulated or real: where the mover
is, what the limit sensors read, which sensor edges a stroke makes and when, and where the mover
stops when the drive is cut. The Python firmware emulator (`mcu_firmware.McuEmulator`) and the
simavr harness's rig helper (firmware/harness/rig_helper.py) both use it, so the reference
firmware meets the same physics as the emulator. Times are host (physical) nanoseconds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from usmswitch.drivers.events import Channel, Direction

from .model import Stroke, UsmSwitchModel

#: The far sensor's chatter after an injected bounce: 1, 0 after this, 1 after twice this.
BOUNCE_NS = 30_000

Edges = list[tuple[int, Channel, int]]  # (t_ns, channel, level)


@dataclass(frozen=True)
class StrokePlan:
    """What the drive switched on at `t_start_ns` will do."""

    t_start_ns: int
    #: The mover already sat at the far sensor: the stroke arrives at its start, with no edge.
    there: bool
    #: The source sensor's release (level 0), when it was active and the mover gets that far.
    depart_ns: int | None
    #: The far sensor's edge (level 1); None when the mover jams (an injected stall).
    arrive_ns: int | None
    #: This stroke was jammed half way by `jam_next()`.
    jammed: bool = False

    def edges(self, direction: Direction) -> Edges:
        """The sensor edges of the stroke, in time order."""
        out: Edges = []
        if self.depart_ns is not None:
            out.append((self.depart_ns, direction.source, 0))
        if self.arrive_ns is not None and not self.there:
            out.append((self.arrive_ns, direction.dest, 1))
        return out


class Mover:
    """The mover's position, the sensors it makes, and the strokes the model draws for it."""

    def __init__(self, model: UsmSwitchModel, start_at: Channel = Channel.A) -> None:
        self.model = model
        p = model.params
        self.stroke_mm = p.stroke_mm
        self.release_mm = p.release_mm
        self.position_mm = 0.0 if start_at is Channel.A else p.stroke_mm
        self.drive_on = False
        self._direction = Direction.ON
        self._stroke: Stroke | None = None
        self._plan: StrokePlan | None = None
        self._jam_next = False
        self._bounce_next = False

    def sensors(self, t_ns: int | None = None) -> tuple[int, int]:
        """Sensor A and sensor B at `t_ns` (now if None), 1 where active (the mover within
        release_mm of it). During a stroke the source is released from its departure on, as its
        EDGE said: a PONG's snapshot never contradicts the edges sent before it."""
        a = 1 if self.position_mm <= self.release_mm else 0
        b = 1 if self.position_mm >= self.stroke_mm - self.release_mm else 0
        plan = self._plan
        now = time.monotonic_ns() if t_ns is None else t_ns
        if self.drive_on and plan is not None and plan.depart_ns is not None and now >= plan.depart_ns:
            if self._direction.source is Channel.A:
                a = 0
            else:
                b = 0
        return a, b

    def jam_next(self) -> None:
        """The next stroke that moves jams half way (no arrival: a stall)."""
        self._jam_next = True

    def bounce_next(self) -> None:
        """The next arrival bounces (see `stop`)."""
        self._bounce_next = True

    def start(self, direction: Direction, t_ns: int) -> StrokePlan:
        """The drive goes on at `t_ns` towards `direction`'s far sensor."""
        d = Direction(direction)
        self._direction = d
        self.drive_on = True
        self._stroke = None
        distance = (self.stroke_mm - self.position_mm) if d is Direction.ON else self.position_mm
        if distance <= self.release_mm:
            plan = StrokePlan(t_ns, there=True, depart_ns=None, arrive_ns=t_ns)
        else:
            src_active = self.sensors()[int(d.source)] == 1
            jammed, self._jam_next = self._jam_next, False
            st = self.model.next_stroke(d, t_ns, distance_mm=distance, jam_fraction=0.5 if jammed else None)
            self._stroke = st
            depart = (
                t_ns + st.time_at_ns(self.release_mm) if src_active and st.end_mm >= self.release_mm else None
            )
            arrive = None if st.operating_ns is None else t_ns + st.operating_ns
            plan = StrokePlan(t_ns, there=False, depart_ns=depart, arrive_ns=arrive, jammed=jammed)
        self._plan = plan
        return plan

    def stop(self, t_ns: int) -> Edges:
        """The drive is cut at `t_ns` (arrival, stall timeout, host stop, power loss).

        The mover ends at the far sensor if it had arrived, else where it got to. Returns the
        far sensor's chatter when an arrival bounces (`bounce_next`): 0 then 1, after the arrival.
        """
        if not self.drive_on:
            return []
        self.drive_on = False
        self.model.drive_off(t_ns)
        plan, st, d = self._plan, self._stroke, self._direction
        self._plan = self._stroke = None
        if plan is None:
            return []
        dest_mm = self.stroke_mm if d is Direction.ON else 0.0
        if plan.arrive_ns is not None and t_ns >= plan.arrive_ns:
            self.position_mm = dest_mm
            if plan.there or not self._bounce_next:
                return []
            self._bounce_next = False
            a, ch = plan.arrive_ns, d.dest
            return [(a + BOUNCE_NS, ch, 0), (a + 2 * BOUNCE_NS, ch, 1)]
        if st is not None:
            travelled = st.displacement_mm(t_ns - plan.t_start_ns)
            if d is Direction.ON:
                self.position_mm = min(self.stroke_mm, self.position_mm + travelled)
            else:
                self.position_mm = max(0.0, self.position_mm - travelled)
        return []
