"""Issue 38: a run's label and notes, set at its start, edited during and after it (`annotate_run`),
through a real usmswitchd subprocess and its Unix socket, read back by every reader."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from usmswitch.client import Client, InvalidParams, RecordsFile, WrongState

sys.path.insert(0, str(Path(__file__).parent))
import daemonproc
from test_runs import PERIOD, Rig

BOB = "bob@elsewhere pid 1 (bob.py)"


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    r = Rig(tmp_path_factory.mktemp("labels"))
    yield r
    daemonproc.stop(r.proc)
    assert r.proc.returncode == 0


def _run_note(lab: Client, run_id: int, timeout: float = 20.0) -> dict:
    """The next `run` notification of `run_id`."""
    while True:
        note = lab.next_notification(timeout)
        if note.topic == "run" and note.payload["run_id"] == run_id:
            return note.payload


def test_a_label_and_notes_given_at_the_start_are_the_runs(rig: Rig) -> None:
    with rig.client() as lab:
        run = lab.run(count=6, period=PERIOD, target="12ms", label="sweep-12", notes="first try\nT = 12 ms")
        info = run.wait()
        assert (info["label"], info["notes"]) == ("sweep-12", "first try\nT = 12 ms")
        listed = {r["run_id"]: r for r in lab.runs()}[run.run_id]
        assert (listed["label"], listed["notes"]) == ("sweep-12", "first try\nT = 12 ms")
        assert lab.stats(run.run_id)["run"]["label"] == "sweep-12"
        plain = lab.run(count=2, period=PERIOD).wait()  # none given: none
        assert (plain["label"], plain["notes"]) == (None, None)
    with RecordsFile(rig.tmp / "state") as f:
        assert f.run(run.run_id)["label"] == "sweep-12"


def test_notes_edited_after_the_run_by_its_owner_or_an_operator(rig: Rig) -> None:
    with rig.client() as lab:
        run_id = lab.run(count=4, period=PERIOD, label="drift").wait()["run_id"]
        lab.subscribe("run")
        edited = lab.annotate_run(run_id, "drift seen after stroke 3")
        assert (edited["label"], edited["notes"]) == ("drift", "drift seen after stroke 3")
        assert _run_note(lab, run_id)["notes"] == "drift seen after stroke 3"  # subscribers are told
        assert {r["run_id"]: r for r in lab.runs()}[run_id]["notes"] == "drift seen after stroke 3"
        relabelled = lab.annotate_run(run_id, label="drift-2")  # notes left as they are
        assert (relabelled["label"], relabelled["notes"]) == ("drift-2", "drift seen after stroke 3")
        assert lab.annotate_run(run_id, "", label="")["label"] is None  # "" clears
        assert {r["run_id"]: r for r in lab.runs()}[run_id]["notes"] is None

        # Another person's run: refused by mistake, done on purpose.
        with pytest.raises(WrongState, match=r"its owner edits its label and notes, or an operator"):
            lab.annotate_run(run_id, "not mine", owner=BOB)
        by_bob = lab.annotate_run(run_id, "checked by bob", owner=BOB, operator=True)
        assert by_bob["notes"] == "checked by bob"
        # The same person from another process (usmswitchctl beside the script) is its owner.
        me = lab.runs()[-1]["settings"]["owner"].split(" pid ")[0]
        assert lab.annotate_run(run_id, "mine", owner=f"{me} pid 99 (usmswitchctl)")["notes"] == "mine"

        with pytest.raises(InvalidParams, match="no run 9999"):
            lab.annotate_run(9999, "x")
    with RecordsFile(rig.tmp / "state") as f:
        assert f.run(run_id)["notes"] == "mine"


def test_notes_edited_during_a_run_survive_its_end(rig: Rig) -> None:
    with rig.client() as lab:
        run = lab.run(count=0, period=PERIOD, label="endless", notes="before")
        lab.annotate_run(run.run_id, "during")
        lab.stop_cycling()
        info = run.wait()
        assert info["notes"] == "during"  # the end's row and notification carry the edit
        assert {r["run_id"]: r for r in lab.runs()}[run.run_id]["notes"] == "during"


def test_a_bad_label_is_refused_before_anything_starts(rig: Rig) -> None:
    with rig.client() as lab:
        before = lab.runs()[-1]["run_id"]
        with pytest.raises(ValueError, match="not a label"):
            lab.start_cycling(PERIOD, 2, label="two words")
        with pytest.raises(InvalidParams, match="not a label"):  # a client that does not check
            lab.call("start_cycling", 25_000_000, 2, None, False, False, "", "two words", None)
        with pytest.raises(InvalidParams, match="notes are 4,001 bytes"):
            lab.call("start_cycling", 25_000_000, 2, None, False, False, "", "ok", "x" * 4001)
        assert lab.runs()[-1]["run_id"] == before


def test_runs_stats_and_export_of_a_label_over_the_socket(rig: Rig) -> None:
    """`runs --label`, `stats --label` (pooled and per run) and `export --label`: read from the
    records file by the server's reader processes, the file's own answers."""
    with rig.client() as lab:
        ids = [lab.run(count=8, period=PERIOD, label="socket-pool").wait()["run_id"] for _ in range(2)]
        lab.run(count=3, period=PERIOD, label="elsewhere").wait()
        assert [r["run_id"] for r in lab.runs(100, label="socket-pool")] == ids
        assert lab.runs(label="never-used") == []
        stats = lab.stats(label="socket-pool")
        assert [r["run_id"] for r in stats["runs"]] == ids
        assert [p["run"]["run_id"] for p in stats["per_run"]] == ids
        assert stats["all"]["strokes"] == 16 == sum(p["all"]["strokes"] for p in stats["per_run"])
        assert stats["per_run"][0]["all"] == lab.stats(ids[0])["all"]
        with pytest.raises(InvalidParams, match="not both"):
            lab.call("stats", ids[0], None, None, "socket-pool")
        text = "".join(t for _, _, t in lab.export_csv(label="socket-pool"))
    with RecordsFile(rig.tmp / "state") as f:
        assert text == "".join(t for _, _, t in f.csv_chunks(label="socket-pool"))
        assert text.count("\n") == 16


def test_usmswitchctl_sets_shows_edits_and_exports_a_label(rig: Rig) -> None:
    """The CLI's side: `cycle --label --notes`, `runs --label`, `notes`, `stats --label` and
    `export --label`, over the socket and from the records file (--state-dir), the same answers."""
    state = str(rig.tmp / "state")
    done = rig.ctl(
        "cycle", "--count", "6", "--period", PERIOD, "--label", "cli-a", "--notes", "by cli", "--wait"
    )
    assert done.returncode == 0, done.stderr
    run_id = int(done.stdout.split()[1].rstrip(":"))
    for where in ((), ("--state-dir", state)):
        listed = rig.ctl("runs", "--label", "cli-a", *where)
        assert listed.returncode == 0 and "cli-a" in listed.stdout, listed.stderr
        assert f"run {run_id} notes: by cli" in listed.stdout
        stats = rig.ctl("stats", "--label", "cli-a", *where)
        assert stats.returncode == 0, stats.stderr
        assert stats.stdout.startswith(f"label cli-a: runs {run_id} pooled"), stats.stdout
    edited = rig.ctl("notes", str(run_id), "seen: fine\nline two")
    assert edited.returncode == 0 and "notes: seen: fine" in edited.stdout, edited.stderr
    shown = rig.ctl("notes", str(run_id), "--json")
    assert shown.returncode == 0 and '"notes": "seen: fine\\nline two"' in shown.stdout
    assert f"run {run_id} notes: seen: fine / line two" in rig.ctl("runs").stdout
    refused = rig.ctl("runs", "--label", "two words")
    assert refused.returncode != 0 and "not a label" in refused.stderr

    exports = []
    for where in ((), ("--state-dir", state)):
        out = rig.tmp / f"cli-a{len(exports)}.csv"
        made = rig.ctl("export", "--label", "cli-a", "--csv", str(out), *where)
        assert made.returncode == 0, made.stderr
        exports.append(out.read_text())
    assert exports[0] == exports[1]
    lines = exports[0].splitlines()
    assert lines[0] == f'# run {run_id}: {{"label": "cli-a", "notes": "seen: fine\\nline two"}}'
    assert lines[1].startswith("cycle,") and len(lines) == 2 + 6
