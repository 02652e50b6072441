"""Every `python` and `sh` block of README.md and docs/*.md, run verbatim against the daemon as
`make run` starts it (`usmswitchd --sim --web PORT`, its default socket and state directory).

The blocks run in document order (README first, then docs/ by name), in one working directory, with
the venv's bin first on PATH (README: `. .venv/bin/activate`), as a reader who types them in would.
A block that cannot run here says so in the document, in an HTML comment just above it:

    <!-- doctest: skip: needs root and systemd (tests/daemon/test_systemd_service.py runs these) -->
    <!-- doctest: skip-line usmswitchd --config: a real rig -->
    <!-- doctest: interrupt usmswitchctl watch after 3 -->

`skip` skips the block, `skip-line PREFIX` the lines of an `sh` block that start with PREFIX,
`interrupt PREFIX after N` runs that line and sends it Ctrl-C (SIGINT) after N seconds, as a reader
ends a command that runs until stopped. Each skip carries its reason, printed in the test's skip line.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BIN = Path(sys.executable).parent
DIRECTIVE = re.compile(r"^<!--\s*doctest:\s*(.*?)\s*-->\s*$")
FENCE = re.compile(r"^```(\w*)\s*$")


@dataclass
class Block:
    path: Path
    line: int  # of the opening fence
    lang: str
    text: str
    skip: str | None = None
    skip_lines: dict[str, str] = field(default_factory=dict)  # prefix -> reason
    interrupts: dict[str, float] = field(default_factory=dict)  # prefix -> seconds

    @property
    def id(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def parse_directive(block: Block, text: str) -> None:
    if text.startswith("skip-line "):
        prefix, _, reason = text[len("skip-line ") :].partition(":")
        block.skip_lines[prefix.strip()] = reason.strip()
    elif text.startswith("skip:"):
        block.skip = text[len("skip:") :].strip()
    elif m := re.fullmatch(r"interrupt (.+) after (\d+(?:\.\d+)?)", text):
        block.interrupts[m.group(1).strip()] = float(m.group(2))
    else:
        raise ValueError(f"unknown doctest directive {text!r}")


def blocks_of(path: Path) -> list[Block]:
    out: list[Block] = []
    pending: list[str] = []
    lines = path.read_text().splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        m = FENCE.match(line)
        if m:
            start, body = i + 1, []
            i += 1
            while i < len(lines) and not lines[i].startswith("```"):
                body.append(lines[i])
                i += 1
            if m.group(1) in ("python", "sh"):
                block = Block(path, start, m.group(1), "\n".join(body) + "\n")
                for text in pending:
                    parse_directive(block, text)
                out.append(block)
            pending = []
        elif d := DIRECTIVE.match(line):
            pending.append(d.group(1))
        elif line.strip():
            pending = []
        i += 1
    return out


BLOCKS = [b for path in DOCS for b in blocks_of(path)]


def shell_script(block: Block) -> str:
    """The block with its skipped lines commented out and its interrupted lines under `timeout`."""
    out = ["set -e -o pipefail"]
    for line in block.text.splitlines():
        bare = line.strip()
        if any(bare.startswith(p) for p in block.skip_lines):
            out.append(f": skipped: {shlex.quote(bare)}")
            continue
        for prefix, seconds in block.interrupts.items():
            if bare.startswith(prefix):
                # timeout's 124 is "interrupted as planned"; anything else is the command's own end.
                out.append(f"{{ timeout -s INT {seconds} {line}\n}} || [ $? -eq 124 ]")
                break
        else:
            out.append(line)
    return "\n".join(out) + "\n"


@pytest.fixture(scope="module")
def make_run_daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[dict[str, str], Path]]:
    """`usmswitchd --sim --web` as `make run` starts it, in a home of its own; (its env, the work dir)."""
    home = tmp_path_factory.mktemp("reader")
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith(("USMSWITCH_", "XDG_"))},
        "HOME": str(home),
        "XDG_RUNTIME_DIR": str(home / "run"),
        "XDG_STATE_HOME": str(home / "state"),
        "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
        "MPLBACKEND": "Agg",
    }
    (home / "run").mkdir(mode=0o700)
    work = home / "work"
    work.mkdir()
    proc = subprocess.Popen(
        # The panel as `make run` serves it, on a free port (a reader's own `make run` may hold 8790).
        [str(BIN / "usmswitchd"), "--sim", "--web", "127.0.0.1:0"],
        env=env,
        cwd=work,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        wait = subprocess.run(
            [str(BIN / "python"), "-c", WAIT_SERVING], env=env, capture_output=True, text=True, timeout=60
        )
        assert wait.returncode == 0, wait.stderr
        yield env, work
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err.decode()[-3000:]


WAIT_SERVING = """
import time
from usmswitch.client import Client
end = time.monotonic() + 50
while True:
    try:
        with Client(timeout=5) as c:
            c.status()
        break
    except Exception:
        if time.monotonic() > end:
            raise
        time.sleep(0.1)
"""


@pytest.mark.parametrize("block", BLOCKS, ids=[b.id for b in BLOCKS])
def test_doc_block_runs_verbatim(block: Block, make_run_daemon: tuple[dict[str, str], Path]) -> None:
    if block.skip is not None:
        pytest.skip(f"{block.id}: {block.skip}")
    env, work = make_run_daemon
    if block.lang == "python":
        cmd = [str(BIN / "python"), "-c", block.text]
    else:
        cmd = ["bash", "-c", shell_script(block)]
    proc = subprocess.run(cmd, env=env, cwd=work, capture_output=True, text=True, timeout=240)
    said = f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    assert proc.returncode == 0, f"{block.id} exited {proc.returncode}\n{said}"


def test_every_directive_names_a_line_of_its_block() -> None:
    """A skip-line or interrupt that matches nothing would hide a renamed command."""
    for block in BLOCKS:
        bare = [line.strip() for line in block.text.splitlines()]
        for prefix in [*block.skip_lines, *block.interrupts]:
            assert any(line.startswith(prefix) for line in bare), f"{block.id}: {prefix!r} matches no line"
        for reason in block.skip_lines.values():
            assert reason, f"{block.id}: a skip-line without its reason"
