"""Shared test set-up: the repository root, so tests can find docs/ and systemd/ files; a real
PostgreSQL server (tests/pgserver.py) for the shipping and fleet tests, one per session."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_databases = itertools.count(1)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


@pytest.fixture(scope="session")
def pg_server() -> Iterator[object]:
    """One PostgreSQL 15 cluster for the session (skipped, or failed under CI, when not installed)."""
    import pgserver

    pgserver.require()
    server = pgserver.PgServer()
    server.start()
    try:
        yield server
    finally:
        server.close()


@pytest.fixture
def pg(pg_server: object) -> Iterator[tuple[object, str, str]]:
    """(server, database name, URL) of a fresh database owned by the shipping role; the server
    is started again after a test that stopped it."""
    name = f"t{next(_databases)}"
    url = pg_server.database(name)  # type: ignore[attr-defined]
    try:
        yield pg_server, name, url
    finally:
        if not pg_server.started:  # type: ignore[attr-defined]
            pg_server.start()  # type: ignore[attr-defined]
