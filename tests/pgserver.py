"""A real PostgreSQL 15 for tests and benchmarks: a throwaway cluster in a temporary directory.

initdb refuses to run as root, so under root the cluster belongs to an unprivileged user (the
`postgres` user the Debian package creates, else one made with useradd). It listens on a free
loopback port (password auth, scram-sha-256) and on a Unix socket in its own directory (trust,
for the superuser that sets databases up). Without the Debian package `postgresql-15`, `require()`
skips with one line naming it, except under CI=true, where that is a failure (.ci/run installs it).
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path
from typing import Any

PG_BIN = Path(os.environ.get("USMSWITCH_PG_BIN", "/usr/lib/postgresql/15/bin"))
PACKAGE = "postgresql-15"
SUPERUSER = "postgres"
#: The role the daemons ship as, and its password.
ROLE = "usmswitch"
PASSWORD = "rig-secret-1"
TEST_USER = "usmswitch-pgtest"


def missing() -> str | None:
    """Why a server cannot be started here (None: it can)."""
    for tool in ("initdb", "pg_ctl", "postgres"):
        if not (PG_BIN / tool).exists():
            return f"PostgreSQL 15 missing ({PG_BIN / tool}): apt-get install {PACKAGE}"
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return "psycopg missing: pip install -e '.[postgres]'"
    return None


def require() -> None:
    """Skip the calling test (fail it under CI=true) when PostgreSQL cannot be run here."""
    import pytest

    why = missing()
    if why is None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(why, pytrace=False)
    pytest.skip(why)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _owner() -> pwd.struct_passwd | None:
    """The unprivileged user that owns the cluster when we are root (None: we are not root)."""
    if os.geteuid() != 0:
        return None
    for name in (SUPERUSER, TEST_USER):
        try:
            return pwd.getpwnam(name)
        except KeyError:
            continue
    subprocess.run(
        ["useradd", "--system", "--no-create-home", "--shell", "/usr/sbin/nologin", TEST_USER], check=True
    )
    return pwd.getpwnam(TEST_USER)


class PgServer:
    """One PostgreSQL cluster: start, stop (as a crash or an outage would), databases for tests."""

    def __init__(self) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="usm-pg-"))
        self.data = self.dir / "data"
        self.sockdir = self.dir
        self.port = _free_port()
        self.owner = _owner()
        if self.owner is not None:
            os.chown(self.dir, self.owner.pw_uid, self.owner.pw_gid)
        pwfile = self.dir / "pw"
        pwfile.write_text(PASSWORD + "\n")
        if self.owner is not None:
            os.chown(pwfile, self.owner.pw_uid, self.owner.pw_gid)
        self._run(
            "initdb", "-D", str(self.data), "-U", SUPERUSER, "--auth-local=trust",
            "--auth-host=scram-sha-256", f"--pwfile={pwfile}", "-E", "UTF8", "--no-sync",
        )  # fmt: skip
        self.started = False
        self._roles_made = False

    def _run(self, tool: str, *args: str) -> None:
        kw: dict[str, Any] = {}
        if self.owner is not None:
            kw = {"user": self.owner.pw_uid, "group": self.owner.pw_gid, "extra_groups": []}
        proc = subprocess.run(
            [str(PG_BIN / tool), *args], capture_output=True, text=True, check=False, cwd=self.dir, **kw
        )
        if proc.returncode != 0:
            raise RuntimeError(
                f"{tool} failed ({proc.returncode}): {proc.stdout[-2000:]} {proc.stderr[-2000:]}"
            )

    def start(self) -> None:
        """Start (or start again) on the same port and data."""
        opts = (
            f"-p {self.port} -k {self.sockdir} -c listen_addresses=127.0.0.1 -c fsync=off"
            " -c full_page_writes=off -c max_connections=50"
        )
        self._run(
            "pg_ctl", "-D", str(self.data), "-o", opts, "-l", str(self.dir / "log"), "-w", "-t", "30", "start"
        )
        self.started = True

    def stop(self, mode: str = "fast") -> None:
        """Stop: "fast" ends client sessions (an outage), "immediate" is a crash."""
        if self.started:
            self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "30", "stop")
            self.started = False

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.dir, ignore_errors=True)

    def admin(
        self, sql: str, dbname: str = "postgres", params: tuple[Any, ...] = ()
    ) -> list[tuple[Any, ...]]:
        """Run SQL as the superuser over the Unix socket (autocommit: CREATE DATABASE works)."""
        import psycopg

        with psycopg.connect(
            host=str(self.sockdir), port=self.port, user=SUPERUSER, dbname=dbname, autocommit=True
        ) as conn:
            cur = conn.execute(sql, params)
            return cur.fetchall() if cur.description else []

    def database(self, name: str) -> str:
        """A new database owned by the shipping role; its URL (password in it) over TCP."""
        if not self._roles_made:
            self.admin(f"CREATE ROLE {ROLE} LOGIN PASSWORD '{PASSWORD}'")
            self._roles_made = True
        self.admin(f'CREATE DATABASE "{name}" OWNER {ROLE}')
        return self.url(name)

    def url(self, dbname: str, password: str = PASSWORD, user: str = ROLE) -> str:
        return f"postgresql://{user}:{password}@127.0.0.1:{self.port}/{dbname}"

    def query(self, dbname: str, sql: str, params: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        """Rows of a query in a test's database (as the superuser)."""
        return self.admin(sql, dbname, params)


def synthetic_records(first: int, count: int, seed: int = 1, run_id: int | None = None) -> list[Any]:
    """Strokes as the loop makes them, with a scatter of errors, late and stalled ones and None
    stamps: what a shipper must carry over field for field."""
    import random

    from usmswitch.protocol.record import CycleRecord, Flag

    rng = random.Random(seed * 1_000_003 + first)
    out = []
    for cycle in range(first, first + count):
        t_cmd = seed * 10**15 + cycle * 50_000_000  # another seed: another clock, as another file's
        delay = 1_500_000 + rng.randrange(-50_000, 50_000)
        t_start = t_cmd + delay + rng.randrange(0, 80_000)
        stall = rng.random() < 0.01
        operating = 10_500_000 + rng.randrange(-300_000, 300_000)
        out.append(
            CycleRecord.build(
                cycle=cycle,
                direction=(cycle - 1) % 2,
                mode="closed",
                target_ns=12_000_000,
                order=1,
                coefficients=(0.9 + rng.random() / 10,),
                t_hat_ns=10_500_000 + rng.randrange(-1000, 1000),
                delay_ns=delay,
                t_cmd_ns=t_cmd,
                t_start_ns=t_start,
                t_depart_ns=None if stall else t_start + 300_000,
                t_arrive_ns=None if stall else t_start + operating,
                lateness_ns=t_start - t_cmd - delay,
                temperature_c=None if cycle % 7 == 0 else 25.0 + cycle / 1e4,
                frequency_hz=40_000.0,
                flags=(Flag.STALL | Flag.FAULT) if stall else (Flag.LATE if rng.random() < 0.05 else 0),
                wall_ns=1_700_000_000_000_000_000 + t_cmd + operating,
                run_id=run_id,
            )
        )
    return out
