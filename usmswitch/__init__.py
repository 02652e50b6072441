"""usmswitch: a real-time controller for a mechanical switch driven by an ultrasonic motor.

The parts are subpackages (usmswitch.client, .daemon, .drivers, .predictor, .sim, .experiments);
this file only names the version, as `usmswitch.__version__`.
"""

from usmswitch.daemon.version import PACKAGE_VERSION as __version__

__all__ = ["__version__"]
