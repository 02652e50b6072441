"""DAQ drivers: the interface (`Daq`), its clocks and events, and the hardware drivers."""

from .clock import Clock, MonotonicClock, VirtualClock
from .daq import Daq, DaqDisconnected, DaqError, DaqHalted, check_ns
from .events import Channel, Commanded, Conditions, Direction, Event, EventKind, FaultCode

__all__ = [
    "Channel",
    "Clock",
    "Commanded",
    "Conditions",
    "Daq",
    "DaqDisconnected",
    "DaqError",
    "DaqHalted",
    "Direction",
    "Event",
    "EventKind",
    "FaultCode",
    "MonotonicClock",
    "VirtualClock",
    "check_ns",
]
