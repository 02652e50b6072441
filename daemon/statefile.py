"""Small JSON files beside the records (rig.json, sensitivities.json): written whole or not at all."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def write_private_json(path: Path, obj: Any) -> None:
    """Write `obj` as JSON to `path`, mode 0600, atomically (a reader, or a start after a crash,
    never sees half a file); OSError when it cannot."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
    with os.fdopen(fd, "w") as fh:
        json.dump(obj, fh)
    os.replace(tmp, path)
