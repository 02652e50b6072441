"""The installed package's version, for `--version` on both tools and the status reply.

Pure standard library: the client imports it as well as the daemon.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    PACKAGE_VERSION = version("usmswitch")
except PackageNotFoundError:  # a source tree that was never installed
    PACKAGE_VERSION = "0+unknown"


def version_text(prog: str, protocol_version: int) -> str:
    """What `PROG --version` prints: the package version and the socket protocol it speaks."""
    return f"{prog} {PACKAGE_VERSION} (protocol {protocol_version})"
