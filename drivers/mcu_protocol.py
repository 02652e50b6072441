"""The MCU wire protocol codec: COBS framing, CRC-16, message layouts, sequence tracking, clock unwrap.

Pure and I/O free, so the host drivers (drivers/mcu.py) and the firmware emulator (sim/mcu_emulator.py)
speak exactly the same bytes. The specification is docs/mcu-protocol.md; its byte-level examples are
checked against this module by the tests.

A frame on the wire is `COBS(type | seq | body | crc16) 0x00`, every integer little-endian.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass, fields
from enum import IntEnum, IntFlag
from typing import ClassVar

PROTOCOL_MAJOR = 1
PROTOCOL_MINOR = 1
#: The newest minor version this codec decodes: 1.2 adds EDGE.flags, PONG.events_lost and
#: edges_missed, FAULT EVENTS_LOST and FAULT SENSORS at a start away from the source sensor. The
#: firmware speaks it (sim/mcu_firmware.py too, when asked); the host says PROTOCOL_MINOR in its
#: HELLO until it uses 1.2's fields, and a session speaks the lower of the two.
LATEST_MINOR = 2

#: Largest payload (type, seq, body, crc) either side may send; longer input is garbage.
MAX_PAYLOAD = 64
#: Largest COBS-encoded frame without its delimiter: one overhead byte per 254 data bytes.
MAX_ENCODED = MAX_PAYLOAD + 1

U32_MOD = 1 << 32
U16_MOD = 1 << 16


class ProtocolError(ValueError):
    """A frame that cannot be decoded: bad COBS, bad CRC, unknown type or wrong length."""


# -- COBS ---------------------------------------------------------------------------------------
def cobs_encode(data: bytes) -> bytes:
    """COBS-encode `data` so the result holds no 0x00 (the frame delimiter)."""
    out = bytearray()
    code_at = 0
    out.append(0)
    code = 1
    for b in data:
        if b == 0:
            out[code_at] = code
            code_at = len(out)
            out.append(0)
            code = 1
            continue
        out.append(b)
        code += 1
        if code == 0xFF:
            out[code_at] = code
            code_at = len(out)
            out.append(0)
            code = 1
    out[code_at] = code
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Undo `cobs_encode`; raises ProtocolError on a zero byte or a code that runs past the end."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError(f"COBS: zero byte at offset {i} inside a frame")
        end = i + code
        if end > n:
            raise ProtocolError(f"COBS: code {code} at offset {i} runs past the frame end ({n} bytes)")
        block = data[i + 1 : end]
        if 0 in block:
            raise ProtocolError(f"COBS: zero byte inside the block at offset {i}")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


# -- CRC ----------------------------------------------------------------------------------------
def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0); check("123456789") = 0x29B1."""
    return binascii.crc_hqx(data, 0xFFFF)


# -- messages -----------------------------------------------------------------------------------
class MsgType(IntEnum):
    """Frame types. Host to MCU below 0x80, MCU to host from 0x80."""

    HELLO = 0x01
    ARM = 0x02
    COMMAND = 0x03
    STOP = 0x04
    PING = 0x05
    HELLO_ACK = 0x81
    ACK = 0x82
    PONG = 0x83
    EDGE = 0x90
    START = 0x91
    STOPPED = 0x92
    STROKE = 0x93
    FAULT = 0x94
    BOOT = 0x95  # 1.1


class Caps(IntFlag):
    """What the firmware can do, announced in HELLO_ACK."""

    HW_DELAY = 0x01  # it times the start delay itself
    EDGE_STAMP = 0x02  # it stamps sensor edges with input capture
    STROKE_REPORT = 0x04  # it sends a STROKE summary after each stroke
    STOP_ON_ARRIVAL = 0x08  # it switches the drive off on the arrival edge
    WATCHDOG = 0x10  # it stops the drive when the host goes silent


# The STROKE report is the device's own account of each stroke, which the host holds the stroke's
# frames against (and rebuilds lost ones from): without it no stroke could be checked.
REQUIRED_CAPS = Caps.HW_DELAY | Caps.EDGE_STAMP | Caps.STROKE_REPORT | Caps.STOP_ON_ARRIVAL | Caps.WATCHDOG


class ResetCause(IntFlag):
    """Why the MCU last started (HELLO_ACK.reset_cause and BOOT, 1.1): the ATmega's MCUSR bits.

    0 means not known (a bootloader cleared MCUSR before the firmware read it). Bits add up when
    several causes came before the firmware read them (a power-on and then a watchdog reset)."""

    POWER_ON = 0x01
    EXTERNAL = 0x02  # the RESET pin (an Arduino's auto-reset when its port is opened)
    BROWN_OUT = 0x04
    WATCHDOG = 0x08  # the hardware watchdog: the firmware's main loop stopped coming round
    JTAG = 0x10


class Status(IntEnum):
    """ACK status: 0 is success, anything else says why the request was refused."""

    OK = 0
    NOT_SYNCED = 1  # no HELLO since reset or since the watchdog fired
    NOT_ARMED = 2  # COMMAND for a stroke that is not the armed one
    BUSY = 3  # a stroke is in progress
    BAD_ARG = 4  # a field is out of range (direction, delay, timeout)
    BAD_TIME = 5  # COMMAND's t_cmd_us is more than 1 s away from the device clock
    UNKNOWN_TYPE = 6


class StopReason(IntEnum):
    """Why the drive went off (STOPPED event, STOP request)."""

    ARRIVED = 0
    HOST = 1
    STALL = 2
    WATCHDOG = 3
    RESET = 4  # a HELLO arrived during a stroke
    FAULT = 5


class DeviceFault(IntEnum):
    """FAULT codes the firmware reports."""

    STALL = 1  # no arrival within the armed timeout
    HOST_SILENT = 2  # the watchdog fired
    SENSORS = 3  # at a start the source sensor was not active (detail: sensor bits, 1 A, 2 B)
    DRIVE = 4  # the drive was on with no stroke running (the firmware cut it)
    LATE_START = 5  # the start instant had passed when the COMMAND arrived
    EVENTS_LOST = 6  # 1.2: interrupt events were lost (detail: how many since the last report)


class StrokeFlags(IntFlag):
    """STROKE report flags: which stamps are valid and how the stroke ended."""

    DEPARTED = 0x01
    ARRIVED = 0x02
    STALL = 0x04
    HOST_STOP = 0x08
    LATE = 0x10
    WATCHDOG = 0x20
    EVENTS_LOST = 0x40  # 1.2: ended because the device lost interrupt events
    MISSED_EDGE = 0x80  # 1.2: a stamp of it is a missed edge's (EdgeFlags.MISSED), not a capture's


class EdgeFlags(IntFlag):
    """EDGE flags (1.2): how the device knows of the edge."""

    MISSED = 0x01  # its capture unit missed it; found by reading the pin back, stamped then (late)
    CUT = 0x02  # an arrival known from the external interrupt's drive cut, stamped by it


class StateFlags(IntFlag):
    """PONG state bits."""

    SYNCED = 0x01
    ARMED = 0x02
    DRIVE_ON = 0x04
    SENSOR_A = 0x08
    SENSOR_B = 0x10


@dataclass(frozen=True, slots=True)
class Message:
    """Base of every message: a type and a struct layout for the body (sequence lives in the frame)."""

    TYPE: ClassVar[MsgType]
    FORMAT: ClassVar[str]

    def pack_body(self) -> bytes:
        """The body bytes (after type and seq)."""
        return struct.pack(self.FORMAT, *(getattr(self, f.name) for f in fields(self)))


@dataclass(frozen=True, slots=True)
class Hello(Message):
    major: int
    minor: int
    watchdog_ms: int
    TYPE = MsgType.HELLO
    FORMAT = "<BBH"


@dataclass(frozen=True, slots=True)
class Arm(Message):
    stroke: int
    direction: int
    delay_us: int
    timeout_us: int
    TYPE = MsgType.ARM
    FORMAT = "<HBII"


@dataclass(frozen=True, slots=True)
class Command(Message):
    stroke: int
    t_cmd_us: int
    at: int  # 1: t_cmd_us is the command instant; 0: the instant of receipt
    TYPE = MsgType.COMMAND
    FORMAT = "<HIB"


@dataclass(frozen=True, slots=True)
class Stop(Message):
    reason: int
    TYPE = MsgType.STOP
    FORMAT = "<B"


@dataclass(frozen=True, slots=True)
class Ping(Message):
    token: int
    TYPE = MsgType.PING
    FORMAT = "<I"


@dataclass(frozen=True, slots=True)
class HelloAck(Message):
    """`minor` is the session's: the lower of the host's and the device's. From 1.1 the body ends
    with `reset_cause` (ResetCause bits); a 1.0 body has none, and decodes with 0 (not known)."""

    major: int
    minor: int
    caps: int
    fw_version: int
    t_us: int
    max_delay_us: int
    reset_cause: int = 0
    TYPE = MsgType.HELLO_ACK
    FORMAT = "<BBIHIIB"
    FORMAT_1_0: ClassVar[str] = "<BBIHII"

    def pack_body(self) -> bytes:
        if self.minor == 0:
            if self.reset_cause:
                raise ValueError(f"HelloAck field out of range: a 1.0 body has no reset_cause: {self!r}")
            return struct.pack(self.FORMAT_1_0, *(getattr(self, f.name) for f in fields(self)[:-1]))
        return struct.pack(self.FORMAT, *(getattr(self, f.name) for f in fields(self)))


@dataclass(frozen=True, slots=True)
class Ack(Message):
    acked_type: int
    acked_seq: int
    status: int
    stroke: int
    t_us: int
    TYPE = MsgType.ACK
    FORMAT = "<BHBHI"


class _Short(Message):
    """A message that 1.2 extended at its end: the fields past FORMAT_1_1's are None in a 1.0/1.1
    body (decoded from one, or to be sent to a 1.0/1.1 host), which packs in the old layout."""

    __slots__ = ()
    FORMAT_1_1: ClassVar[str]

    def pack_body(self) -> bytes:
        values = [getattr(self, f.name) for f in fields(self)]
        n = len(self.FORMAT_1_1) - 1
        extra = values[n:]
        if all(v is None for v in extra):
            return struct.pack(self.FORMAT_1_1, *values[:n])
        if any(v is None for v in extra):
            raise ValueError(
                f"{type(self).__name__} field out of range: the 1.2 fields go together: {self!r}"
            )
        return struct.pack(self.FORMAT, *values)


@dataclass(frozen=True, slots=True)
class Pong(_Short):
    """1.2 adds `events_lost` (interrupt events the device lost: its queue was full) and
    `edges_missed` (edges its capture units missed, reported flagged), both since the last HELLO,
    modulo 65536; None in a 1.0/1.1 body."""

    token: int
    t_us: int
    state: int
    rx_errors: int
    rx_lost: int
    events_lost: int | None = None
    edges_missed: int | None = None
    TYPE = MsgType.PONG
    FORMAT = "<IIBHHHH"
    FORMAT_1_1: ClassVar[str] = "<IIBHH"


@dataclass(frozen=True, slots=True)
class Edge(_Short):
    """1.2 adds `flags` (EdgeFlags; 0 for an edge its capture unit stamped); None in a 1.0/1.1
    body."""

    channel: int
    level: int
    t_us: int
    flags: int | None = None
    TYPE = MsgType.EDGE
    FORMAT = "<BBIB"
    FORMAT_1_1: ClassVar[str] = "<BBI"


@dataclass(frozen=True, slots=True)
class Start(Message):
    stroke: int
    direction: int
    t_us: int
    late_us: int
    TYPE = MsgType.START
    FORMAT = "<HBII"


@dataclass(frozen=True, slots=True)
class Stopped(Message):
    stroke: int
    reason: int
    t_us: int
    TYPE = MsgType.STOPPED
    FORMAT = "<HBI"


@dataclass(frozen=True, slots=True)
class Stroke(Message):
    stroke: int
    direction: int
    flags: int
    t_cmd_us: int
    t_start_us: int
    t_depart_us: int
    t_arrive_us: int
    TYPE = MsgType.STROKE
    FORMAT = "<HBBIIII"


@dataclass(frozen=True, slots=True)
class Fault(Message):
    code: int
    t_us: int
    detail: int
    TYPE = MsgType.FAULT
    FORMAT = "<BIH"


@dataclass(frozen=True, slots=True)
class Boot(Message):
    """1.1: sent once by the firmware as it starts, unasked (a 1.0 host counts it as a frame of
    unknown type): a reset the host did not cause is seen at once, with its cause."""

    reset_cause: int
    fw_version: int
    TYPE = MsgType.BOOT
    FORMAT = "<BH"


_ALL = (Hello, Arm, Command, Stop, Ping, HelloAck, Ack, Pong, Edge, Start, Stopped, Stroke, Fault, Boot)
MESSAGES: dict[int, type[Message]] = {cls.TYPE: cls for cls in _ALL}
_SIZES = {t: struct.calcsize(cls.FORMAT) for t, cls in MESSAGES.items()}
_SIZE_1_0 = {MsgType.HELLO_ACK: struct.calcsize(HelloAck.FORMAT_1_0)}  # the body of a 1.0 session
#: The bodies of a 1.0/1.1 session of the messages 1.2 extended.
_SHORT: dict[int, type[_Short]] = {MsgType.PONG: Pong, MsgType.EDGE: Edge}
_SIZE_1_1 = {t: struct.calcsize(cls.FORMAT_1_1) for t, cls in _SHORT.items()}
_HEADER = struct.Struct("<BH")


def encode_payload(msg: Message, seq: int) -> bytes:
    """type | seq | body | crc16: the frame before COBS, for tests and the documentation."""
    if not 0 <= seq < U16_MOD:
        raise ValueError(f"seq must be 0..65535, got {seq!r}")
    try:
        raw = _HEADER.pack(msg.TYPE, seq) + msg.pack_body()
    except struct.error as exc:
        raise ValueError(f"{type(msg).__name__} field out of range: {msg!r} ({exc})") from None
    return raw + struct.pack("<H", crc16(raw))


def encode_frame(msg: Message, seq: int) -> bytes:
    """The bytes to put on the wire for `msg` numbered `seq`, delimiter included."""
    return cobs_encode(encode_payload(msg, seq)) + b"\x00"


def decode_payload(payload: bytes) -> tuple[int, Message]:
    """(seq, message) from a COBS-decoded payload; ProtocolError if it is not a valid frame."""
    n = len(payload)
    if n < 5:
        raise ProtocolError(f"frame of {n} bytes is shorter than header + CRC (5)")
    if n > MAX_PAYLOAD:
        raise ProtocolError(f"frame of {n} bytes exceeds the {MAX_PAYLOAD}-byte limit")
    (crc,) = struct.unpack_from("<H", payload, n - 2)
    calc = crc16(payload[:-2])
    if crc != calc:
        raise ProtocolError(f"CRC mismatch: frame says 0x{crc:04X}, computed 0x{calc:04X}")
    mtype, seq = _HEADER.unpack_from(payload)
    cls = MESSAGES.get(mtype)
    if cls is None:
        raise ProtocolError(f"unknown message type 0x{mtype:02X}")
    body = payload[3:-2]
    if mtype in _SIZE_1_0 and len(body) == _SIZE_1_0[mtype] and body[1] == 0:
        return seq, cls(*struct.unpack(HelloAck.FORMAT_1_0, body))
    if mtype in _SIZE_1_1 and len(body) == _SIZE_1_1[mtype]:
        return seq, cls(*struct.unpack(_SHORT[mtype].FORMAT_1_1, body))
    if len(body) != _SIZES[mtype]:
        raise ProtocolError(f"{cls.__name__} body is {len(body)} bytes, expected {_SIZES[mtype]}")
    return seq, cls(*struct.unpack(cls.FORMAT, body))


class FrameDecoder:
    """Split a byte stream into frames at 0x00 and decode them; garbage is counted, never raised.

    Resynchronisation is free: any 0x00 ends whatever came before it, so after line noise the
    next delimiter starts a clean frame.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._overrun = False
        #: Frames dropped for bad COBS or length.
        self.framing_errors = 0
        #: Frames dropped for a CRC mismatch.
        self.crc_errors = 0
        #: Frames dropped for an unknown type or a body of the wrong size.
        self.format_errors = 0
        #: Good frames decoded.
        self.frames = 0
        self.last_error = ""

    @property
    def errors(self) -> int:
        """Every frame discarded, whatever the reason."""
        return self.framing_errors + self.crc_errors + self.format_errors

    def feed(self, data: bytes) -> list[tuple[int, Message]]:
        """Decode every frame completed by `data`; partial trailing bytes wait for the next call."""
        out: list[tuple[int, Message]] = []
        buf = self._buf
        start = 0
        while True:
            z = data.find(0, start)
            if z < 0:
                chunk = data[start:]
                if len(buf) + len(chunk) > MAX_ENCODED:
                    self._overrun = True
                    buf.clear()
                else:
                    buf += chunk
                return out
            chunk = data[start:z]
            start = z + 1
            if self._overrun or len(buf) + len(chunk) > MAX_ENCODED:
                self._overrun = False
                buf.clear()
                self.framing_errors += 1
                self.last_error = f"frame longer than {MAX_ENCODED} encoded bytes"
                continue
            if buf:
                buf += chunk
                raw = bytes(buf)
                buf.clear()
            else:
                raw = chunk
            if not raw:
                continue  # back-to-back delimiters: an idle or flushing line, not an error
            try:
                payload = cobs_decode(raw)
            except ProtocolError as exc:
                self.framing_errors += 1
                self.last_error = str(exc)
                continue
            try:
                out.append(decode_payload(payload))
            except ProtocolError as exc:
                if "CRC" in str(exc):
                    self.crc_errors += 1
                else:
                    self.format_errors += 1
                self.last_error = str(exc)
                continue
            self.frames += 1


class SeqTracker:
    """Receive-side sequence check: counts frames lost between two received ones."""

    def __init__(self) -> None:
        self.expected: int | None = None
        #: Frames the peer sent that never arrived.
        self.lost = 0
        #: Frames whose number went backwards (the peer restarted its count).
        self.resets = 0

    def reset(self, next_seq: int | None = None) -> None:
        """Forget the count (new session); `next_seq` is the number the next frame must carry."""
        self.expected = next_seq

    def check(self, seq: int) -> int:
        """Record frame `seq`; returns how many frames were lost just before it (0 when in order)."""
        exp = self.expected
        self.expected = (seq + 1) % U16_MOD
        if exp is None:
            return 0
        gap = (seq - exp) % U16_MOD
        if gap == 0:
            return 0
        if gap < U16_MOD // 2:
            self.lost += gap
            return gap
        self.resets += 1
        return 0


class Unwrapper:
    """Extend the device's 32-bit microsecond counter to an unbounded count (it wraps every 71.6 min).

    A stamp may be slightly older than one already seen (an edge captured before a PONG was sent),
    so differences are taken as signed 32-bit values and the reference only moves forward.
    """

    def __init__(self) -> None:
        self._raw: int | None = None
        self._full = 0
        #: Wrap-arounds seen.
        self.wraps = 0

    def reset(self) -> None:
        """Forget the reference (a new session with a device whose clock may have restarted)."""
        self._raw = None
        self._full = 0

    def unwrap(self, raw_us: int) -> int:
        """The unwrapped microsecond count for a raw 32-bit stamp."""
        if not 0 <= raw_us < U32_MOD:
            raise ValueError(f"raw_us must be a 32-bit unsigned stamp, got {raw_us!r}")
        if self._raw is None:
            self._raw = raw_us
            self._full = raw_us
            return raw_us
        delta = (raw_us - self._raw) % U32_MOD
        if delta >= U32_MOD // 2:
            return self._full - (U32_MOD - delta)
        if raw_us < self._raw:
            self.wraps += 1
        self._raw = raw_us
        self._full += delta
        return self._full
