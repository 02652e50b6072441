"""Fixtures of the socket server's tests."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest


@pytest.fixture
def sockdir() -> Iterator[Path]:
    """A directory for the sockets: short and world-traversable, since AF_UNIX paths are limited to
    ~107 bytes and the permission tests connect as another user."""
    d = Path(tempfile.mkdtemp(prefix="usmrpc-", dir="/tmp"))
    d.chmod(0o755)
    yield d
    for p in d.iterdir():
        p.unlink()
    d.rmdir()
