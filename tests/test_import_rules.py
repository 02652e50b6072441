"""The layout's import rules (docs: README, "Layout"), read from the source with ast: every import of
ours, at module level or inside a function, is an arrow."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: Each room, and the rooms of ours it may import besides itself (None: any).
ALLOWED: dict[str, set[str] | None] = {
    "protocol": set(),
    "predictor": set(),
    "fleet": {"protocol"},
    "web": {"protocol", "fleet"},
    "runtime": {"protocol"},
    "server": {"protocol", "web", "fleet", "runtime"},
    "client": {"protocol", "fleet"},
}
#: Arrows no room may draw, whatever it may otherwise import.
FORBIDDEN = {
    ("client", "daemon"),
    ("daemon", "client"),
    ("daemon", "experiments"),
    ("drivers", "sim"),
    ("fleet", "daemon"),
    ("web", "daemon"),
    ("server", "daemon"),
    ("runtime", "daemon"),
}
#: The only modules of client that may import fleet: those that read PostgreSQL.
CLIENT_FLEET_READERS = {"usmswitch.client.pgrecords", "usmswitch.client.sources"}


def _modules() -> dict[str, Path]:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    mods = {}
    for pkg, folder in cfg["tool"]["setuptools"]["package-dir"].items():
        for f in (ROOT / folder).rglob("*.py"):
            parts = [p for p in f.relative_to(ROOT / folder).with_suffix("").parts if p != "__init__"]
            mods[".".join([pkg, *parts])] = f
    return mods


def _imports(mod: str, path: Path) -> set[str]:
    """The modules named `usmswitch.*` that `mod` imports, relative imports resolved."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
                pkg = pkg[: len(pkg) - (node.level - 1)]
                base = ".".join([*pkg, base] if base else pkg)
            out.add(base)
    return {m for m in out if m.startswith("usmswitch.")}


def _room(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else ""


ARROWS = sorted((m, d) for m, f in _modules().items() for d in _imports(m, f))


@pytest.mark.parametrize("room", sorted(ALLOWED))
def test_a_room_imports_only_what_it_may(room: str):
    allowed = {room, *(ALLOWED[room] or ())}
    wrong = [f"{m} -> {d}" for m, d in ARROWS if _room(m) == room and _room(d) and _room(d) not in allowed]
    assert not wrong, wrong


def test_no_forbidden_arrow():
    wrong = [f"{m} -> {d}" for m, d in ARROWS if (_room(m), _room(d)) in FORBIDDEN]
    assert not wrong, wrong


def test_the_client_reads_fleet_only_to_read_postgresql():
    wrong = [
        f"{m} -> {d}"
        for m, d in ARROWS
        if _room(m) == "client" and _room(d) == "fleet" and m not in CLIENT_FLEET_READERS
    ]
    assert not wrong, wrong


def test_the_rules_see_every_room():
    rooms = {_room(m) for m in _modules()}
    expected = {
        "protocol",
        "fleet",
        "web",
        "server",
        "runtime",
        "daemon",
        "client",
        "predictor",
        "drivers",
        "sim",
    }
    assert expected <= rooms
    assert any(_room(m) == "client" and _room(d) == "protocol" for m, d in ARROWS)  # the walk finds arrows
