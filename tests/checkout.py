"""Builds from the checkout (`pip wheel .`, `pip install .`): setuptools writes build/ into the
checkout, so they run one at a time across make test's processes (pytest-xdist), and build/ is
left as it was found."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def building_from(repo_root: Path) -> Iterator[None]:
    """Hold the checkout's build lock (a file under the temp directory, named for the checkout)."""
    key = hashlib.sha1(str(repo_root.resolve()).encode()).hexdigest()[:12]
    with open(Path(tempfile.gettempdir()) / f"usmswitch-build-{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        build_dir = repo_root / "build"
        had_build = build_dir.exists()
        try:
            yield
        finally:
            if not had_build:
                shutil.rmtree(build_dir, ignore_errors=True)
