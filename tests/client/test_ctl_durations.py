"""Issue 35, item 13: every duration a person types is exact or refused as a usage error (exit 2,
one line, no traceback), on every command that takes one, and in the daemon's flags and config."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from usmswitch.client import Client

BAD = ("1e999999ms", "1e999999", "1e-9999999999ms", "١٢ms")


def _run(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *argv], capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("bad", BAD)
def test_usmswitchctl_refuses_each_bad_duration_as_usage(tmp_path: Path, bad: str) -> None:
    sock = str(tmp_path / "none.sock")
    for argv in (
        ["target", "set", bad],
        ["cycle", "--period", bad],
        ["mode", "open", "--delay", bad],
        ["--timeout", bad, "status"],
        ["--json", "target", "set", bad],
    ):
        r = _run("-m", "usmswitch.client.ctl", "--socket", sock, *argv)
        assert r.returncode == 2, (argv, r.returncode, r.stderr)
        assert "Traceback" not in r.stderr and r.stderr.strip(), (argv, r.stderr)


@pytest.mark.parametrize("bad", BAD)
def test_the_client_raises_value_error_before_sending(tmp_path: Path, bad: str) -> None:
    client = Client.__new__(Client)  # no connection: the duration is refused before any is needed
    with pytest.raises(ValueError):
        Client.set_target(client, bad)


def test_usmswitchd_refuses_a_bad_duration_flag_and_config(tmp_path: Path) -> None:
    common = ["-m", "usmswitch.daemon.cli", "--sim", "--state-dir", str(tmp_path / "s")]
    common += ["--socket", str(tmp_path / "d.sock")]
    r = _run(*common, "--target", "1e999999ms")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    conf = tmp_path / "d.toml"
    conf.write_text('[control]\ntarget = "1e999999ms"\n')
    r = _run(*common, "--config", str(conf))
    assert r.returncode == 2 and "control.target" in r.stderr and "Traceback" not in r.stderr, r.stderr
