"""The MCU codec: COBS, CRC, message layouts, sequence tracking, unwrap, and the doc's byte examples."""

from __future__ import annotations

import re
from dataclasses import fields, replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from usmswitch.drivers import mcu_protocol as mp
from usmswitch.drivers.mcu_protocol import (
    MESSAGES,
    Edge,
    FrameDecoder,
    ProtocolError,
    SeqTracker,
    Unwrapper,
    cobs_decode,
    cobs_encode,
    crc16,
    decode_payload,
    encode_frame,
    encode_payload,
)


def test_crc_check_value() -> None:
    assert crc16(b"123456789") == 0x29B1


@pytest.mark.parametrize(
    ("raw", "enc"),
    [
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    ],
)
def test_cobs_reference_vectors(raw: bytes, enc: bytes) -> None:
    assert cobs_encode(raw) == enc
    assert cobs_decode(enc) == raw


@given(st.binary(max_size=700))
def test_cobs_round_trip_has_no_zero(data: bytes) -> None:
    enc = cobs_encode(data)
    assert 0 not in enc
    assert cobs_decode(enc) == data


def test_cobs_rejects_bad_input() -> None:
    with pytest.raises(ProtocolError, match="runs past"):
        cobs_decode(b"\x05\x01\x02")
    with pytest.raises(ProtocolError, match="zero"):
        cobs_decode(b"\x03\x00\x01")


def _sample(cls: type[mp.Message], draw: st.DrawFn) -> mp.Message:
    widths = {"B": 0xFF, "H": 0xFFFF, "I": 0xFFFFFFFF}
    codes = cls.FORMAT[1:]
    msg = cls(*(draw(st.integers(0, widths[c])) for c in codes))
    if isinstance(msg, mp.HelloAck) and msg.minor == 0:
        msg = replace(msg, reset_cause=0)  # a 1.0 session's HELLO_ACK has no reset cause
    return msg


@given(st.data())
def test_every_message_round_trips(data: st.DataObject) -> None:
    cls = data.draw(st.sampled_from(sorted(MESSAGES.values(), key=lambda c: c.TYPE)))
    msg = _sample(cls, data.draw)
    seq = data.draw(st.integers(0, 0xFFFF))
    frame = encode_frame(msg, seq)
    assert frame.endswith(b"\x00") and 0 not in frame[:-1]
    assert FrameDecoder().feed(frame) == [(seq, msg)]


def test_hello_ack_of_a_1_0_session_has_no_reset_cause() -> None:
    """1.1 adds reset_cause at the end of HELLO_ACK; a session at 1.0 (a 1.0 host or device) keeps
    the 16-byte body, which decodes with reset_cause 0 (not known)."""
    old = mp.HelloAck(1, 0, 31, 0x0100, 5, 1_000_000)
    assert len(old.pack_body()) == 16 and FrameDecoder().feed(encode_frame(old, 0)) == [(0, old)]
    new = mp.HelloAck(1, 1, 31, 0x0101, 5, 1_000_000, int(mp.ResetCause.WATCHDOG))
    assert len(new.pack_body()) == 17 and FrameDecoder().feed(encode_frame(new, 0)) == [(0, new)]
    with pytest.raises(ValueError, match="no reset_cause"):
        encode_frame(replace(old, reset_cause=8), 0)
    body = bytearray(old.pack_body())
    body[1] = 1  # a 16-byte body that says 1.1
    raw = bytes([mp.MsgType.HELLO_ACK, 0, 0]) + bytes(body)
    with pytest.raises(ProtocolError, match="expected 17"):
        decode_payload(raw + crc16(raw).to_bytes(2, "little"))


def test_field_out_of_range_names_the_message() -> None:
    with pytest.raises(ValueError, match="Edge field out of range"):
        encode_payload(Edge(2, 1, 1 << 32), 0)
    with pytest.raises(ValueError, match="seq"):
        encode_payload(Edge(0, 1, 5), 70000)


def test_decoder_counts_and_resyncs_after_garbage() -> None:
    good = encode_frame(Edge(1, 1, 1234), 9)
    bad_crc = bytearray(encode_frame(Edge(0, 0, 99), 10))
    bad_crc[4] ^= 0x10
    unknown = mp.cobs_encode(b"\x7f\x00\x00" + b"\x00\x00") + b"\x00"
    dec = FrameDecoder()
    stream = b"\xde\xad\xbe\xef\x00" + bytes(bad_crc) + unknown + b"\xff" * 200 + b"\x00" + b"\x00\x00" + good
    out = []
    for i in range(0, len(stream), 7):  # arbitrary chunking, as a serial port delivers
        out += dec.feed(stream[i : i + 7])
    assert out == [(9, Edge(1, 1, 1234))]
    assert dec.crc_errors >= 1 and dec.framing_errors >= 1 and dec.errors >= 3
    assert dec.frames == 1


def test_decode_payload_rejects_wrong_length() -> None:
    p = encode_payload(Edge(1, 1, 5), 3)
    body_short = p[:-3] + mp.struct.pack("<H", crc16(p[:-3]))
    with pytest.raises(ProtocolError, match="body is"):
        decode_payload(body_short)


def test_seq_tracker_counts_gaps_and_resets() -> None:
    t = SeqTracker()
    assert t.check(65534) == 0
    assert t.check(65535) == 0
    assert t.check(0) == 0  # wrap of the counter
    assert t.check(3) == 2
    assert t.lost == 2
    assert t.check(1) == 0 and t.resets == 1


def test_unwrap_over_the_32_bit_wrap() -> None:
    u = Unwrapper()
    assert u.unwrap(0xFFFF_FF00) == 0xFFFF_FF00
    assert u.unwrap(0x0000_0010) == (1 << 32) + 0x10
    assert u.wraps == 1
    assert u.unwrap(0xFFFF_FFF0) == 0xFFFF_FFF0  # a slightly older stamp, not a wrap forward
    assert u.unwrap(0x0000_0020) == (1 << 32) + 0x20
    for k in range(2, 5):  # several wraps, seen often enough
        for raw in (0x4000_0000, 0x8000_0000, 0xC000_0000, 0x0000_0005):
            v = u.unwrap(raw)
        assert v == (k << 32) + 5
    with pytest.raises(ValueError, match="raw_us"):
        u.unwrap(-1)


EXAMPLE = re.compile(
    r"^(?P<msg>(?P<cls>\w+)\((?P<args>[^)]*)\)) seq=(?P<seq>\d+)\n"
    r"payload: (?P<payload>[0-9a-f ]+)\n"
    r"wire: +(?P<wire>[0-9a-f ]+)$",
    re.M,
)


def test_doc_byte_examples_match_the_codec(repo_root) -> None:
    text = (repo_root / "docs" / "mcu-protocol.md").read_text()
    examples = list(EXAMPLE.finditer(text))
    seen = {m["cls"] for m in examples}
    assert seen == {cls.__name__ for cls in MESSAGES.values()}, "every message has an example"
    for m in examples:
        cls = getattr(mp, m["cls"])
        kwargs = dict(kv.split("=") for kv in m["args"].split(", "))
        assert set(kwargs) == {f.name for f in fields(cls)}
        msg = cls(**{k: int(v, 0) for k, v in kwargs.items()})
        seq = int(m["seq"])
        assert encode_payload(msg, seq).hex(" ") == m["payload"].strip(), m["msg"]
        wire = bytes.fromhex(m["wire"])
        assert encode_frame(msg, seq) == wire, m["msg"]
        assert FrameDecoder().feed(wire) == [(seq, msg)]


def test_doc_states_the_crc_check_value(repo_root) -> None:
    text = (repo_root / "docs" / "mcu-protocol.md").read_text()
    assert "CRC-16/CCITT-FALSE" in text and f"0x{crc16(b'123456789'):04X}" in text
