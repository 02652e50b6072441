"""usmswitchctl: the command line over `usmswitch.client` (docs/usmswitchctl.md)."""

from .main import main

__all__ = ["main"]
