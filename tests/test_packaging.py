"""The package as pip builds it: the panel's files inside, and no setuptools warnings about them."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

from checkout import building_from


def test_the_wheel_carries_the_panel_and_builds_without_warnings(tmp_path: Path, repo_root: Path) -> None:
    """Issue 37's bites: installing printed ~40 lines of "Package 'usmswitch.web.static' is absent
    from the packages configuration" (a data folder setuptools took for an undeclared package)."""
    with building_from(repo_root):
        r = subprocess.run(
            [sys.executable, "-m", "pip", "wheel", str(repo_root), "--no-deps", "-w", str(tmp_path)],
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
            cwd=tmp_path,
        )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "is absent" not in r.stdout + r.stderr
    (wheel,) = tmp_path.glob("usmswitch-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for f in ("index.html", "panel.js", "panel.css", "uPlot.iife.min.js", "uPlot-LICENSE.txt"):
        assert f"usmswitch/web/static/{f}" in names, f
