"""Shared test set-up: the repository root, so tests can find docs/ and systemd/ files; a real
PostgreSQL server (tests/pgserver.py) for the shipping and fleet tests, one per session; a records
file of 100,000 strokes (issue 36's scale tests), made once per session."""

from __future__ import annotations

import fcntl
import itertools
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_databases = itertools.count(1)

# The Ctrl-C tests send SIGINT to commands they start, which get it as from a terminal only if this
# process does not ignore it: a shell script's `make test &` starts it ignored (POSIX, without job
# control), exec passes that on, and seven of them failed so ('KeyboardInterrupt' not in '').
# Handled here, it is the default again in every child.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


#: Files that take a minute or more (their module fixtures and tests; a loaded machine doubles it),
#: collected first: `make test`'s two processes take whole files in collection order as each frees,
#: and one of these taken last kept one process busy for minutes after the other had finished.
SLOW_FIRST = (
    "tests/daemon/test_systemd_service.py",
    "tests/experiments/test_experiments.py",
    "tests/test_docs_blocks.py",
    "tests/daemon/test_service_doc.py",
    "tests/test_packaging.py",
    "tests/experiments/test_live_rig.py",
    "tests/daemon/test_daemon_device_truth.py",
    "tests/client/test_export_scale.py",
    "tests/client/test_export_socket.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The SLOW_FIRST files ahead, in that order; every other file after them, as collected."""
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.relative_to(ROOT).as_posix(), len(rank)))


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


#: Strokes in the shared records file, and in each of its runs.
RECORDS_100K = 100_000
RECORDS_100K_RUN = 10_000


@pytest.fixture(scope="session")
def records_100k(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A records file of RECORDS_100K strokes in runs of RECORDS_100K_RUN (`_make_records_100k`),
    made once per run of the suite: under `make test` its two processes share one (the first to ask
    makes it, the other waits for it: made twice it cost 14-25 s of a loaded machine's CPU twice).
    Read-only to its users: copy it to write."""
    base = tmp_path_factory.getbasetemp()
    # Under xdist each worker's base is popen-gwN in the run's own directory, shared by the workers
    # of this run only; a plain pytest's parent is shared by every run, so it keeps its own.
    where = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    path = where / "records-100k" / "records.sqlite"
    with open(where / "records-100k.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not path.exists():
            making = where / f"records-100k.{os.getpid()}"
            making.mkdir()
            _make_records_100k(making / "records.sqlite")
            making.rename(path.parent)  # whole or not at all
    return path


def _make_records_100k(path: Path) -> None:
    """The first RECORDS_100K_RUN strokes are written by the control loop on the simulated rig in
    virtual time through the real record writer; the file is then filled by SQLite copies of them
    (the cycles, stamps, wall times and run ids shifted past the last: nine more runs of the same
    strokes, as a long reliability test repeats), and opened once more by a writer, which builds
    the copied runs' statistics as it does for a file from before them. Making all 100,000 with the
    loop cost 2.4 min of the suite's 12."""
    import sqlite3
    import sys

    sys.path.insert(0, str(ROOT / "tests" / "daemon"))
    from test_loop import make_loop

    from usmswitch.daemon.records import RecordStore
    from usmswitch.protocol.record import FIELDS, RUN_FIELDS

    store = RecordStore(path, wait_when_behind=20_000)
    loop, _daq, _ = make_loop(target_ns=12_000_000, sink=store.submit, seed=21)
    loop.run_sink = store.submit_run
    while loop.cycle - 1 < RECORDS_100K_RUN:
        loop.run_cycles(30_000_000, RECORDS_100K_RUN - (loop.cycle - 1))
        if loop.state.value == "fault":
            loop.reset_fault()
    assert store.close() and store.dropped == 0
    shifted = {"cycle": "c", "run_id": "r", "wall_ns": "w"}
    shifted.update({f: "t" for f in ("t_cmd_ns", "t_start_ns", "t_depart_ns", "t_arrive_ns")})
    with sqlite3.connect(path) as db:
        runs, t_span, w_span = db.execute(
            "SELECT max(run_id), max(t_arrive_ns) - min(t_cmd_ns) + 30000000, max(wall_ns) - min(wall_ns) + 1"
            " FROM cycles"
        ).fetchone()
        cols = ", ".join(f'"{f}"' for f in FIELDS)
        cycles = ", ".join(f'"{f}" + :{shifted[f]}' if f in shifted else f'"{f}"' for f in FIELDS)
        run_shift = {"run_id": "r", "first_cycle": "c", "last_cycle": "c"}
        run_shift.update(started_wall_ns="w", ended_wall_ns="w")
        run_cols = ", ".join(RUN_FIELDS)
        run_vals = ", ".join(f"{f} + :{run_shift[f]}" if f in run_shift else f for f in RUN_FIELDS)
        for k in range(1, RECORDS_100K // RECORDS_100K_RUN):
            shift = {"c": k * RECORDS_100K_RUN, "r": k * runs, "t": k * t_span, "w": k * w_span}
            db.execute(
                f"INSERT INTO cycles ({cols}) SELECT {cycles} FROM cycles WHERE cycle <= {RECORDS_100K_RUN}",
                shift,
            )
            db.execute(
                f"INSERT INTO runs ({run_cols}) SELECT {run_vals} FROM runs WHERE run_id <= {runs}", shift
            )
    RecordStore(path).close()  # the copied runs' statistics, built as for a file from before them


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


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    """A fresh directory with a short path (/tmp/usm- and eight random characters), for trees of
    Unix sockets: a socket's path is at most 107 bytes, and tmp_path's (longer under pytest-xdist's
    per-worker directories) left too few for a unit's runtime directory and its sockets."""
    import shutil
    import tempfile

    path = Path(tempfile.mkdtemp(prefix="usm-", dir="/tmp"))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)
