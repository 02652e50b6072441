"""The installed package's version, for `--version` on both tools and the status reply.

Pure standard library: the client imports it as well as the daemon.
"""

from __future__ import annotations

import functools
from typing import Any


@functools.cache
def package_version() -> str:
    """The installed package's version; "0+unknown" in a source tree never installed. Read on first
    use: importlib.metadata costs a command-line tool ~0.2 s of its start-up."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("usmswitch")
    except PackageNotFoundError:
        return "0+unknown"


def __getattr__(name: str) -> Any:
    if name == "PACKAGE_VERSION":  # the name modules import, read when they ask for it
        return package_version()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def version_text(prog: str, protocol_version: int) -> str:
    """What `PROG --version` prints: the package version and the socket protocol it speaks."""
    return f"{prog} {package_version()} (protocol {protocol_version})"
