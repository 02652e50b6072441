"""What a DAQ driver reports: timestamped edges, motor starts and stops, faults.

Every stamp is an integer of nanoseconds on the driver's own clock (see `Daq.now_ns`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class Channel(IntEnum):
    """A limit sensor. The mover rests at A when the switch is off and at B when it is on."""

    A = 0
    B = 1


class Direction(IntEnum):
    """A stroke: "on" moves A -> B, "off" moves B -> A."""

    ON = 0
    OFF = 1

    @property
    def source(self) -> Channel:
        """The sensor the mover leaves (its release is the depart edge)."""
        return Channel.A if self is Direction.ON else Channel.B

    @property
    def dest(self) -> Channel:
        """The sensor the mover reaches (its activation is the arrive edge)."""
        return Channel.B if self is Direction.ON else Channel.A

    @property
    def opposite(self) -> Direction:
        return Direction.OFF if self is Direction.ON else Direction.ON


class EventKind(IntEnum):
    EDGE = 0  # a limit sensor changed level
    START = 1  # the drive was switched on for a stroke (actual instant)
    STOP = 2  # the drive was switched off (end of stroke, stop or emergency stop)
    FAULT = 3  # the driver or device reports a fault
    REPORT = 4  # the device's own account of the stroke that just ended (drivers that report)


class FaultCode(IntEnum):
    STALL = 1  # no arrival within the stroke timeout
    DISCONNECT = 2  # the device went away (unplug, port closed)
    WIRE = 3  # corrupt or lost frames on the link
    DRIVE = 4  # the drive board reports an error or stopped answering
    SEQUENCE = 5  # events out of order or inconsistent with the stroke in progress


@dataclass(frozen=True, slots=True)
class StrokeReport:
    """A device's own account of a stroke, for the host to hold its stamps against.

    Stamps are on the driver's clock (None: the device did not say, or said something not to be
    believed); `detail` is what the driver's own checks found wrong with the device's account ("":
    nothing)."""

    t_start_ns: int | None = None
    t_depart_ns: int | None = None
    t_arrive_ns: int | None = None
    arrived: bool = False
    #: The device stamped the stroke itself (a STROKE report); else only the driver's checks speak.
    has_stamps: bool = False
    detail: str = ""


@dataclass(frozen=True, slots=True)
class Event:
    """One timestamped thing a driver saw. Fields that do not apply to a kind stay None."""

    kind: EventKind
    t_ns: int
    channel: Channel | None = None  # EDGE
    level: int | None = None  # EDGE: 1 = sensor active (mover present), 0 = released
    direction: Direction | None = None  # START, STOP
    fault: FaultCode | None = None  # FAULT
    detail: str = ""
    lateness_ns: int | None = None  # START from a hardware-timed device: how late it fired
    report: StrokeReport | None = None  # REPORT

    @classmethod
    def edge(cls, t_ns: int, channel: Channel, level: int) -> Event:
        return cls(EventKind.EDGE, t_ns, channel=channel, level=level)

    @classmethod
    def start(cls, t_ns: int, direction: Direction, lateness_ns: int | None = None) -> Event:
        return cls(EventKind.START, t_ns, direction=direction, lateness_ns=lateness_ns)

    @classmethod
    def stop(cls, t_ns: int, direction: Direction | None = None, detail: str = "") -> Event:
        return cls(EventKind.STOP, t_ns, direction=direction, detail=detail)

    @classmethod
    def report_event(cls, t_ns: int, report: StrokeReport) -> Event:
        return cls(EventKind.REPORT, t_ns, report=report)

    @classmethod
    def fault_event(cls, t_ns: int, fault: FaultCode, detail: str = "") -> Event:
        return cls(EventKind.FAULT, t_ns, fault=fault, detail=detail)


@dataclass(frozen=True, slots=True)
class Commanded:
    """What `Daq.command` did: the command instant and, when the host timed it, the start."""

    direction: Direction
    t_cmd_ns: int
    delay_ns: int
    # Software-timed: the host's start stamp and how late it was against t_cmd + delay.
    # Hardware-timed: None; the device reports the start as a START event.
    t_start_ns: int | None = None
    lateness_ns: int | None = None


@dataclass(frozen=True, slots=True)
class Conditions:
    """Drive conditions at a stroke, when the rig can tell them (sim, Modbus drive board)."""

    temperature_c: float | None = None
    frequency_hz: float | None = None
    voltage_vpp: float | None = None
