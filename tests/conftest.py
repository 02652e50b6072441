"""Shared test set-up: the repository root, so tests can find docs/ and systemd/ files; a real
PostgreSQL server (tests/pgserver.py) for the shipping and fleet tests, one per session; a records
file of 100,000 strokes (issue 36's scale tests), made once per session."""

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


#: Strokes in the shared records file, and in each of its runs.
RECORDS_100K = 100_000
RECORDS_100K_RUN = 10_000


@pytest.fixture(scope="session")
def records_100k(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A records file of RECORDS_100K strokes in runs of RECORDS_100K_RUN, written by the control
    loop on the simulated rig in virtual time through the real record writer (~30-60 s, once per
    session). Read-only to its users: copy it to write."""
    import sys

    sys.path.insert(0, str(ROOT / "tests" / "daemon"))
    from test_loop import make_loop

    from usmswitch.daemon.records import RecordStore

    path = tmp_path_factory.mktemp("records-100k") / "records.sqlite"
    store = RecordStore(path, wait_when_behind=20_000)
    loop, _daq, _ = make_loop(target_ns=12_000_000, sink=store.submit, seed=21)
    loop.run_sink = store.submit_run
    done = 0
    while done < RECORDS_100K:
        before = loop.cycle
        loop.run_cycles(30_000_000, min(RECORDS_100K_RUN, RECORDS_100K - done))
        done += loop.cycle - before
        if loop.state.value == "fault":
            loop.reset_fault()
    assert store.close() and store.dropped == 0
    return path


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
