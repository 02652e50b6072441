"""docs/service.md's install block, run verbatim (issue 37, item 4: it ran `install -g usmswitch`
before `systemd-sysusers` and never said how `usmswitchd` reached /usr/bin) in a real systemd
booted in a namespace of its own (tests/realsystemd.py), where /etc, /opt, /usr and /var are
overlays: the venv, the links, the user, the units and the config vanish with it.

What stands in for the machine the block was written for, and nothing else:
* root runs it; `sudo` is a shim that runs its command (sudo is not installed here);
* udev does not run in a namespace: the block's `udevadm` line fails there, as in any container,
  and the block goes on (it is the left of an `&&` list, which `set -e` lets fail);
* the board is the MCU emulator (usmswitch.sim.mcu_emulator) on a pty at /dev/usmswitch, the
  name the udev rule gives a board; its mode opened to the unit's user as the rule's GROUP would,
  and a drop-in lets the unit open a pty (it allows ttyACM and ttyUSB only).
The block's `pip install .` builds the checkout (a minute or two: the suite's other worker goes on).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import realsystemd
from checkout import building_from
from test_docs_blocks import blocks_of, shell_script

CI = os.environ.get("CI") == "true"
BOARD = Path("/dev/usmswitch")
SUDO_SHIM = "/tmp/shim"


def _skip_or_fail(why: str) -> None:
    if CI:
        pytest.fail(f"{why} (CI=true: the service doc's block must run)")
    pytest.skip(why)


def install_block(repo_root: Path) -> str:
    """The first shell block of docs/service.md: the install."""
    for block in blocks_of(repo_root / "docs" / "service.md"):
        if block.lang == "sh":
            return shell_script(block)
    raise AssertionError("docs/service.md has no sh block")


@pytest.fixture
def board() -> Iterator[Path]:
    """The MCU emulator on a pty at /dev/usmswitch (the host's /dev: the namespace shares it)."""
    if BOARD.exists() or BOARD.is_symlink():
        _skip_or_fail(f"{BOARD} exists on this machine (a board?): this test would take its name")
    emu = subprocess.Popen(
        [sys.executable, "-m", "usmswitch.sim.mcu_emulator", "--link", str(BOARD), "--seed", "5"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        line = emu.stdout.readline() if emu.stdout else b""
        assert line.startswith(b"mcu emulator on"), line + (emu.stderr.read() if emu.stderr else b"")
        os.chmod(os.path.realpath(BOARD), 0o666)  # the udev rule's GROUP usmswitch, MODE 0660
        yield BOARD
    finally:
        emu.send_signal(signal.SIGTERM)
        emu.communicate(timeout=10)
        BOARD.unlink(missing_ok=True)


def test_the_install_block_runs_verbatim_and_the_service_serves_the_board(
    board: Path, repo_root: Path
) -> None:
    if os.geteuid() != 0:
        _skip_or_fail("the service doc's block needs root")
    script = install_block(repo_root)
    try:
        sd = realsystemd.BootedSystemd()
    except realsystemd.BootError as exc:
        _skip_or_fail(f"no real systemd here: {exc}")
    try:
        root = Path(f"/proc/{sd.pid}/root")
        dropin = root / "etc/systemd/system/usmswitchd.service.d"
        dropin.mkdir(parents=True)
        (dropin / "pty.conf").write_text(
            "[Service]\n# The emulator's pty stands in for the board.\nDeviceAllow=char-pts rw\n"
        )
        sd.run(
            ["sh", "-c", f"mkdir -p {SUDO_SHIM} && printf '#!/bin/sh\\nexec \"$@\"\\n' > {SUDO_SHIM}/sudo"]
        )
        sd.run(["chmod", "+x", f"{SUDO_SHIM}/sudo"])
        env = {"PATH": f"{SUDO_SHIM}:/usr/sbin:/usr/bin:/sbin:/bin", "USER": "root", "HOME": "/root"}
        env.update(
            {k: v for k, v in os.environ.items() if k.startswith(("PIP_", "http", "https", "no_proxy"))}
        )
        with building_from(repo_root):
            done = sd.run(["bash", "-c", script], check=False, timeout=900, env=env, cwd=str(repo_root))
        assert done.returncode == 0, f"the block failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
        # The service is up on the board and its socket answers the group's tools from /usr/bin.
        state = sd.wait_for("usmswitchd.service", timeout=60, ActiveState="active")
        assert state["ActiveState"] == "active", sd.journal("usmswitchd.service")
        status = _status(sd)
        assert "serial" in status and "idle" in status, status + sd.journal("usmswitchd.service")
        assert os.readlink(root / "usr/bin/usmswitchd") == "/opt/usmswitch/bin/usmswitchd"
        members = sd.run(["id", "-nG", "root"]).stdout.split()
        assert "usmswitch" in members  # the block's last line: usermod -aG usmswitch "$USER"
    finally:
        sd.close()


def _status(sd: realsystemd.BootedSystemd) -> str:
    """`usmswitchctl status` as a member of the group would run it, once the daemon has its board."""
    deadline = time.monotonic() + 60
    out = ""
    while time.monotonic() < deadline:
        done = sd.run(["/usr/bin/usmswitchctl", "status"], check=False)
        out = done.stdout + done.stderr
        if done.returncode == 0 and "idle" in out:
            return out
        time.sleep(0.5)
    return out
