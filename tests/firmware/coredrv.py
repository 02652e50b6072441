"""A session with the native protocol core (tests/firmware/core_test.c) through its stdin script."""

from __future__ import annotations

import subprocess
from pathlib import Path

from usmswitch.drivers.mcu_protocol import FrameDecoder, Message, encode_frame


class CoreDriver:
    """Feed the core and collect what it sends, one command at a time."""

    def __init__(self, binary: Path) -> None:
        self.proc = subprocess.Popen(
            [str(binary)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1
        )
        self.host_seq = 0
        self.decoder = FrameDecoder()

    def cmd(self, line: str) -> list[str]:
        """Run one command; returns its output lines (the driver prints a marker after each)."""
        assert self.proc.stdin and self.proc.stdout
        self.proc.stdin.write(line + "\n# end\n")
        self.proc.stdin.write("size ff\n")  # a sentinel reply: "size -1"
        self.proc.stdin.flush()
        out = []
        while True:
            ln = self.proc.stdout.readline()
            assert ln, "core_test exited"
            ln = ln.strip()
            if ln == "size -1":
                return out
            out.append(ln)

    def clock(self, t_us: int) -> None:
        self.cmd(f"clock {t_us}")

    def sensors(self, bits: int) -> None:
        self.cmd(f"sensors {bits}")

    def rx_wire(self, wire: bytes) -> list[str]:
        return self.cmd("rx " + wire.hex())

    def send(self, msg: Message, seq: int | None = None) -> list[str]:
        """Send a host message numbered by the host counter (or `seq`); returns the output lines."""
        if seq is None:
            seq = self.host_seq
        self.host_seq = (seq + 1) % 65536
        return self.rx_wire(encode_frame(msg, seq))

    @staticmethod
    def frames(lines: list[str]) -> list[bytes]:
        return [bytes.fromhex(ln[3:]) for ln in lines if ln.startswith("tx ")]

    def messages(self, lines: list[str]) -> list[tuple[int, Message]]:
        out = []
        for f in self.frames(lines):
            out += self.decoder.feed(f)
        return out

    def close(self) -> None:
        if self.proc.stdin:
            self.proc.stdin.close()
        self.proc.wait(5)
