"""The simulated rig: the USM switch's physics (`UsmSwitchModel`) and its DAQ face (`SimDaq`).

`sim` imports the DAQ interface from `usmswitch.drivers`; `drivers` never imports `sim`.
"""

from .daq import SimDaq
from .faults import FAULT_KINDS, FaultPlan
from .model import Profile, Stroke, UsmSwitchModel
from .params import RigParams

__all__ = ["FAULT_KINDS", "FaultPlan", "Profile", "RigParams", "SimDaq", "Stroke", "UsmSwitchModel"]
