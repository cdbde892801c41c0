"""The strobe controller's serial protocol: framing, CRC and messages (docs/hardware.md).

Pure bytes-in / bytes-out functions, shared by the driver
(:mod:`mifacerf.capture.hardware.controller`) and the simulated controller
(:mod:`mifacerf.capture.simulation.device`); nothing here touches a port.

Frame (all integers little-endian)::

    offset  size  field
    0       1     SOF = 0xA5
    1       1     protocol version (1)
    2       1     sequence number (0-255), chosen by the host; a reply carries its command's number
    3       1     message type; < 0x80 host -> device (commands), >= 0x80 device -> host (replies, events)
    4       2     payload length n (<= MAX_PAYLOAD)
    6       1     header check: CRC-8 (poly 0x07) of bytes 1 .. 5
    7       n     payload
    7+n     2     CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of bytes 1 .. 6+n

A receiver scans for SOF, checks version, header check, length and CRC, and on any
failure drops that one SOF byte and scans again (:class:`FrameDecoder`), so line
noise, a truncated frame or a flipped bit costs at most the frames it touches; the
header check keeps a corrupted length from making the receiver wait for bytes that
will never come.

Every command is answered by exactly one ACK (with the command's data) or one NAK
(with a reason code and a text), never both. A command re-sent with the same
sequence number and the same bytes is not executed twice: the device replays its
cached reply (retries are idempotent). RUN is acknowledged at once; the device
then streams one EVENT per step and a final DONE, all carrying RUN's sequence
number; a host that lost some of them reads them back with READLOG. After a
reset the device announces itself with an unsolicited BOOT (sequence 0) and has
forgotten its sequence; its ``boot_id`` (also in HELLO and STATUS) changes.
"""
from __future__ import annotations

import binascii
import enum
import struct
from dataclasses import dataclass, field
from ...errors import MifacerfError

SOF = 0xA5
VERSION = 1
HEADER = struct.Struct("<BBBBHB")  # SOF, version, seq, type, length, header CRC-8
MAX_PAYLOAD = 1024
OVERHEAD = HEADER.size + 2
#: The cameras run at 60 Hz: one trigger (and at most one strobe) per 1/60 s.
CAMERA_RATE_HZ = 60
MIN_PERIOD_US = 1_000_000 // CAMERA_RATE_HZ  # 16666 us


class ProtocolError(MifacerfError, ValueError):
    """Bytes that do not form a valid message (bad length, unknown type, short payload)."""


class Msg(enum.IntEnum):
    """Message types. Commands (< 0x80) go host -> device, the rest device -> host."""

    HELLO = 0x01     # -> ACK HelloInfo
    STATUS = 0x02    # -> ACK StatusInfo
    ROTATE = 0x03    # u16 arm position -> ACK u16 position (after the move)
    LOAD = 0x04      # u16 offset, u8 count, count x Step -> ACK u16 steps loaded
    RUN = 0x05       # u32 period_us, u16 n_steps -> ACK; then EVENT x n, DONE
    ABORT = 0x06     # -> ACK
    CLEAR = 0x07     # forget the loaded sequence -> ACK
    READLOG = 0x08   # u16 first step, u8 count -> ACK u16 first, u8 count, count x Event
    ACK = 0x80       # u8 command type, command-specific data
    NAK = 0x81       # u8 command type, u8 Reason, utf-8 text
    EVENT = 0x82     # Event
    DONE = 0x83      # Done
    BOOT = 0x84      # u32 boot_id, u8 BootReason (unsolicited, seq 0)

    @property
    def is_command(self) -> bool:
        return self < 0x80


class Reason(enum.IntEnum):
    """Why a command was refused (NAK)."""

    UNKNOWN_COMMAND = 1
    BAD_PAYLOAD = 2
    OUT_OF_RANGE = 3
    BUSY = 4
    NO_SEQUENCE = 5
    TOO_MANY_STEPS = 6
    RATE_TOO_HIGH = 7
    NOT_CONTIGUOUS = 8


class State(enum.IntEnum):
    IDLE = 0
    LOADED = 1
    RUNNING = 2


class BootReason(enum.IntEnum):
    POWER_ON = 0
    WATCHDOG = 1
    BROWN_OUT = 2


# ---------------------------------------------------------------------- CRC and framing
def _crc8_table() -> list[int]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table.append(c)
    return table


_CRC8 = _crc8_table()


def crc8(data: bytes) -> int:
    """CRC-8 (poly 0x07, init 0; check value of b"123456789" is 0xF4)."""
    c = 0
    for b in data:
        c = _CRC8[c ^ b]
    return c


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value of b"123456789" is 0x29B1)."""
    return binascii.crc_hqx(bytes(data), 0xFFFF)


def encode_frame(seq: int, msg_type: int, payload: bytes = b"") -> bytes:
    """One frame for message ``msg_type`` with sequence number ``seq`` (0-255)."""
    payload = bytes(payload)
    if not 0 <= seq <= 255:
        raise ProtocolError(f"sequence number {seq} outside 0-255")
    if not 0 <= msg_type <= 255:
        raise ProtocolError(f"message type {msg_type} outside 0-255")
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    head = struct.pack("<BBBH", VERSION, seq, msg_type, len(payload))
    body = head + bytes([crc8(head)]) + payload
    return bytes([SOF]) + body + struct.pack("<H", crc16(body))


@dataclass(frozen=True)
class Frame:
    seq: int
    type: int
    payload: bytes = b""

    @property
    def msg(self) -> Msg | None:
        try:
            return Msg(self.type)
        except ValueError:
            return None

    def encode(self) -> bytes:
        return encode_frame(self.seq, self.type, self.payload)

    def __repr__(self) -> str:
        m = self.msg
        return f"Frame(seq={self.seq}, {m.name if m else hex(self.type)}, {self.payload.hex()})"


@dataclass
class FrameDecoder:
    """Incremental decoder: :meth:`feed` bytes, get complete valid frames back.

    Counts what it threw away (``dropped_bytes``, ``crc_errors``) so the driver can
    report a noisy line.
    """

    buffer: bytearray = field(default_factory=bytearray)
    crc_errors: int = 0
    dropped_bytes: int = 0

    def feed(self, data: bytes) -> list[Frame]:
        self.buffer += data
        out = []
        buf = self.buffer
        while True:
            start = buf.find(bytes([SOF]))
            if start < 0:
                self.dropped_bytes += len(buf)
                buf.clear()
                break
            if start:
                self.dropped_bytes += start
                del buf[:start]
            if len(buf) < HEADER.size:
                break
            _, ver, seq, typ, n, hcrc = HEADER.unpack_from(buf)
            if ver != VERSION or n > MAX_PAYLOAD or hcrc != crc8(bytes(buf[1:HEADER.size - 1])):
                self.dropped_bytes += 1
                del buf[:1]
                continue
            if len(buf) < n + OVERHEAD:
                break
            body = bytes(buf[1:HEADER.size + n])
            (crc,) = struct.unpack_from("<H", buf, HEADER.size + n)
            if crc != crc16(body):
                self.crc_errors += 1
                self.dropped_bytes += 1
                del buf[:1]
                continue
            out.append(Frame(seq, typ, bytes(buf[HEADER.size:HEADER.size + n])))
            del buf[:n + OVERHEAD]
        return out


def decode_frames(data: bytes) -> list[Frame]:
    """All valid frames in ``data`` (a convenience over :class:`FrameDecoder`)."""
    return FrameDecoder().feed(data)


# -------------------------------------------------------------------------- payloads
STEP = struct.Struct("<HBB")         # arm position, strobe, camera mask
EVENT = struct.Struct("<HIHBBI")     # step, trigger counter, arm position, strobe, fired, time_us
DONE = struct.Struct("<HHHB")        # steps, fired, misfired, aborted
HELLO = struct.Struct("<BHBBHI")     # protocol version, n_positions, n_strobes, n_cameras, max_steps, boot_id
STATUS = struct.Struct("<BHIIHHB")   # state, arm position, boot_id, trigger counter, loaded, done, misfires
RUN = struct.Struct("<IH")           # period_us, n_steps
BOOT = struct.Struct("<IB")          # boot_id, reason
LOAD_HEAD = struct.Struct("<HB")     # offset, count
READLOG = struct.Struct("<HB")       # first step, count
#: Steps per LOAD frame and events per READLOG reply that fit in MAX_PAYLOAD.
MAX_STEPS_PER_LOAD = min(255, (MAX_PAYLOAD - LOAD_HEAD.size) // STEP.size)
MAX_EVENTS_PER_READ = min(255, (MAX_PAYLOAD - 1 - READLOG.size) // EVENT.size)


@dataclass(frozen=True)
class Step:
    """One step of a strobe sequence: move the arm to ``arm_position`` (if not there),
    fire ``strobe`` and trigger the cameras in ``camera_mask`` on the same 1/60 s tick."""

    arm_position: int
    strobe: int
    camera_mask: int = 0xFF

    def pack(self) -> bytes:
        return STEP.pack(self.arm_position, self.strobe, self.camera_mask)


@dataclass(frozen=True)
class Event:
    """What happened at one step: ``fired`` is False when the strobe's photodiode saw no flash."""

    step: int
    trigger: int
    arm_position: int
    strobe: int
    fired: bool
    time_us: int

    def pack(self) -> bytes:
        return EVENT.pack(self.step, self.trigger, self.arm_position, self.strobe, int(self.fired), self.time_us)

    @classmethod
    def unpack(cls, data: bytes, offset: int = 0) -> "Event":
        if len(data) < offset + EVENT.size:
            raise ProtocolError(f"EVENT: payload of {len(data) - offset} bytes, expected {EVENT.size}")
        s, trig, arm, strobe, fired, t = EVENT.unpack_from(data, offset)
        return cls(s, trig, arm, strobe, bool(fired), t)


@dataclass(frozen=True)
class Done:
    steps: int
    fired: int
    misfired: int
    aborted: bool

    def pack(self) -> bytes:
        return DONE.pack(self.steps, self.fired, self.misfired, int(self.aborted))

    @classmethod
    def unpack(cls, data: bytes) -> "Done":
        s, f, m, a = _unpack(DONE, data, "DONE")
        return cls(s, f, m, bool(a))


@dataclass(frozen=True)
class HelloInfo:
    protocol: int
    n_positions: int
    n_strobes: int
    n_cameras: int
    max_steps: int
    boot_id: int

    def pack(self) -> bytes:
        return HELLO.pack(self.protocol, self.n_positions, self.n_strobes, self.n_cameras, self.max_steps,
                          self.boot_id)

    @classmethod
    def unpack(cls, data: bytes) -> "HelloInfo":
        return cls(*_unpack(HELLO, data, "HELLO reply"))


@dataclass(frozen=True)
class StatusInfo:
    state: State
    arm_position: int
    boot_id: int
    trigger_counter: int
    steps_loaded: int
    steps_done: int
    misfires: int

    def pack(self) -> bytes:
        return STATUS.pack(int(self.state), self.arm_position, self.boot_id, self.trigger_counter,
                           self.steps_loaded, self.steps_done, self.misfires)

    @classmethod
    def unpack(cls, data: bytes) -> "StatusInfo":
        st, *rest = _unpack(STATUS, data, "STATUS reply")
        try:
            state = State(st)
        except ValueError:
            raise ProtocolError(f"STATUS reply: unknown state {st}") from None
        return cls(state, *rest)


def _unpack(st: struct.Struct, data: bytes, what: str) -> tuple:
    if len(data) != st.size:
        raise ProtocolError(f"{what}: payload is {len(data)} bytes, expected {st.size}")
    return st.unpack(data)


def pack_load(offset: int, steps: list[Step]) -> bytes:
    if len(steps) > MAX_STEPS_PER_LOAD:
        raise ProtocolError(f"at most {MAX_STEPS_PER_LOAD} steps per LOAD, got {len(steps)}")
    return LOAD_HEAD.pack(offset, len(steps)) + b"".join(s.pack() for s in steps)


def unpack_load(data: bytes) -> tuple[int, list[Step]]:
    if len(data) < LOAD_HEAD.size:
        raise ProtocolError("LOAD: payload shorter than its header")
    offset, count = LOAD_HEAD.unpack_from(data)
    if len(data) != LOAD_HEAD.size + count * STEP.size:
        raise ProtocolError(f"LOAD: {len(data)} bytes do not hold {count} steps")
    steps = [Step(*STEP.unpack_from(data, LOAD_HEAD.size + i * STEP.size)) for i in range(count)]
    return offset, steps


def pack_events(first: int, events: list[Event]) -> bytes:
    return READLOG.pack(first, len(events)) + b"".join(e.pack() for e in events)


def unpack_events(data: bytes) -> tuple[int, list[Event]]:
    if len(data) < READLOG.size:
        raise ProtocolError("READLOG reply: payload shorter than its header")
    first, count = READLOG.unpack_from(data)
    if len(data) != READLOG.size + count * EVENT.size:
        raise ProtocolError(f"READLOG reply: {len(data)} bytes do not hold {count} events")
    return first, [Event.unpack(data, READLOG.size + i * EVENT.size) for i in range(count)]


def pack_nak(command: int, reason: Reason, text: str) -> bytes:
    return bytes([command & 0xFF, int(reason)]) + text.encode("utf-8", "replace")[:MAX_PAYLOAD - 2]


def unpack_nak(data: bytes) -> tuple[int, Reason | int, str]:
    if len(data) < 2:
        raise ProtocolError("NAK: payload shorter than 2 bytes")
    try:
        reason: Reason | int = Reason(data[1])
    except ValueError:
        reason = data[1]
    return data[0], reason, data[2:].decode("utf-8", "replace")


def describe(frame: Frame) -> str:
    """A one-line human description of a frame (for logs and transcripts)."""
    m = frame.msg
    name = m.name if m else f"0x{frame.type:02x}"
    try:
        if m is Msg.NAK:
            cmd, reason, text = unpack_nak(frame.payload)
            r = reason.name if isinstance(reason, Reason) else reason
            return f"#{frame.seq} NAK {name_of(cmd)} {r}: {text}"
        if m is Msg.ACK and frame.payload:
            return f"#{frame.seq} ACK {name_of(frame.payload[0])} {frame.payload[1:].hex()}"
        if m is Msg.EVENT:
            return f"#{frame.seq} EVENT {Event.unpack(frame.payload)}"
        if m is Msg.DONE:
            return f"#{frame.seq} DONE {Done.unpack(frame.payload)}"
    except (ProtocolError, struct.error):
        pass
    return f"#{frame.seq} {name} {frame.payload.hex()}"


def name_of(t: int) -> str:
    try:
        return Msg(t).name
    except ValueError:
        return f"0x{t:02x}"
