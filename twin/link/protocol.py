"""The VRScroll serial protocol: framing, checksum and messages (see docs/protocol.md).

A frame on the wire is ``COBS(header | body | crc16) 0x00``:

- header: version u8, message id u8, sequence u16 (little-endian, 4 bytes);
- body: the message's fields, little-endian, integer firmware units;
- crc16: CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over header and body.

Pure functions only: `encode(msg)` gives the bytes of one frame, `Decoder.feed(data)`
gives the messages found in a stream of bytes, resyncing on the next 0x00 after
garbage and counting the frames it had to drop. Messages are dataclasses in SI-free
wire units (counts, microseconds, milliamps, duty * 32767); conversions to SI live
with their users (`PidGains` <-> `Gains` here, counts <-> angles in controllers.encoder).
"""

from __future__ import annotations

import dataclasses
import enum
import struct

PROTOCOL_VERSION = 1
MAX_FRAME = 512  # bytes of decoded payload (header + body + crc); longer is garbage
DUTY_SCALE = 32767  # duty [-1, 1] on the wire as int16 duty * 32767
GAIN_SCALE = 10_000_000  # kp, ki, kd on the wire as int32 gain * 1e7
CUTOFF_SCALE = 10  # derivative cutoff on the wire as uint16 Hz * 10
BROADCAST = 0xFF  # "every hinge" in SET_GAINS

# The gains the firmware accepts in SET_GAINS, in SI units, inclusive (docs/protocol.md, "Gain
# bounds"). The device refuses anything outside them with NACK BAD_VALUE; the host checks them
# before it sends anything. The derivative cutoff stays below the Nyquist rate of the 1 kHz loop.
GAIN_BOUNDS = {
    "kp": (0.0, 1.0),  # duty per count
    "ki": (0.0, 10.0),  # duty per count*s
    "kd": (0.0, 0.05),  # duty per count/s
    "derivative_cutoff": (1.0, 450.0),  # Hz
    "integral_limit": (0.0, 1.0),  # duty
    "deadband_duty": (0.0, 0.5),  # duty
    "hold_band": (0, 50),  # counts
}

_HEADER = struct.Struct("<BBH")


class MsgId(enum.IntEnum):
    # host -> device
    HELLO = 0x01
    HEARTBEAT = 0x02
    SET_TARGETS = 0x03
    SET_GAINS = 0x04
    GET_STATE = 0x05
    ESTOP = 0x06
    CLEAR_FAULT = 0x07
    SET_TELEMETRY_RATE = 0x08
    GET_GAINS = 0x09
    # device -> host
    ACK = 0x80
    NACK = 0x81
    HELLO_REPLY = 0x82
    STATE = 0x83
    GAINS = 0x84
    TELEMETRY = 0x90


class Nack(enum.IntEnum):
    """Why the device refused a command."""

    UNKNOWN_MESSAGE = 1
    BAD_LENGTH = 2
    BAD_VERSION = 3
    OUT_OF_RANGE = 4  # a target outside the hinge range
    BAD_STATE = 5  # e.g. SET_TARGETS while in ESTOP or FAULT
    BAD_VALUE = 6  # e.g. a telemetry rate over the maximum
    FAULT_PERSISTS = 7  # CLEAR_FAULT while the cause is still there


class State(enum.IntEnum):
    IDLE = 0  # motors off, no targets
    ACTIVE = 1  # PID holding the targets
    ESTOP = 2  # motors off after ESTOP; CLEAR_FAULT to leave
    FAULT = 3  # motors off after a fault; CLEAR_FAULT to leave


class Fault(enum.IntFlag):
    NONE = 0
    WATCHDOG = 0x01  # host quiet longer than the watchdog timeout
    ESTOP = 0x02  # ESTOP received
    STALL = 0x04  # a hinge did not move under high duty (jammed)
    LIMIT = 0x08  # a hinge passed its range
    OVERCURRENT = 0x10  # a winding current over the limit


class ProtocolError(ValueError):
    """A frame that cannot be decoded (bad COBS, CRC, length, version or id)."""


# ---- checksum and framing -----------------------------------------------------------

def _crc_table() -> list[int]:
    table = []
    for b in range(256):
        c = b << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no xor-out ("123456789" -> 0x29B1)."""
    c = 0xFFFF
    for b in data:
        c = ((c << 8) & 0xFFFF) ^ _CRC_TABLE[(c >> 8) ^ b]
    return c


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result has no 0x00 bytes."""
    out = bytearray([0])
    code_at, code = 0, 1
    for b in data:
        if b == 0:
            out[code_at] = code
            code_at, code = len(out), 1
            out.append(0)
        else:
            out.append(b)
            code += 1
            if code == 0xFF:
                out[code_at] = code
                code_at, code = len(out), 1
                out.append(0)
    out[code_at] = code
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of cobs_encode; ProtocolError on a malformed block."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError("COBS: zero byte inside a frame")
        end = i + code
        if end > n:
            raise ProtocolError("COBS: block runs past the end of the frame")
        block = data[i + 1:end]
        if 0 in block:
            raise ProtocolError("COBS: zero byte inside a frame")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


# ---- messages -----------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Hello:
    """Host -> device: start of a session; the device answers HelloReply."""

    MSG = MsgId.HELLO


@dataclasses.dataclass(frozen=True)
class Heartbeat:
    """Host -> device: 'still here'; feeds the device watchdog, not answered."""

    MSG = MsgId.HEARTBEAT


@dataclasses.dataclass(frozen=True)
class SetTargets:
    """Host -> device: hinge targets, encoder counts (int32 each)."""

    MSG = MsgId.SET_TARGETS
    counts: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class Gains:
    """PID gains in wire units: kp, ki, kd as gain * 1e7 (duty per count, per count*s, per count/s);
    cutoff Hz * 10; integral limit and deadband as duty * 32767; hold band in counts."""

    kp: int
    ki: int
    kd: int
    cutoff: int
    integral_limit: int
    deadband: int
    hold_band: int

    _FMT = struct.Struct("<iiiHHHH")

    @classmethod
    def from_pid(cls, g) -> "Gains":
        """From a controllers.pid.PidGains (SI) to wire units; rounds to the nearest step."""
        return cls(round(g.kp * GAIN_SCALE), round(g.ki * GAIN_SCALE), round(g.kd * GAIN_SCALE),
                   round(g.derivative_cutoff * CUTOFF_SCALE), round(g.integral_limit * DUTY_SCALE),
                   round(g.deadband_duty * DUTY_SCALE), int(g.hold_band))

    def to_pid(self):
        """The controllers.pid.PidGains these wire values stand for."""
        from controllers.pid import PidGains

        return PidGains(self.kp / GAIN_SCALE, self.ki / GAIN_SCALE, self.kd / GAIN_SCALE,
                        self.cutoff / CUTOFF_SCALE, self.integral_limit / DUTY_SCALE,
                        self.deadband / DUTY_SCALE, self.hold_band)


@dataclasses.dataclass(frozen=True)
class SetGains:
    """Host -> device: gains for one hinge (or BROADCAST = every hinge)."""

    MSG = MsgId.SET_GAINS
    hinge: int
    gains: Gains


@dataclasses.dataclass(frozen=True)
class GetState:
    MSG = MsgId.GET_STATE


@dataclasses.dataclass(frozen=True)
class EStop:
    """Host -> device: motors off now, latched until CLEAR_FAULT."""

    MSG = MsgId.ESTOP


@dataclasses.dataclass(frozen=True)
class ClearFault:
    """Host -> device: leave ESTOP/FAULT for IDLE; targets become the present counts."""

    MSG = MsgId.CLEAR_FAULT


@dataclasses.dataclass(frozen=True)
class SetTelemetryRate:
    """Host -> device: telemetry frames per second (0 = off, at most the device's maximum)."""

    MSG = MsgId.SET_TELEMETRY_RATE
    rate_hz: int


@dataclasses.dataclass(frozen=True)
class GetGains:
    """Host -> device: ask for one hinge's gains; the device answers GainsReply."""

    MSG = MsgId.GET_GAINS
    hinge: int


@dataclasses.dataclass(frozen=True)
class Ack:
    """Device -> host: command `acked` (its id) done at device time `time_us`; seq echoes the request."""

    MSG = MsgId.ACK
    acked: int
    time_us: int


@dataclasses.dataclass(frozen=True)
class NackMsg:
    """Device -> host: command `acked` refused for `reason` (Nack); `detail` e.g. the offending hinge."""

    MSG = MsgId.NACK
    acked: int
    reason: int
    detail: int


@dataclasses.dataclass(frozen=True)
class HelloReply:
    """Device -> host: firmware version, protocol version and the device's fixed figures."""

    MSG = MsgId.HELLO_REPLY
    firmware: tuple[int, int, int]
    protocol: int
    n_hinges: int
    loop_rate_hz: int
    watchdog_ms: int
    max_telemetry_hz: int


@dataclasses.dataclass(frozen=True)
class StateMsg:
    """Device -> host: state, faults, counts and targets at device time `time_us`."""

    MSG = MsgId.STATE
    firmware: tuple[int, int, int]
    state: int
    faults: int
    fault_hinge: int  # 0xFF: none
    time_us: int
    rx_bad_frames: int
    counts: tuple[int, ...]
    targets: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class GainsReply:
    MSG = MsgId.GAINS
    hinge: int
    gains: Gains


@dataclasses.dataclass(frozen=True)
class Telemetry:
    """Device -> host, streamed: one firmware tick. seq (in the header) counts telemetry frames.

    time_us: device time (u32, wraps after 71 min); duty: int16 duty * 32767; current: mA.
    """

    MSG = MsgId.TELEMETRY
    time_us: int
    state: int
    faults: int
    fault_hinge: int
    counts: tuple[int, ...]
    targets: tuple[int, ...]
    duty: tuple[int, ...]
    current_ma: tuple[int, ...]


# ---- body codecs ----------------------------------------------------------------------

def _counted(fmt: str, values) -> bytes:
    return struct.pack(f"<B{len(values)}{fmt}", len(values), *values)


def _encode_body(msg) -> bytes:
    m = msg.MSG
    if m in (MsgId.HELLO, MsgId.HEARTBEAT, MsgId.GET_STATE, MsgId.ESTOP, MsgId.CLEAR_FAULT):
        return b""
    if m == MsgId.SET_TARGETS:
        return _counted("i", msg.counts)
    if m in (MsgId.SET_GAINS, MsgId.GAINS):
        return struct.pack("<B", msg.hinge) + Gains._FMT.pack(*dataclasses.astuple(msg.gains))
    if m == MsgId.SET_TELEMETRY_RATE:
        return struct.pack("<H", msg.rate_hz)
    if m == MsgId.GET_GAINS:
        return struct.pack("<B", msg.hinge)
    if m == MsgId.ACK:
        return struct.pack("<BI", msg.acked, msg.time_us)
    if m == MsgId.NACK:
        return struct.pack("<BBB", msg.acked, msg.reason, msg.detail)
    if m == MsgId.HELLO_REPLY:
        return struct.pack("<BBBBBHHH", *msg.firmware, msg.protocol, msg.n_hinges, msg.loop_rate_hz,
                           msg.watchdog_ms, msg.max_telemetry_hz)
    if m == MsgId.STATE:
        return (struct.pack("<BBBBHBII", *msg.firmware, msg.state, msg.faults, msg.fault_hinge, msg.time_us,
                            msg.rx_bad_frames)
                + _counted("i", msg.counts) + struct.pack(f"<{len(msg.targets)}i", *msg.targets))
    if m == MsgId.TELEMETRY:
        n = len(msg.counts)
        return (struct.pack("<IBHBB", msg.time_us, msg.state, msg.faults, msg.fault_hinge, n)
                + struct.pack(f"<{n}i{n}i{n}h{n}h", *msg.counts, *msg.targets, *msg.duty, *msg.current_ma))
    raise ValueError(f"cannot encode {msg!r}")


def _need(body: bytes, size: int, what: str) -> None:
    if len(body) != size:
        raise ProtocolError(f"{what}: body of {len(body)} bytes, expected {size}")


def _decode_body(mid: int, body: bytes):
    try:
        m = MsgId(mid)
    except ValueError:
        raise ProtocolError(f"unknown message id 0x{mid:02x}") from None
    simple = {MsgId.HELLO: Hello, MsgId.HEARTBEAT: Heartbeat, MsgId.GET_STATE: GetState, MsgId.ESTOP: EStop,
              MsgId.CLEAR_FAULT: ClearFault}
    if m in simple:
        _need(body, 0, m.name)
        return simple[m]()
    if m == MsgId.SET_TARGETS:
        n = body[0] if body else -1
        _need(body, 1 + 4 * n, m.name)
        return SetTargets(struct.unpack(f"<{n}i", body[1:]))
    if m in (MsgId.SET_GAINS, MsgId.GAINS):
        _need(body, 1 + Gains._FMT.size, m.name)
        g = Gains(*Gains._FMT.unpack(body[1:]))
        return (SetGains if m == MsgId.SET_GAINS else GainsReply)(body[0], g)
    if m == MsgId.SET_TELEMETRY_RATE:
        _need(body, 2, m.name)
        return SetTelemetryRate(*struct.unpack("<H", body))
    if m == MsgId.GET_GAINS:
        _need(body, 1, m.name)
        return GetGains(body[0])
    if m == MsgId.ACK:
        _need(body, 5, m.name)
        return Ack(*struct.unpack("<BI", body))
    if m == MsgId.NACK:
        _need(body, 3, m.name)
        return NackMsg(*struct.unpack("<BBB", body))
    if m == MsgId.HELLO_REPLY:
        _need(body, 11, m.name)
        v = struct.unpack("<BBBBBHHH", body)
        return HelloReply(tuple(v[:3]), *v[3:])
    if m == MsgId.STATE:
        head = struct.Struct("<BBBBHBII")
        n = body[head.size] if len(body) > head.size else -1
        _need(body, head.size + 1 + 8 * n, m.name)
        v = head.unpack(body[:head.size])
        vals = struct.unpack(f"<{2 * n}i", body[head.size + 1:])
        return StateMsg(tuple(v[:3]), *v[3:], counts=vals[:n], targets=vals[n:])
    if m == MsgId.TELEMETRY:
        head = struct.Struct("<IBHBB")
        n = body[head.size - 1] if len(body) >= head.size else -1
        _need(body, head.size + 12 * n, m.name)
        t, state, faults, fh, _ = head.unpack(body[:head.size])
        v = struct.unpack(f"<{n}i{n}i{n}h{n}h", body[head.size:])
        return Telemetry(t, state, faults, fh, v[:n], v[n:2 * n], v[2 * n:3 * n], v[3 * n:])
    raise ProtocolError(f"no decoder for {m.name}")  # pragma: no cover


# ---- frames -------------------------------------------------------------------------

def encode(msg, seq: int) -> bytes:
    """One complete frame, delimiter included, for a message and a sequence number (mod 65536)."""
    payload = _HEADER.pack(PROTOCOL_VERSION, int(msg.MSG), seq & 0xFFFF) + _encode_body(msg)
    payload += struct.pack("<H", crc16(payload))
    if len(payload) > MAX_FRAME:
        raise ValueError(f"frame of {len(payload)} bytes is over the {MAX_FRAME}-byte maximum")
    return cobs_encode(payload) + b"\x00"


def decode_frame(frame: bytes) -> tuple[int, object]:
    """(seq, message) from one frame without its 0x00 delimiter; ProtocolError if it is not valid."""
    payload = cobs_decode(frame)
    if len(payload) < _HEADER.size + 2:
        raise ProtocolError(f"frame of {len(payload)} bytes is shorter than header and CRC")
    body, (crc,) = payload[:-2], struct.unpack("<H", payload[-2:])
    if crc16(body) != crc:
        raise ProtocolError("CRC mismatch")
    version, mid, seq = _HEADER.unpack(body[:_HEADER.size])
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"protocol version {version}, expected {PROTOCOL_VERSION}")
    return seq, _decode_body(mid, body[_HEADER.size:])


class Decoder:
    """Streaming frame decoder: feed it bytes as they come, get (seq, message) pairs back.

    Bytes up to each 0x00 are one candidate frame; a candidate that fails COBS, CRC,
    version, id or length checks is dropped and counted in `bad_frames`, and decoding
    resumes at the next delimiter. Candidates longer than MAX_FRAME are dropped as
    they grow, so garbage without delimiters cannot use up memory.
    """

    def __init__(self):
        self._buf = bytearray()
        self._overflow = False
        self.bad_frames = 0
        self.good_frames = 0
        self.last_error = ""

    def feed(self, data: bytes) -> list[tuple[int, object]]:
        out = []
        start = 0
        while True:
            end = data.find(b"\x00", start)
            chunk = data[start:] if end < 0 else data[start:end]
            if not self._overflow:
                self._buf += chunk
                if len(self._buf) > MAX_FRAME + MAX_FRAME // 254 + 2:
                    self._overflow, self._buf = True, bytearray()
            if end < 0:
                return out
            if self._overflow:
                self._bad("frame over the maximum length")
                self._overflow = False
            elif self._buf:
                try:
                    out.append(decode_frame(bytes(self._buf)))
                    self.good_frames += 1
                except (ProtocolError, struct.error, IndexError) as exc:
                    self._bad(str(exc))
            self._buf = bytearray()
            start = end + 1

    def _bad(self, why: str) -> None:
        self.bad_frames += 1
        self.last_error = why
