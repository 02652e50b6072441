"""usmswitchctl without a daemon: --version, --rig, usage errors (plain and --json), documented exit codes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from usmswitch.client.ctl import args as ctl_args
from usmswitch.daemon.version import PACKAGE_VERSION
from usmswitch.daemon.wire import PROTOCOL_VERSION

BIN = Path(sys.executable).parent / "usmswitchctl"
CTL = [str(BIN)] if BIN.exists() else [sys.executable, "-m", "usmswitch.client.ctl"]


def ctl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CTL, *args], capture_output=True, text=True, timeout=30, check=False)


def test_version() -> None:
    r = ctl("--version")
    assert (
        r.returncode == 0
        and r.stdout.strip() == f"usmswitchctl {PACKAGE_VERSION} (protocol {PROTOCOL_VERSION})"
    )


def test_rig_names_the_instance_socket() -> None:
    r = ctl("--rig", "no-such-rig-xyz", "status")
    assert r.returncode == ctl_args.EXIT_CONNECT, r.stderr
    assert "/run/usmswitch/no-such-rig-xyz/usmswitchd.sock" in r.stderr
    r = ctl("--rig", "../etc", "status")
    assert r.returncode == ctl_args.EXIT_USAGE and "--rig" in r.stderr
    r = ctl("--rig", "a", "--socket", "/x.sock", "status")
    assert r.returncode == ctl_args.EXIT_USAGE and "--socket and --rig" in r.stderr
