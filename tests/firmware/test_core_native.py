"""The firmware's protocol core, built natively, against docs/mcu-protocol.md byte by byte.

Every example of section 8 goes through the C codec (CRC, COBS both ways, body sizes), and the
doc's session is replayed through the C state machine: the frames the device sends must be the
doc's bytes wherever the doc's session is self-consistent.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from coredrv import CoreDriver

from usmswitch.drivers import mcu_protocol as mp

DOC = Path(__file__).resolve().parents[2] / "docs" / "mcu-protocol.md"
_EXAMPLE = re.compile(r"^(\w+)\((.*)\) seq=(\d+)\npayload: ([0-9a-f ]+)\nwire:    ([0-9a-f ]+)$", re.M)


def doc_examples() -> list[tuple[str, str, int, bytes, bytes]]:
    text = DOC.read_text()
    out = []
    for name, args, seq, payload, wire in _EXAMPLE.findall(text):
        out.append((name, args, int(seq), bytes.fromhex(payload), bytes.fromhex(wire)))
    return out


EXAMPLES = doc_examples()


def _message(name: str, args: str) -> mp.Message:
    cls = getattr(mp, name)
    kw = dict(kv.split("=") for kv in args.split(", "))
    return cls(**{k: int(v) for k, v in kw.items()})


@pytest.fixture
def core(core_test_bin: Path) -> Iterator[CoreDriver]:
    drv = CoreDriver(core_test_bin)
    yield drv
    drv.close()


def test_the_doc_has_every_message_type() -> None:
    assert {name for name, *_ in EXAMPLES} == {cls.__name__ for cls in mp.MESSAGES.values()}
    assert len(EXAMPLES) == 17


def test_crc_check_value(core: CoreDriver) -> None:
    assert core.cmd("crc " + b"123456789".hex()) == ["crc 29b1"]


@pytest.mark.parametrize(("name", "args", "seq", "payload", "wire"), EXAMPLES, ids=[e[0] for e in EXAMPLES])
def test_doc_example_through_the_c_codec(
    core: CoreDriver, name: str, args: str, seq: int, payload: bytes, wire: bytes
) -> None:
    assert core.cmd("crc " + payload[:-2].hex()) == [f"crc {payload[-2:][::-1].hex()}"]
    assert core.cmd("cobs " + payload.hex()) == [f"cobs {wire[:-1].hex()}"]
    assert core.cmd("uncobs " + wire[:-1].hex()) == [f"uncobs {payload.hex()}"]
    size = len(payload) - 5 + (name == "HelloAck" and "minor=0" in args)  # the C size is 1.1's
    assert core.cmd(f"size {payload[0]:x}") == [f"size {size}"]
    assert wire == mp.encode_frame(_message(name, args), seq)  # the doc line says what the bytes say


def test_cobs_long_runs_and_errors(core: CoreDriver) -> None:
    for data in (b"\x00", b"\x00\x00", bytes(range(1, 200)), b"\x11" * 63 + b"\x00", bytes(64)):
        enc = mp.cobs_encode(data)
        assert core.cmd("cobs " + data.hex()) == [f"cobs {enc.hex()}"]
        assert core.cmd("uncobs " + enc.hex()) == [f"uncobs {data.hex()}"]
    assert core.cmd("uncobs 0511") == ["uncobs error"]  # runs past the end
    assert core.cmd("uncobs 030100") == ["uncobs error"]  # a zero inside


def _wire(name: str, seq: int | None = None) -> bytes:
    for n, _, s, _, wire in EXAMPLES:
        if n == name and (seq is None or s == seq):
            return wire
    raise KeyError(name)


def test_doc_session_replayed_through_the_state_machine(core: CoreDriver) -> None:
    """The doc's session: HELLO, ARM, COMMAND across the wrap, edges, PING, in the doc's bytes."""
    core.sensors(1)  # at A
    core.clock(4294667296)
    assert core.frames(core.cmd("boot 8")) == [_wire("Boot")]  # started by its watchdog
    core.cmd("boot 1")  # powered on, for the doc's session
    out = core.rx_wire(_wire("Hello"))
    assert core.frames(out) == [_wire("HelloAck")]
    core.clock(4294668288)
    out = core.rx_wire(_wire("Arm"))
    assert core.frames(out) == [_wire("Ack", 1)]
    core.clock(4294901000)
    out = core.rx_wire(_wire("Command"))
    assert core.frames(out) == [_wire("Ack", 2)]
    due = (4294901760 + 1850) % 2**32
    assert f"hal schedule {due} 0 1" in out
    out = core.cmd(f"start {due}")
    assert core.frames(out) == [mp.encode_frame(mp.Start(7, 0, due, 0), 3)]
    core.sensors(0)
    out = core.cmd("edge 0 0 116648")  # across the wrap
    assert core.frames(out) == [_wire("Edge", 4)]
    core.sensors(2)
    out = core.cmd("edge 1 1 728090")
    assert "hal off" in out
    assert core.frames(out) == [
        _wire("Edge", 5),
        mp.encode_frame(mp.Stroke(7, 0, 3, 4294901760, due, 116648, 728090), 6),
        _wire("Stopped"),
    ]
    core.clock(729088)
    out = core.rx_wire(_wire("Ping"))
    assert core.frames(out) == [_wire("Pong")]
    out = core.rx_wire(_wire("Stop"))
    assert core.messages(out) == [(9, mp.Ack(4, 4, 0, 7, 729088))]


def test_a_1_0_host_gets_the_1_0_hello_ack(core: CoreDriver) -> None:
    """The session speaks the lower minor version: a 1.0 HELLO gets the 16-byte HELLO_ACK."""
    core.cmd("boot 1")
    core.clock(4294667296)
    out = core.send(mp.Hello(1, 0, 500))
    assert core.messages(out) == [(0, mp.HelloAck(1, 0, 31, 0x0102, 4294667296, 1_000_000, 0))]


def test_doc_fault_example_is_a_stall(core: CoreDriver) -> None:
    """FAULT STALL with the doc's bytes: stroke started, no arrival within 100 ms."""
    core.sensors(1)
    core.clock(0)
    core.send(mp.Hello(1, 0, 60000))
    core.send(mp.Arm(1, 0, 0, 100_000))
    core.clock(1)
    out = core.send(mp.Command(1, 0, 0))  # seq 2 Ack, then Start seq 3
    core.cmd("start 948576")  # stall stamp: 948576 + 100000 = 1048576
    core.cmd("clock 1048575")
    assert core.frames(core.cmd("poll")) == []
    core.cmd("clock 1048576")
    # align the device sequence with the doc: Start is seq 3; emit PONGs up to seq 8
    for _ in range(5):
        core.send(mp.Ping(0))
    out = core.cmd("poll")
    assert core.frames(out)[0] == _wire("Fault")
    assert [m for _, m in core.messages(out)][1:] == [
        mp.Stroke(1, 0, mp.StrokeFlags.STALL | mp.StrokeFlags.LATE, 1, 948576, 0, 0),
        mp.Stopped(1, mp.StopReason.STALL, 1048576),
    ]


def _session_1_2(core: CoreDriver) -> None:
    core.sensors(1)  # at A
    core.clock(1000)
    core.send(mp.Hello(1, 2, 60_000), 0)


def test_lost_events_end_a_running_stroke_and_are_counted(core: CoreDriver) -> None:
    """Issue 33: edges the board lost end the stroke they may belong to (drive off first), with a
    FAULT EVENTS_LOST, the STROKE flagged EVENTS_LOST and STOPPED FAULT; PONG counts them."""
    _session_1_2(core)
    core.send(mp.Arm(1, 0, 1000, 100_000))
    core.send(mp.Command(1, 0, 0))
    core.cmd("start 2000")
    core.clock(2500)
    out = core.cmd("lost 3")
    assert out[0] == "hal off"  # before any frame is built
    msgs = [m for _, m in core.messages(out)]
    assert msgs == [
        mp.Fault(mp.DeviceFault.EVENTS_LOST, 2500, 3),
        mp.Stroke(1, 0, mp.StrokeFlags.EVENTS_LOST, 1000, 2000, 0, 0),
        mp.Stopped(1, mp.StopReason.FAULT, 2500),
    ]
    ((_, pong),) = core.messages(core.send(mp.Ping(5)))
    assert isinstance(pong, mp.Pong) and (pong.events_lost, pong.edges_missed) == (3, 0)


def test_lost_events_at_rest_are_said_at_most_every_10_ms(core: CoreDriver) -> None:
    _session_1_2(core)
    core.clock(2000)
    assert [m for _, m in core.messages(core.cmd("lost 2"))] == [
        mp.Fault(mp.DeviceFault.EVENTS_LOST, 2000, 2)
    ]
    core.clock(5000)
    assert core.messages(core.cmd("lost 5")) == []  # within 10 ms of the last FAULT: counted
    core.clock(11_999)
    assert core.messages(core.cmd("poll")) == []
    core.clock(12_000)
    assert [m for _, m in core.messages(core.cmd("poll"))] == [
        mp.Fault(mp.DeviceFault.EVENTS_LOST, 12_000, 5)
    ]
    ((_, pong),) = core.messages(core.send(mp.Ping(1)))
    assert pong.events_lost == 7


def test_a_missed_edge_is_flagged_for_a_1_2_host_only(core: CoreDriver) -> None:
    _session_1_2(core)
    out = core.cmd(f"edge 1 1 3000 {1}")
    assert [m for _, m in core.messages(out)] == [mp.Edge(1, 1, 3000, mp.EdgeFlags.MISSED)]
    ((_, pong),) = core.messages(core.send(mp.Ping(1)))
    assert (pong.events_lost, pong.edges_missed) == (0, 1)
    core.send(mp.Hello(1, 1, 60_000), 0)  # a 1.1 host: the 1.1 layouts
    assert [m for _, m in core.messages(core.cmd("edge 1 0 4000 1"))] == [mp.Edge(1, 0, 4000)]
    ((_, pong),) = core.messages(core.send(mp.Ping(2)))
    assert pong == mp.Pong(2, 1000, pong.state, 0, 0)


def test_the_drive_on_with_no_stroke_is_cut_and_said(core: CoreDriver) -> None:
    _session_1_2(core)
    core.cmd("drive 1")
    core.clock(3000)
    out = core.cmd("poll")
    assert out[0] == "hal off"
    assert [m for _, m in core.messages(out)] == [mp.Fault(mp.DeviceFault.DRIVE, 3000, 1)]
