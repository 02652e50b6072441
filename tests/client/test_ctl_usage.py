"""usmswitchctl without a daemon: --version, --rig, usage errors (plain and --json), documented exit codes."""

from __future__ import annotations

import argparse
import json
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from usmswitch.client.ctl import args as ctl_args
from usmswitch.protocol.version import PACKAGE_VERSION
from usmswitch.protocol.wire import PROTOCOL_VERSION

BIN = Path(sys.executable).parent / "usmswitchctl"
CTL = [str(BIN)] if BIN.exists() else [sys.executable, "-m", "usmswitch.client.ctl"]


def ctl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CTL, *args], capture_output=True, text=True, timeout=30, check=False)


def test_version() -> None:
    r = ctl("--version")
    assert (
        r.returncode == 0
        and r.stdout.strip() == f"usmswitchctl {PACKAGE_VERSION} (protocol {PROTOCOL_VERSION})"
    )


def test_rig_names_the_instance_socket() -> None:
    r = ctl("--rig", "no-such-rig-xyz", "status")
    assert r.returncode == ctl_args.EXIT_CONNECT, r.stderr
    assert "/run/usmswitch/no-such-rig-xyz/usmswitchd.sock" in r.stderr
    r = ctl("--rig", "../etc", "status")
    assert r.returncode == ctl_args.EXIT_USAGE and "--rig" in r.stderr
    r = ctl("--rig", "a", "--socket", "/x.sock", "status")
    assert r.returncode == ctl_args.EXIT_USAGE and "--socket and --rig" in r.stderr


@pytest.mark.parametrize(
    "args",
    [
        ["--json", "target", "set", "12"],  # no unit: caught before connecting
        ["--json", "frobnicate"],  # argparse's own errors, in JSON too
        ["stats", "--bogus", "--json"],
        ["--json", "history", "-n", "zero"],
        ["--json", "target", "set", "12", "parsecs"],
    ],
)
def test_json_usage_errors_are_json(args: list[str]) -> None:
    r = ctl("--socket", "/nonexistent.sock", *args)
    assert r.returncode == ctl_args.EXIT_USAGE, (r.stdout, r.stderr)
    assert r.stdout == ""
    err = json.loads(r.stderr)["error"]
    assert err["exit"] == 2 and err["message"]


def test_plain_usage_errors_stay_text() -> None:
    r = ctl("frobnicate")
    assert r.returncode == 2 and r.stderr.startswith("usage: usmswitchctl") and "invalid choice" in r.stderr


def test_target_with_the_unit_apart_is_taken_or_shown_the_right_form() -> None:
    # `target set 12 ms` is `12ms`: it gets as far as connecting (exit 3, no daemon here).
    r = ctl("--socket", "/nonexistent.sock", "target", "set", "12", "ms")
    assert r.returncode == ctl_args.EXIT_CONNECT, r.stderr
    r = ctl("--socket", "/nonexistent.sock", "target", "set", "12ms", "now")
    assert r.returncode == ctl_args.EXIT_USAGE and "`target set 12ms`" in r.stderr
    r = ctl("--socket", "/nonexistent.sock", "target", "set", "12", "parsecs")
    assert r.returncode == ctl_args.EXIT_USAGE and "unknown unit 'parsecs'" in r.stderr


def test_every_exit_code_is_documented(repo_root: Path) -> None:
    text = (repo_root / "docs" / "usmswitchctl.md").read_text()
    section = text[text.index("## Exit codes") :]
    documented = {int(m) for m in re.findall(r"^\| (\d+) \|", section, re.M)}
    codes = {v for k, v in vars(ctl_args).items() if k.startswith("EXIT_")}
    assert documented == codes == {0, 1, 2, 3, 4, 130, 141}


def test_a_failed_export_leaves_no_partial_file(tmp_path: Path) -> None:
    # A records file whose row 1500 cannot be read: the export fails after the first chunks are
    # written to out.csv.partial, and must leave neither a .partial nor an out.csv behind.
    from usmswitch.daemon.records import RecordStore
    from usmswitch.protocol.record import CycleRecord

    state = tmp_path / "state"
    state.mkdir()
    with RecordStore(state / "records.sqlite", driver="sim", rig="t") as store:
        for cycle in range(1, 2001):
            t = cycle * 50_000_000
            store.submit(
                CycleRecord.build(
                    cycle=cycle,
                    direction=(cycle - 1) % 2,
                    mode="closed",
                    target_ns=12_000_000,
                    order=1,
                    coefficients=(0.99,),
                    t_hat_ns=10_500_000,
                    delay_ns=1_500_000,
                    t_cmd_ns=t,
                    t_start_ns=t + 1_500_000,
                    t_depart_ns=t + 1_800_000,
                    t_arrive_ns=t + 12_000_000,
                    wall_ns=1_700_000_000 * 10**9 + cycle,
                )
            )
    con = sqlite3.connect(state / "records.sqlite")
    with con:
        con.execute("UPDATE cycles SET coefficients = 'not json' WHERE cycle = 1500")
    con.close()
    out = tmp_path / "out.csv"
    r = ctl("export", "--csv", str(out), "--state-dir", str(state))
    assert r.returncode == ctl_args.EXIT_USAGE, r.stderr[-2000:]
    assert "reading the records failed" in r.stderr and "Traceback" not in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state"]  # no out.csv, no out.csv.partial
    # The same file up to the bad row exports whole.
    r = ctl("export", "--csv", str(out), "--state-dir", str(state), "--last", "1499")
    assert r.returncode == 0 and "1499 records written" in r.stdout
    assert not Path(f"{out}.partial").exists()


def test_a_mistyped_command_gets_a_did_you_mean() -> None:
    """Issue 37's bites: `usmswitchctl satus` listed 17 commands and left the reader to find it."""
    r = ctl("satus")
    assert r.returncode == 2 and r.stderr.rstrip().endswith("did you mean 'status' or 'stats'?"), r.stderr
    j = ctl("--json", "cylce")
    assert j.returncode == 2 and json.loads(j.stderr)["error"]["message"].endswith("did you mean 'cycle'?")
    far = ctl("zzzz")
    assert far.returncode == 2 and "did you mean" not in far.stderr


def test_a_commands_help_shows_its_own_options_first_and_the_connection_flags_once_after() -> None:
    """Issue 37's bites: every command's --help began with 12 lines of connection options."""
    from usmswitch.client.ctl.parser import CONNECTION_GROUP, build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name in sub.choices:
        r = ctl(name, "--help")
        assert r.returncode == 0, (name, r.stderr)
        usage, rest = r.stdout.split("\n\n", 1)
        own, heading, connection = rest.partition(f"\n{CONNECTION_GROUP}:\n")
        assert heading and "--socket" in connection and "--json" in connection, (name, r.stdout)
        assert "--socket" not in own and "--timeout" not in own, (name, own)
        assert r.stdout.count(CONNECTION_GROUP) == 1
        # The usage line too: the command's own options before the connection flags.
        flags = re.findall(r"\[(--?[\w-]+)", usage)
        assert flags.index("--socket") == len(flags) - 6, (name, flags)
