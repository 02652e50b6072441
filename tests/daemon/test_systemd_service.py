"""The shipped units under a real systemd (issue 22): installed as docs/service.md says, started,
driven through the socket by a non-root member of group usmswitch, stopped, killed and frozen.

systemd boots as PID 1 of a namespace of its own (tests/realsystemd.py); the daemon runs from a venv
made with Debian's /usr/bin/python3 under /opt (ProtectHome hides /root and /home; PrivateTmp and
the namespace hide /tmp), through a drop-in that changes ExecStart only. Every other line of the
units is as shipped. The rig is the simulated one in real time (`[driver] kind = "sim"`).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import realsystemd
from checkout import building_from

CI = os.environ.get("CI") == "true"


def _free_port() -> int:
    """A loopback port nobody holds now: the namespace shares the host's network, where a reader's
    own `make run` may hold the panel's 8790."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: The panel's port for this session's units.
PANEL_PORT = _free_port()
NOBODY = 65534
DEBIAN_PYTHON = Path("/usr/bin/python3")


def _skip_or_fail(why: str) -> None:
    if CI:
        pytest.fail(f"{why} (CI=true: the real-systemd test must run)")
    pytest.skip(why)


@pytest.fixture(scope="module")
def system_venv(repo_root: Path) -> Iterator[Path]:
    """A venv of Debian's python with usmswitch installed (not editable: the checkout may be under
    /root, which the unit's ProtectHome hides)."""
    if not DEBIAN_PYTHON.exists():
        _skip_or_fail(f"{DEBIAN_PYTHON} is missing (apt: python3, python3-venv)")
    if os.geteuid() != 0:
        _skip_or_fail("the real-systemd test needs root")
    venv = Path("/opt") / f"usmswitch-test-{uuid.uuid4().hex[:8]}"
    try:
        subprocess.run([str(DEBIAN_PYTHON), "-m", "venv", str(venv)], check=True, capture_output=True)
        with building_from(repo_root):
            pip = subprocess.run(
                [str(venv / "bin" / "pip"), "install", "--quiet", str(repo_root)],
                capture_output=True,
                text=True,
                timeout=600,
            )
        assert pip.returncode == 0, pip.stderr[-3000:]
        yield venv
    finally:
        shutil.rmtree(venv, ignore_errors=True)


@pytest.fixture
def systemd() -> Iterator[realsystemd.BootedSystemd]:
    try:
        booted = realsystemd.BootedSystemd()
    except realsystemd.BootError as exc:
        _skip_or_fail(f"no real systemd here: {exc}")
    try:
        yield booted
    finally:
        booted.close()


class Unit:
    """One of the shipped units, installed into a booted systemd as docs/service.md says."""

    def __init__(self, sd: realsystemd.BootedSystemd, repo: Path, venv: Path, template: bool) -> None:
        self.sd = sd
        self.root = Path(f"/proc/{sd.pid}/root")  # the namespace's file system, seen from here
        self.name = "usmswitchd@rigA.service" if template else "usmswitchd.service"
        self.file = "usmswitchd@.service" if template else "usmswitchd.service"
        self.rig = "rigA" if template else None
        config = "/etc/usmswitch/rigA.toml" if template else "/etc/usmswitch/usmswitchd.toml"
        run = sd.run
        run(["install", "-m644", f"systemd/{self.file}", "/usr/lib/systemd/system/"], cwd=str(repo))
        run(
            ["install", "-m644", "systemd/usmswitch.sysusers", "/usr/lib/sysusers.d/usmswitch.conf"],
            cwd=str(repo),
        )
        run(["systemd-sysusers"])
        run(["install", "-Dm640", "-g", "usmswitch", "systemd/usmswitchd.toml", config], cwd=str(repo))
        # The rig is the simulated one: the example config's driver line, and nothing else, changed.
        cfg = self.root / config.lstrip("/")
        text = cfg.read_text()
        assert 'kind = "serial"' in text
        text = text.replace('kind = "serial"', 'kind = "sim"', 1)
        # The panel on loopback, as docs/panel.md's "As a service" says to set it.
        assert "[web]" in text and '\nlisten = ""                # e.g. "8790"' in text
        cfg.write_text(
            text.replace('\nlisten = ""                # e.g. "8790"', f'\nlisten = "{PANEL_PORT}"  #')
        )
        # The drop-in `systemctl edit` would write: ExecStart only, at this venv.
        shipped = (repo / "systemd" / self.file).read_text()
        exec_line = re.search(r"^ExecStart=/usr/bin/usmswitchd (.*)$", shipped, re.M)
        assert exec_line
        dropin = self.root / "etc/systemd/system" / f"{self.file}.d"
        dropin.mkdir(parents=True)
        (dropin / "venv.conf").write_text(
            f"[Service]\nExecStart=\nExecStart={venv}/bin/usmswitchd {exec_line.group(1)}\n"
        )
        sd.systemctl("daemon-reload")
        self.venv = venv
        self.gid = int(
            next(
                line
                for line in (self.root / "etc/group").read_text().splitlines()
                if line.startswith("usmswitch:")
            ).split(":")[2]
        )

    # -- the service ---------------------------------------------------------------------------
    def start(self) -> dict[str, str]:
        started = self.sd.systemctl("start", self.name, check=False)  # Type=notify: once READY=1 came
        if started.returncode != 0:
            raise AssertionError(
                f"systemctl start {self.name}: {started.stderr.strip()}\n-- its journal --\n"
                + self.sd.journal(self.name)[-4000:]
            )
        return self.sd.wait_for(self.name, ActiveState="active", SubState="running")

    def props(self) -> dict[str, str]:
        return self.sd.show(
            self.name, "ActiveState", "SubState", "Result", "NRestarts", "MainPID", "StatusText"
        )

    def query(self, sql: str, *args: object) -> list[list[object]]:
        """Rows of the daemon's records file, read inside the namespace (as the operator would)."""
        code = (
            "import glob, json, sqlite3, sys\n"
            "(path,) = glob.glob('/var/lib/usmswitch/**/records.sqlite', recursive=True)\n"
            "db = sqlite3.connect(path)\n"
            "print(json.dumps(db.execute(sys.argv[1], json.loads(sys.argv[2])).fetchall()))\n"
        )
        out = self.sd.run([str(self.venv / "bin" / "python"), "-c", code, sql, json.dumps(args)]).stdout
        return json.loads(out)

    def cycles_of_run(self, run_id: int) -> list[int]:
        return [r[0] for r in self.query("SELECT cycle FROM cycles WHERE run_id = ? ORDER BY cycle", run_id)]

    # -- a lab script as a member of group usmswitch who is not root ---------------------------
    def script(self, body: str, timeout: float = 120) -> subprocess.Popen[str]:
        rig = repr(self.rig)
        code = f"import json, sys\nfrom usmswitch.client import Client\nrig_name = {rig}\n{body}"
        cmd = ["nsenter", "-t", str(self.sd.pid), "-m", "-p", "-u"]
        cmd += ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", f"--groups={self.gid}", "--"]
        cmd += [str(self.venv / "bin" / "python"), "-c", code]
        env = {"PATH": "/usr/bin:/bin", "HOME": "/nonexistent"}
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


RUN_200 = """
with Client(rig=rig_name) as rig:
    run = rig.run(count=200, period="30ms", target="12ms")
    cycles = [rec["cycle"] for rec in run]
    print(json.dumps({"run": run.run_id, "cycles": cycles, "end": run.info["end_reason"]}))
"""

# The panel under the unit's sandbox: its URL from status, its token from the file beside the socket
# (readable by group usmswitch), the page, and the token accepted.
PANEL = """
import urllib.request
from usmswitch.protocol.sockets import web_token_path
with Client(rig=rig_name) as rig:
    url = rig.status()["web_url"]
    token = web_token_path(rig.address).read_text().strip()
page = urllib.request.urlopen(url, timeout=10).read()
ask = urllib.request.Request(url + "api/session", headers={"X-Usmswitch-Token": token})
session = json.load(urllib.request.urlopen(ask, timeout=10))
print(json.dumps({"url": url, "page": b'id="estop"' in page, **session}))
"""

# Prints each stroke as it is published (after its commit), until the daemon goes.
RUN_UNTIL_KILLED = """
try:
    with Client(rig=rig_name) as rig:
        run = rig.run(count=2000, period="30ms", target="12ms")
        print(json.dumps({"run": run.run_id}), flush=True)
        for rec in run:
            print(rec["cycle"], flush=True)
except Exception as exc:
    print("gone:", type(exc).__name__, exc, flush=True)
"""


@pytest.mark.parametrize("template", [False, True], ids=["usmswitchd", "usmswitchd@rigA"])
def test_the_shipped_unit_runs_stops_restarts_and_is_watched(
    systemd: realsystemd.BootedSystemd, system_venv: Path, repo_root: Path, template: bool
) -> None:
    unit = Unit(systemd, repo_root, system_venv, template)

    # Started: active (READY=1 came), a STATUS line in `systemctl status`.
    unit.start()
    status = systemd.systemctl("status", unit.name, check=False).stdout
    assert re.search(r"^\s+Status: \".+\"", status, re.M), status

    # 200 strokes through the socket by nobody in group usmswitch.
    proc = unit.script(RUN_200)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    result = json.loads(out.strip().splitlines()[-1])
    assert len(result["cycles"]) == 200 and result["end"] == "done", result

    # The panel is served under the sandbox, and a member of the socket's group may act from it.
    proc = unit.script(PANEL)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    panel = json.loads(out.strip().splitlines()[-1])
    assert panel == {"url": f"http://127.0.0.1:{PANEL_PORT}/", "page": True, "control": True, "message": None}

    # Stopped: inactive, result success, every stroke of the run in the file.
    systemd.systemctl("stop", unit.name)
    props = unit.props()
    assert (props["ActiveState"], props["Result"]) == ("inactive", "success"), props
    assert unit.cycles_of_run(result["run"]) == result["cycles"]

    # Started again it warm-starts from the records (both directions' last strokes).
    unit.start()
    journal = systemd.journal(unit.name)
    warm = [json.loads(line) for line in journal.splitlines() if '"warm start"' in line]
    assert warm and all(w["strokes"] >= 50 for w in warm[-2:]), warm

    # SIGKILL mid-run: restarted (Restart=on-failure), no stroke the client was told of is lost.
    restarts = int(unit.props()["NRestarts"])
    proc = unit.script(RUN_UNTIL_KILLED)
    assert proc.stdout is not None
    seen: list[int] = []
    head = json.loads(proc.stdout.readline())
    for line in proc.stdout:
        seen.append(int(line))
        if len(seen) == 60:
            break
    systemd.systemctl("kill", "-s", "KILL", unit.name)
    rest, _ = proc.communicate(timeout=30)
    seen += [int(x) for x in rest.splitlines() if x.strip().isdigit()]
    assert "gone:" in rest
    got = systemd.wait_for(
        unit.name, timeout=30, NRestarts=str(restarts + 1), ActiveState="active", SubState="running"
    )
    assert got["NRestarts"] == str(restarts + 1)
    kept = set(unit.cycles_of_run(head["run"]))
    assert set(seen) <= kept, sorted(set(seen) - kept)
    journal = systemd.journal(unit.name)
    warm = [json.loads(line) for line in journal.splitlines() if '"warm start"' in line]
    assert len(warm) >= 6 and all(w["strokes"] >= 50 for w in warm[-2:]), warm[-2:]

    # A loop frozen past WatchdogSec: killed by the watchdog and restarted.
    pid = unit.props()["MainPID"]
    systemd.run(["kill", "-STOP", pid])
    t0 = time.monotonic()
    systemd.wait_for(
        unit.name, timeout=60, NRestarts=str(restarts + 2), ActiveState="active", SubState="running"
    )
    took = time.monotonic() - t0
    assert took >= 9, f"restarted after {took:.1f} s, before WatchdogSec=10s could pass"
    assert (
        "Watchdog timeout" in systemd.run(["journalctl", "--no-pager", "-u", unit.name], check=False).stdout
    )

    systemd.systemctl("stop", unit.name)
    props = unit.props()
    assert (props["ActiveState"], props["Result"]) == ("inactive", "success"), props


def test_a_refused_nice_is_a_warning_not_an_exit(
    systemd: realsystemd.BootedSystemd, system_venv: Path, repo_root: Path
) -> None:
    """The unit as it was before issue 22 (setpriority denied by its syscall filter): the server
    process and the loop carry on, each refusal a warning saying what it costs."""
    unit = Unit(systemd, repo_root, system_venv, template=False)
    dropin = unit.root / "etc/systemd/system/usmswitchd.service.d/deny.conf"
    dropin.write_text("[Service]\nSystemCallFilter=~setpriority sched_setscheduler\n")
    systemd.systemctl("daemon-reload")
    unit.start()
    proc = unit.script(RUN_200.replace("count=200", "count=20"))
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    journal = systemd.journal(unit.name)
    warnings = [
        json.loads(line) for line in journal.splitlines() if line.startswith("{") and '"warning"' in line
    ]
    nice = [w for w in warnings if w["event"].startswith("nice refused")]
    assert {w["process"] for w in nice} >= {"server"}, warnings
    assert all(w["cost"] for w in nice)
    fifo = [w for w in warnings if w.get("option") == "sched_fifo_priority"]
    assert fifo and "EPERM" in fifo[0]["reason"], warnings
    systemd.systemctl("stop", unit.name)
    assert unit.props()["Result"] == "success"


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-v"]))
