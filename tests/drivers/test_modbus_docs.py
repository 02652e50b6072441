"""docs/modbus.md's config examples are config the daemon loads."""

from __future__ import annotations

import re
from pathlib import Path

from usmswitch.daemon.config import load_config


def test_every_toml_example_in_modbus_md_loads(repo_root: Path, tmp_path: Path) -> None:
    text = (repo_root / "docs" / "modbus.md").read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, re.S)
    assert len(blocks) >= 2
    for i, block in enumerate(blocks):
        path = tmp_path / f"example{i}.toml"
        path.write_text(block)
        cfg = load_config(path, env={"HOME": str(tmp_path)})
        assert cfg.modbus.url.startswith(("tcp:", "rtu:"))
    assert "[board" not in text  # the section is [modbus]
