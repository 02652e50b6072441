"""Builds for the firmware tests: the native core driver, the AVR image and the simavr harness.

Without the toolchain these tests skip with one line naming the Debian packages, except under
CI=true, where a missing toolchain is a failure (CI installs the packages, see .ci/run).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "firmware"
BUILD = FIRMWARE / "build"

NATIVE_PACKAGES = "gcc make"
AVR_PACKAGES = "gcc-avr avr-libc binutils-avr"
SIM_PACKAGES = "simavr libsimavr-dev libelf-dev"


def _missing(tools: list[str], headers: list[str]) -> list[str]:
    gone = [t for t in tools if shutil.which(t) is None]
    gone += [h for h in headers if not Path(h).exists()]
    return gone


def require(tools: list[str], headers: list[str], packages: str) -> None:
    """Skip (fail under CI=true) when a tool or header of the toolchain is absent."""
    gone = _missing(tools, headers)
    if not gone:
        return
    msg = f"firmware toolchain missing ({', '.join(gone)}): apt-get install {packages}"
    if os.environ.get("CI") == "true":
        pytest.fail(msg, pytrace=False)
    pytest.skip(msg)


def make(*targets: str) -> None:
    """Build firmware targets (one job: the machine is shared), one build at a time: make test's
    two processes (pytest-xdist) would otherwise write the same objects at once."""
    BUILD.mkdir(exist_ok=True)
    with open(BUILD / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        proc = subprocess.run(
            ["make", "-j1", "-C", str(FIRMWARE), *targets], capture_output=True, text=True, check=False
        )
    if proc.returncode != 0:
        pytest.fail(f"make {' '.join(targets)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    warnings = [ln for ln in proc.stderr.splitlines() if "warning:" in ln]
    assert not warnings, "\n".join(warnings)


@pytest.fixture(scope="session")
def core_test_bin() -> Path:
    """The native protocol-core driver (tests/firmware/core_test.c)."""
    require(["cc", "make"], [], NATIVE_PACKAGES)
    make("native")
    return BUILD / "core_test"


@pytest.fixture(scope="session")
def firmware_elf() -> Path:
    """The AVR firmware image."""
    require(["avr-gcc", "avr-objcopy", "make"], ["/usr/lib/avr/include/avr/io.h"], AVR_PACKAGES)
    make("build/usmswitch.hex")
    return BUILD / "usmswitch.elf"


@pytest.fixture(scope="session")
def avrsim(firmware_elf: Path) -> Path:
    """The simavr harness (and the emulator self-test image beside it)."""
    require(["cc"], ["/usr/include/simavr/sim_avr.h", "/usr/include/libelf.h"], SIM_PACKAGES)
    make("harness")
    return BUILD / "usmswitch-avrsim"
