"""docs/records.md lists exactly the event kinds the daemon writes."""

from __future__ import annotations

import re
from pathlib import Path


def test_documented_event_kinds_are_the_ones_written(repo_root: Path) -> None:
    written = set()
    for path in (repo_root / "daemon").glob("*.py"):
        # record_event("kind", ...) in the daemon, and the drive board's on_event("kind", ...) that
        # service.py hands to record_event.
        written |= set(re.findall(r"\b(?:record_event|on_event)\(\s*\"([a-z_]+)\"", path.read_text()))
    text = (repo_root / "docs" / "records.md").read_text()
    section = text[text.index("### Events") : text.index("## Writing")]
    documented = set(re.findall(r"^\| `([a-z_]+)` \|", section, re.M))
    assert written and documented == written, (sorted(documented - written), sorted(written - documented))
