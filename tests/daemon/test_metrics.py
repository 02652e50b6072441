"""The Prometheus page: parsed with prometheus_client's own parser, it agrees with the records."""

from __future__ import annotations

import socket
import sqlite3
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections import Counter
from pathlib import Path
from typing import Any

import daemonproc
import msgpack
import pgserver
import pytest
from prometheus_client.parser import text_string_to_metric_families

from usmswitch.client import Client
from usmswitch.fleet.metrics import FEEDS, StrokeMetrics
from usmswitch.protocol.record import Flag, RunRecord
from usmswitch.web.metrics_page import MetricsPage

# A stroke's outcome written out again here, apart from metrics.outcome(): the flag bits of
# docs/records.md in the order of docs/fleet.md, as SQL both SQLite and PostgreSQL run.
OUTCOME_BITS = ((4, "stall"), (32, "estop"), (128, "aborted"), (16, "fault"), (256, "partial"), (1, "late"))
OUTCOME_SQL = "CASE {} ELSE 'ok' END".format(
    " ".join(f"WHEN (flags & {b}) <> 0 THEN '{o}'" for b, o in OUTCOME_BITS)
)
DIRECTION = {0: "on", 1: "off"}


def samples(text: str) -> dict[tuple[str, frozenset[tuple[str, str]]], float]:
    """Every sample of a page, by name and labels."""
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, frozenset(s.labels.items()))] = s.value
    return out


def value(page: dict[Any, float], name: str, **labels: str) -> float:
    return page[(name, frozenset(labels.items()))]


def sqlite_counts(db: Path) -> Counter[tuple[str, str]]:
    con = sqlite3.connect(db)
    rows = con.execute(f"SELECT direction, {OUTCOME_SQL} AS o, count(*) FROM cycles GROUP BY direction, o")
    out = Counter({(DIRECTION[d], o): n for d, o, n in rows})
    con.close()
    return out


def page_counts(page: dict[Any, float], rig: str) -> Counter[tuple[str, str]]:
    out: Counter[tuple[str, str]] = Counter()
    for (name, labels), v in page.items():
        lab = dict(labels)
        if name == "usmswitch_strokes_total" and lab["rig"] == rig and v:
            out[(lab["direction"], lab["outcome"])] = int(v)
    return out


def test_page_from_records_counts_every_outcome_and_buckets_each_value(tmp_path: Path):
    metrics = StrokeMetrics()
    metrics.on_run(RunRecord(run_id=3, kind="cycling", first_cycle=1, started_wall_ns=0))
    records = pgserver.synthetic_records(1, 400, run_id=3)
    extra = (
        0, Flag.ESTOP | Flag.FAULT, Flag.ABORTED, Flag.FAULT, Flag.PARTIAL, Flag.WARMUP,
        Flag.LATE | Flag.CLAMPED, Flag.STALL | Flag.FAULT, Flag.BOUNCE,
    )  # fmt: skip
    for i, rec in enumerate(records):  # every outcome in both directions, and flags that leave "ok"
        rec.flags |= extra[i % len(extra)]
    metrics.add(records[:250])
    metrics.add(records[250:])
    snaps = {FEEDS[0]: msgpack.packb(metrics.snapshot())}
    page = samples(MetricsPage(lambda: (snaps, {"unix": 2, "tcp": 0})).render("")[0].decode())
    db = tmp_path / "r.sqlite"
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE cycles (cycle, direction, flags, error_ns, operating_ns, lateness_ns)")
    con.executemany(
        "INSERT INTO cycles VALUES (?, ?, ?, ?, ?, ?)",
        [(r.cycle, r.direction, r.flags, r.error_ns, r.operating_ns, r.lateness_ns) for r in records],
    )
    con.commit()
    expected = sqlite_counts(db)
    assert len(expected) == 14  # 7 outcomes x 2 directions all occur
    assert page_counts(page, "") == expected
    for d in (0, 1):
        direction = DIRECTION[d]
        for name, column in (
            ("usmswitch_error_seconds", "error_ns"),
            ("usmswitch_operating_seconds", "operating_ns"),
            ("usmswitch_start_lateness_seconds", "lateness_ns"),
        ):
            (n,) = con.execute(f"SELECT count({column}) FROM cycles WHERE direction = ?", (d,)).fetchone()
            assert value(page, f"{name}_bucket", rig="", direction=direction, le="+Inf") == n
        for le_s, le_ns in (("-0.0001", -100_000), ("0.0", 0), ("5e-05", 50_000), ("0.0002", 200_000)):
            (n,) = con.execute(
                "SELECT count(*) FROM cycles WHERE direction = ? AND error_ns <= ?", (d, le_ns)
            ).fetchone()
            assert value(page, "usmswitch_error_seconds_bucket", rig="", direction=direction, le=le_s) == n
        (total,) = con.execute("SELECT sum(operating_ns) FROM cycles WHERE direction = ?", (d,)).fetchone()
        assert value(page, "usmswitch_operating_seconds_sum", rig="", direction=direction) == pytest.approx(
            total / 1e9, rel=1e-12
        )
        errors = [r.error_ns for r in records if r.direction == d and r.error_ns is not None]
        mean = sum(errors) / len(errors)
        std = (sum((e - mean) ** 2 for e in errors) / (len(errors) - 1)) ** 0.5
        assert value(page, "usmswitch_run_error_std_seconds", rig="", direction=direction) == pytest.approx(
            std / 1e9, rel=1e-9
        )
    assert value(page, "usmswitch_socket_clients", rig="", transport="unix") == 2
    assert value(page, "usmswitch_run_id", rig="") == 3


def test_the_loops_process_never_loads_prometheus_client():
    code = (
        "import sys; import usmswitch.daemon.service, usmswitch.fleet.hooks, usmswitch.fleet.metrics\n"
        "print('prometheus_client' in sys.modules, 'psycopg' in sys.modules, 'aiohttp' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False", "False"]


def scrape(url: str, method: str = "GET", accept: str = "") -> tuple[int, str, str]:
    req = urllib.request.Request(url, method=method, headers={"Accept": accept} if accept else {})
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, resp.headers["Content-Type"], resp.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers["Content-Type"], exc.read().decode()


def test_daemon_page_agrees_with_its_records_file(tmp_path: Path):
    sock = tmp_path / "d.sock"
    args = daemonproc.daemon_args(tmp_path, "--rig", "benchA", "--metrics", "127.0.0.1:0", "--no-autostart")
    proc = daemonproc.spawn(args)
    try:
        daemonproc.wait_serving(sock, proc)
        with Client(str(sock), timeout=10) as c, Client(str(sock), timeout=10):
            url = c.status()["metrics_url"]
            assert url.startswith("http://127.0.0.1:") and url.endswith("/metrics")
            done = list(c.run(count=30, period="20ms", target="12ms", timeout=10))
            assert len(done) == 30
            # Strokes that cannot make a target shorter than the stroke: LATE (and CLAMPED).
            for rec in c.run(count=10, period="20ms", target="6ms", allow_late=True, timeout=10):
                assert rec["flags"] & Flag.LATE
            c.estop()
            time.sleep(0.3)  # the state snapshot follows the fault at the loop's next slack
            status, ctype, text = scrape(url)
            c.reset_fault()
        assert status == 200 and ctype.startswith("text/plain; version=0.0.4")
        page = samples(text)
        assert page_counts(page, "benchA") == sqlite_counts(tmp_path / "state" / "records.sqlite")
        assert sum(page_counts(page, "benchA").values()) == 40
        assert value(page, "usmswitch_fault", rig="benchA") == 1
        assert value(page, "usmswitch_state", rig="benchA", state="fault") == 1
        assert value(page, "usmswitch_socket_clients", rig="benchA", transport="unix") >= 2
        assert value(page, "usmswitch_target_seconds", rig="benchA", direction="on") == 0.006
        assert value(page, "usmswitch_info", rig="benchA", driver="sim", version=c.status()["version"]) == 1
        assert 0.005 < value(page, "usmswitch_predicted_seconds", rig="benchA", direction="off") < 0.02
        time.sleep(1.2)
        assert value(samples(scrape(url)[2]), "usmswitch_fault", rig="benchA") == 0  # reset seen
        # OpenMetrics when asked; HEAD, other paths and methods.
        status, ctype, text = scrape(url, accept="application/openmetrics-text; version=1.0.0")
        assert status == 200 and ctype.startswith("application/openmetrics-text") and text.endswith("# EOF\n")
        assert scrape(url, method="HEAD")[0] == 200
        assert scrape(url.replace("/metrics", "/nope"))[0] == 404
        assert scrape(url, method="POST")[0] == 405
        host, port = url.split("/")[2].split(":")
        # Kept alive between scrapes (as Prometheus scrapes), pipelined too, answered 20 ms apart
        # at the most (a hammering scraper waits instead of keeping a core busy); "close" honoured.
        with socket.create_connection((host, int(port)), timeout=10) as raw:
            get = f"GET /metrics HTTP/1.1\r\nHost: {host}\r\n".encode()
            t0 = time.monotonic()
            raw.sendall((get + b"\r\n") * 9 + get + b"Connection: close\r\n\r\n")
            replies = b""
            while chunk := raw.recv(65_536):  # until the server closes, after the tenth
                replies += chunk
            took = time.monotonic() - t0
            assert replies.count(b"HTTP/1.1 200 OK") == 10 and replies.count(b"# HELP usmswitch_info") == 10
            assert replies.count(b"Connection: keep-alive") == 9 and replies.count(b"Connection: close") == 1
            assert took >= 9 * 0.020
        with socket.create_connection((host, int(port)), timeout=10) as raw:
            raw.sendall(b"x" * 10_000)  # no head in sight: refused, not buffered forever
            assert raw.recv(100).split(b" ")[1] == b"400"  # aiohttp's parser: the line is too long
    finally:
        err = daemonproc.stop(proc)
    assert proc.returncode == 0, err.decode()[-2000:]


def test_a_metrics_port_in_use_stops_the_daemon_naming_it(tmp_path: Path):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        args = daemonproc.daemon_args(tmp_path, "--metrics", f"127.0.0.1:{port}")
        proc = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3
    assert f"cannot listen for the metrics page on 127.0.0.1:{port}" in proc.stderr


def test_the_grafana_dashboard_asks_only_for_metrics_the_page_has(repo_root: Path):
    import json
    import re

    metrics = StrokeMetrics()
    metrics.on_run(RunRecord(run_id=1, kind="cycling", first_cycle=1, started_wall_ns=0))
    metrics.add(pgserver.synthetic_records(1, 20, run_id=1))
    state = {
        "rig": "r", "driver": "sim", "version": "0", "state": "cycling", "fault": None,
        "targets_ns": [12_000_000, 12_000_000], "records": {"backlog": 0, "writer_error": None},
        "postgres": {"connected": True, "lag": 0, "shipped_cycle": 20, "shipped": 20, "error_count": 0},
    }  # fmt: skip
    snaps = {FEEDS[0]: msgpack.packb(metrics.snapshot()), FEEDS[1]: msgpack.packb(state)}
    names = {name for name, _ in samples(MetricsPage(lambda: (snaps, {"unix": 0})).render("")[0].decode())}
    dashboard = json.loads((repo_root / "systemd" / "grafana-usmswitch.json").read_text())
    exprs = [t["expr"] for p in dashboard["panels"] for t in p["targets"]]
    exprs.append(dashboard["templating"]["list"][1]["query"]["query"])
    used = {m for e in exprs for m in re.findall(r"usmswitch_\w+", e)}
    assert len(used) >= 15 and used <= names, sorted(used - names)
    fleet = (repo_root / "docs" / "fleet.md").read_text()  # and docs/fleet.md explains each
    documented = set(re.findall(r"`(usmswitch_\w+)`", fleet))
    families = {re.sub(r"_(bucket|sum|count)$", "", n) for n in names}
    assert families <= documented | {n for n in documented if n.endswith("_total")}, sorted(
        families - documented
    )
