"""`make flash` without a PORT says how to name one, and never runs avrdude with `-P ` empty."""

from __future__ import annotations

import subprocess
from pathlib import Path


def test_make_flash_without_a_port_says_how_and_runs_no_avrdude(firmware_elf: Path, repo_root: Path) -> None:
    r = subprocess.run(
        ["make", "-C", str(repo_root), "flash", "PORT="],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert r.returncode != 0
    assert "make flash PORT=/dev/ttyACM0" in r.stderr, r.stderr
    assert "avrdude" not in r.stdout.replace("Entering", "")
