"""usmswitch: a real-time controller for a mechanical switch driven by an ultrasonic motor.

The parts are subpackages (usmswitch.client, .daemon, .protocol, .drivers, .predictor, .sim,
.experiments);
this file only names the version, as `usmswitch.__version__`.
"""

from usmswitch.protocol.version import PACKAGE_VERSION as __version__

__all__ = ["__version__"]
