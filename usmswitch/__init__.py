"""usmswitch: a real-time controller for a mechanical switch driven by an ultrasonic motor.

The parts are subpackages (usmswitch.client, .daemon, .protocol, .drivers, .predictor, .sim,
.experiments);
this file only names the version, as `usmswitch.__version__`.
"""

from typing import Any

__all__ = ["__version__"]


def __getattr__(name: str) -> Any:
    if name == "__version__":  # read on first use: importing usmswitch stays cheap
        from usmswitch.protocol.version import package_version

        return package_version()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
