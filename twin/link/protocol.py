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

import binascii
import dataclasses
import enum
import struct

from controllers.pid import PidGains
from controllers.program import ProgramEnd  # noqa: F401  (the end reasons' one home; the header writes them)

PROTOCOL_VERSION = 7  # 2: the reset reason, the failed set-up step and the zero's state; CONFIRM_ZERO; HOLDING;
# 3: STATE carries each hinge's PID integral; 4: PROGRAM, GET_PROGRAM, PROGRAM_STATUS, PROGRAM_SAMPLE (PULSE is a
# program of one segment: the range and a stall end it); 5: SET_WIRING and WIRING carry each hinge's bridge;
# 6: SET_WIRING's WIRING_DISABLED flag, HELLO_REPLY and STATE carry the disabled hinges, NACK HINGE_DISABLED;
# 7: a PROGRAM segment may coast (PROGRAM_COAST), and a PROGRAM_SAMPLE says a coasting tick so
MAX_FRAME = 512  # bytes of decoded payload (header + body + crc); longer is garbage
DUTY_SCALE = 32767  # duty [-1, 1] on the wire as int16 duty * 32767
GAIN_SCALE = 10_000_000  # kp, ki, kd on the wire as int32 gain * 1e7
CUTOFF_SCALE = 10  # derivative cutoff on the wire as uint16 Hz * 10
BROADCAST = 0xFF  # "every hinge" in SET_GAINS
PULSE_MAX_DUTY = 0.4  # |duty| a bring-up PULSE may ask for
PULSE_MAX_MS = 500  # ms a PULSE may last
PROGRAM_MAX_SEGMENTS = 16  # segments (duty, duration) in one PROGRAM
PROGRAM_MAX_DUTY = 0.8  # |duty| a PROGRAM segment may ask for
PROGRAM_MAX_MS = 10_000  # ms a PROGRAM may last: its segments' sum and its timeout each (sample seqs stay < 2**16)
PROGRAM_LOOKAHEAD_MS = 40  # the window ends a program where the hinge would be this long ahead at its present speed
PROGRAM_RATE_TICKS = 8  # ticks over which the core measures that speed
PROGRAM_COAST = -32768  # a PROGRAM segment's duty (and a PROGRAM_SAMPLE's) that coasts: the windings open, no
# current, no back-EMF braking (the int16 below -DUTY_SCALE: no duty means it, and a core before version 7 refuses
# it as a duty past -1 rather than drive)
WIRING_ENCODER_REVERSED = 0x01  # SET_WIRING flags: the hinge's encoder counts the other way (A and B swapped)
WIRING_MOTOR_REVERSED = 0x02  # ... its motor turns the other way (its two leads swapped)
WIRING_DISABLED = 0x04  # ... the hinge is disabled: braked, never driven (a dead wire, or the user's choice); kept
# with the wiring across power cycles and CLEAR_FAULT alike

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
    CONFIRM_ZERO = 0x0A
    PULSE = 0x0B
    SET_WIRING = 0x0C
    GET_WIRING = 0x0D
    PROGRAM = 0x0E
    GET_PROGRAM = 0x0F
    # device -> host
    ACK = 0x80
    NACK = 0x81
    HELLO_REPLY = 0x82
    STATE = 0x83
    GAINS = 0x84
    WIRING = 0x85
    PROGRAM_STATUS = 0x86
    TELEMETRY = 0x90
    PROGRAM_SAMPLE = 0x91


class Nack(enum.IntEnum):
    """Why the device refused a command."""

    UNKNOWN_MESSAGE = 1
    BAD_LENGTH = 2
    BAD_VERSION = 3
    OUT_OF_RANGE = 4  # a target outside the hinge range
    BAD_STATE = 5  # e.g. SET_TARGETS while in ESTOP or FAULT
    BAD_VALUE = 6  # e.g. a telemetry rate over the maximum
    FAULT_PERSISTS = 7  # CLEAR_FAULT while the cause is still there
    ZERO_UNCONFIRMED = 8  # SET_TARGETS before CONFIRM_ZERO since the device started
    HINGE_DISABLED = 9  # a target that moves a disabled hinge, or a PULSE or PROGRAM on one (detail: the hinge)


class State(enum.IntEnum):
    IDLE = 0  # motors off, no targets
    ACTIVE = 1  # PID holding the targets
    ESTOP = 2  # motors off after ESTOP; CLEAR_FAULT to leave
    FAULT = 3  # motors off after a fault; CLEAR_FAULT to leave
    HOLDING = 4  # the host went quiet: the targets held for host_away_hold, then FAULT WATCHDOG; any frame resumes


class Fault(enum.IntFlag):
    NONE = 0
    WATCHDOG = 0x01  # host quiet longer than the watchdog timeout
    ESTOP = 0x02  # ESTOP received
    STALL = 0x04  # a hinge did not move under high duty (jammed)
    LIMIT = 0x08  # a hinge passed its range
    OVERCURRENT = 0x10  # a winding current over the limit
    HARDWARE = 0x20  # a peripheral's set-up failed at boot (HELLO_REPLY's setup_error names it); persists
    BATTERY = 0x40  # the battery reading is implausible (a broken divider, the ADC): PWM as for the nominal pack;
    # persists while the reading does
    RUNAWAY = 0x80  # a hinge moved against a high duty for a stall window (a reversed encoder or motor)


class ResetReason(enum.IntEnum):
    """Why the device last started: every esp_reset_reason_t (ESP-IDF v5.4.1, components/esp_system/include/
    esp_system.h)."""

    UNKNOWN = 0
    POWERON = 1
    EXT = 2  # the reset pin
    SW = 3  # esp_restart()
    PANIC = 4  # an exception or abort
    INT_WDT = 5  # the interrupt watchdog
    TASK_WDT = 6  # the task watchdog: loop() held too long
    WDT = 7  # another watchdog
    DEEPSLEEP = 8
    BROWNOUT = 9  # the supply sagged below the brown-out level
    SDIO = 10
    USB = 11  # the USB peripheral (the S3 after a USB reset, e.g. an upload)
    JTAG = 12
    EFUSE = 13  # an eFuse error
    PWR_GLITCH = 14  # a power glitch detected
    CPU_LOCKUP = 15  # a CPU lock-up (double exception)


class SetupStep(enum.IntEnum):
    """The board's set-up call that failed (HELLO_REPLY setup_error; 0: none). The sketch reports the first
    failure with the hinge it was setting up as the HARDWARE fault's hinge."""

    NONE = 0
    PWM_TIMER = 1  # mcpwm_new_timer / enable / start
    PWM_OPERATOR = 2  # mcpwm_new_operator / connect_timer
    PWM_COMPARATOR = 3  # mcpwm_new_comparator
    PWM_GENERATOR = 4  # mcpwm_new_generator / its actions
    ENCODER_COUNTER = 5  # pcnt_new_unit / channels / actions / glitch filter / watch points / start
    TICK_TIMER = 6  # timerBegin
    SERIAL = 7  # Serial's receive buffer


def enum_name(kind, value: int) -> str:
    """The member's name, or the number for a value the table does not have (a newer device's)."""
    return kind(value).name if value in kind._value2member_map_ else str(value)


class ProtocolError(ValueError):
    """A frame that cannot be decoded (bad COBS, CRC, length, version or id)."""


class VersionError(ProtocolError):
    """An intact frame (its CRC good) of another protocol version: `version`, the one its sender speaks."""

    def __init__(self, version: int):
        self.version = version
        super().__init__(f"protocol version {version}, expected {PROTOCOL_VERSION}")


def elapsed_s(since_us: int, now_us: int) -> float:
    """s from `since_us` to `now_us` on the device's clock (time_us: u32 microseconds, wrapping after 71 min); a
    time before since_us wraps to about 71 min."""
    return ((now_us - since_us) & 0xFFFFFFFF) / 1e6


# ---- checksum and framing -----------------------------------------------------------

def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no xor-out ("123456789" -> 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


# COBS stays written out here (about 30 lines, checked against the reference vectors in
# tests/firmware/test_protocol.py): a package would add a dependency without sparing a test, and the
# firmware core has its own C version (vrs_wire.c), which the golden-frame tests hold to this one.

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

    @classmethod
    def from_pid(cls, g) -> "Gains":
        """From a controllers.pid.PidGains (SI) to wire units; rounds to the nearest step."""
        return cls(round(g.kp * GAIN_SCALE), round(g.ki * GAIN_SCALE), round(g.kd * GAIN_SCALE),
                   round(g.derivative_cutoff * CUTOFF_SCALE), round(g.integral_limit * DUTY_SCALE),
                   round(g.deadband_duty * DUTY_SCALE), int(g.hold_band))

    def to_pid(self) -> PidGains:
        """The controllers.pid.PidGains these wire values stand for."""
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
class ConfirmZero:
    """Host -> device: the flaps lie flat now; their counts become zero. IDLE only; SET_TARGETS is refused
    (ZERO_UNCONFIRMED) from every start until this."""

    MSG = MsgId.CONFIRM_ZERO


@dataclasses.dataclass(frozen=True)
class Pulse:
    """Host -> device, for bring-up: drive one hinge's motor open loop at duty (int16 duty * 32767, at most
    PULSE_MAX_DUTY) for duration_ms (at most PULSE_MAX_MS), the others braked. IDLE only; the hinge's range
    still ends it."""

    MSG = MsgId.PULSE
    hinge: int
    duty: int
    duration_ms: int


@dataclasses.dataclass(frozen=True)
class Program:
    """Host -> device, for identification: an open-loop duty program on one hinge, the others braked. Segments
    0..n_segments-1 of `duty` (int16 duty * 32767, each at most PROGRAM_MAX_DUTY) and `duration_ms` run in
    order (the rest are zeros); a segment whose duty is PROGRAM_COAST coasts (its windings open). The core ends
    it itself at the window [low, high] (counts, within the hinge's range, the hinge inside it now), on a stall,
    after timeout_ms, when the host goes quiet, on any state change, braking the hinge. IDLE with the zero
    confirmed only; PROGRAM_SAMPLE streams its ticks, GET_PROGRAM tells its end."""

    MSG = MsgId.PROGRAM
    hinge: int
    low: int
    high: int
    timeout_ms: int
    n_segments: int
    duty: tuple[int, ...]
    duration_ms: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class GetProgram:
    """Host -> device: how the last program stands; the device answers ProgramStatus."""

    MSG = MsgId.GET_PROGRAM


@dataclasses.dataclass(frozen=True)
class ProgramStatus:
    """Device -> host: the last program (or PULSE): its hinge (0xFF: none since the start), `end`
    (ProgramEnd: RUNNING while it runs), the ticks it ran (one PROGRAM_SAMPLE each), the samples its transmit
    queue had to drop, the battery it read at the end (mV, 0: not sensed) and the hinge's counts now."""

    MSG = MsgId.PROGRAM_STATUS
    hinge: int
    end: int
    ticks: int
    dropped: int
    battery_mv: int
    counts: int


@dataclasses.dataclass(frozen=True)
class ProgramSample:
    """Device -> host, streamed while a program runs: one tick, its index from the program's start in the
    header's seq: the hinge's counts read in it and the duty applied from it (int16 duty * 32767; PROGRAM_COAST:
    the hinge coasts from it)."""

    MSG = MsgId.PROGRAM_SAMPLE
    counts: int
    duty: int


@dataclasses.dataclass(frozen=True)
class SetWiring:
    """Host -> device: the wiring correction per hinge: which encoder input is the hinge's (a permutation),
    WIRING_* flags, and which H-bridge drives its motor (a permutation: motors on each other's bridges). IDLE
    only; the device keeps it across power cycles; the zero must be confirmed again."""

    MSG = MsgId.SET_WIRING
    encoder: tuple[int, ...]
    flags: tuple[int, ...]
    bridge: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class GetWiring:
    MSG = MsgId.GET_WIRING


@dataclasses.dataclass(frozen=True)
class WiringReply:
    """Device -> host: the wiring correction the device applies (SetWiring's fields)."""

    MSG = MsgId.WIRING
    encoder: tuple[int, ...]
    flags: tuple[int, ...]
    bridge: tuple[int, ...]


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
    reset_reason: int = ResetReason.UNKNOWN  # ResetReason: why the device last started
    setup_error: int = SetupStep.NONE  # SetupStep: the first set-up call that failed at boot
    zero_confirmed: int = 0  # 1 once CONFIRM_ZERO was heard since the start
    wiring_set: int = 0  # 1 when a wiring correction other than the identity is applied
    disabled: int = 0  # bit k: hinge k is disabled (SET_WIRING's WIRING_DISABLED): braked, never driven


@dataclasses.dataclass(frozen=True)
class StateMsg:
    """Device -> host: state, faults, counts, targets and PID integrals at device time `time_us`."""

    MSG = MsgId.STATE
    firmware: tuple[int, int, int]
    state: int
    faults: int
    fault_hinge: int  # 0xFF: none
    time_us: int
    rx_bad_frames: int
    counts: tuple[int, ...]
    targets: tuple[int, ...]
    integral: tuple[int, ...]  # each hinge's PID integral, duty * DUTY_SCALE: the effort it holds a load with
    zero_confirmed: int = 0  # 1 once CONFIRM_ZERO was heard since the start
    derated: int = 0  # bit k: hinge k's duty held to its continuous rating by the I2t protection
    disabled: int = 0  # bit k: hinge k is disabled (SET_WIRING's WIRING_DISABLED): braked, never driven

    @property
    def integral_duty(self) -> tuple[float, ...]:
        """Each hinge's PID integral, duty (-1 to 1)."""
        return tuple(x / DUTY_SCALE for x in self.integral)


@dataclasses.dataclass(frozen=True)
class GainsReply:
    MSG = MsgId.GAINS
    hinge: int
    gains: Gains


# what answers a request: these their data, every other command an ACK (or a NACK) naming it
REPLY_TO = {MsgId.HELLO: MsgId.HELLO_REPLY, MsgId.GET_STATE: MsgId.STATE, MsgId.GET_GAINS: MsgId.GAINS,
            MsgId.GET_WIRING: MsgId.WIRING, MsgId.GET_PROGRAM: MsgId.PROGRAM_STATUS}


def answers(request: "MsgId", reply) -> bool:
    """Whether `reply` (a decoded message) answers a request of id `request`: its data, or an ACK or NACK
    naming it. Anything else with the request's sequence number (an echo of the host's own frame on a
    looped-back line, a reply to another command) is not its answer."""
    if isinstance(reply, (Ack, NackMsg)):
        return reply.acked == request and (isinstance(reply, NackMsg) or request not in REPLY_TO)
    return reply.MSG == REPLY_TO.get(request)


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


# ---- the message table ----------------------------------------------------------------
#
# Each message's body, written once: its fixed fields in order, then (for messages that carry a
# value per hinge) a count byte n and each per-hinge field as an array of n. A field's format is a
# struct code (B H I h i: u8 u16 u32 i16 i32), "3B" for a tuple of three u8, or "gains" for the
# 20-byte gains block. `encode` and `decode_frame` read this table, and
# twin/link/firmware_header.py writes it into the C firmware's header.

GAINS_BLOCK = (("kp", "i"), ("ki", "i"), ("kd", "i"), ("cutoff", "H"), ("integral_limit", "H"),
               ("deadband", "H"), ("hold_band", "H"))


@dataclasses.dataclass(frozen=True)
class Layout:
    """One message's body: fixed fields (name, format), then per-hinge fields after a count byte."""

    cls: type
    fields: tuple = ()
    per_hinge: tuple = ()

    @property
    def codes(self) -> str:
        """The struct codes of the fixed part, tuples and the gains block spelled out ("BBBBHBII")."""
        return "".join(_codes(f) for _, f in self.fields)

    @property
    def hinge_codes(self) -> str:
        return "".join(f for _, f in self.per_hinge)

    @property
    def fixed_size(self) -> int:
        return struct.calcsize("<" + self.codes) + (1 if self.per_hinge else 0)

    @property
    def hinge_size(self) -> int:
        """Body bytes per hinge (0: the message has no per-hinge part)."""
        return struct.calcsize("<" + self.hinge_codes) if self.per_hinge else 0


def _repeat(fmt: str) -> int:
    """How many values a field of format fmt holds as a tuple ("3B": 3, "16h": 16); 0 for a single value."""
    return int(fmt[:-1]) if fmt[0].isdigit() else 0


def _codes(fmt: str) -> str:
    if fmt == "gains":
        return "".join(f for _, f in GAINS_BLOCK)
    return fmt[-1] * _repeat(fmt) if _repeat(fmt) else fmt


LAYOUTS = {
    MsgId.HELLO: Layout(Hello),
    MsgId.HEARTBEAT: Layout(Heartbeat),
    MsgId.SET_TARGETS: Layout(SetTargets, per_hinge=(("counts", "i"),)),
    MsgId.SET_GAINS: Layout(SetGains, (("hinge", "B"), ("gains", "gains"))),
    MsgId.GET_STATE: Layout(GetState),
    MsgId.ESTOP: Layout(EStop),
    MsgId.CLEAR_FAULT: Layout(ClearFault),
    MsgId.CONFIRM_ZERO: Layout(ConfirmZero),
    MsgId.PULSE: Layout(Pulse, (("hinge", "B"), ("duty", "h"), ("duration_ms", "H"))),
    MsgId.SET_WIRING: Layout(SetWiring, per_hinge=(("encoder", "B"), ("flags", "B"), ("bridge", "B"))),
    MsgId.GET_WIRING: Layout(GetWiring),
    MsgId.PROGRAM: Layout(Program, (("hinge", "B"), ("low", "i"), ("high", "i"), ("timeout_ms", "H"),
                                    ("n_segments", "B"), ("duty", f"{PROGRAM_MAX_SEGMENTS}h"),
                                    ("duration_ms", f"{PROGRAM_MAX_SEGMENTS}H"))),
    MsgId.GET_PROGRAM: Layout(GetProgram),
    MsgId.PROGRAM_STATUS: Layout(ProgramStatus, (("hinge", "B"), ("end", "B"), ("ticks", "I"), ("dropped", "I"),
                                                 ("battery_mv", "H"), ("counts", "i"))),
    MsgId.PROGRAM_SAMPLE: Layout(ProgramSample, (("counts", "i"), ("duty", "h"))),
    MsgId.WIRING: Layout(WiringReply, per_hinge=(("encoder", "B"), ("flags", "B"), ("bridge", "B"))),
    MsgId.SET_TELEMETRY_RATE: Layout(SetTelemetryRate, (("rate_hz", "H"),)),
    MsgId.GET_GAINS: Layout(GetGains, (("hinge", "B"),)),
    MsgId.ACK: Layout(Ack, (("acked", "B"), ("time_us", "I"))),
    MsgId.NACK: Layout(NackMsg, (("acked", "B"), ("reason", "B"), ("detail", "B"))),
    MsgId.HELLO_REPLY: Layout(HelloReply, (("firmware", "3B"), ("protocol", "B"), ("n_hinges", "B"),
                                           ("loop_rate_hz", "H"), ("watchdog_ms", "H"), ("max_telemetry_hz", "H"),
                                           ("reset_reason", "B"), ("setup_error", "B"), ("zero_confirmed", "B"),
                                           ("wiring_set", "B"), ("disabled", "B"))),
    MsgId.STATE: Layout(StateMsg, (("firmware", "3B"), ("state", "B"), ("faults", "H"), ("fault_hinge", "B"),
                                   ("time_us", "I"), ("rx_bad_frames", "I"), ("zero_confirmed", "B"), ("derated", "B"),
                                   ("disabled", "B")),
                        (("counts", "i"), ("targets", "i"), ("integral", "h"))),
    MsgId.GAINS: Layout(GainsReply, (("hinge", "B"), ("gains", "gains"))),
    MsgId.TELEMETRY: Layout(Telemetry, (("time_us", "I"), ("state", "B"), ("faults", "H"), ("fault_hinge", "B")),
                            (("counts", "i"), ("targets", "i"), ("duty", "h"), ("current_ma", "h"))),
}


def wire_values(msg) -> tuple[list[int], int]:
    """A message's body as integers in table order (fixed fields, then each per-hinge field's n
    values) and its hinge count n (0 for messages without per-hinge fields)."""
    lay = LAYOUTS[msg.MSG]
    values = []
    for name, fmt in lay.fields:
        v = getattr(msg, name)
        if _repeat(fmt) and len(v) != _repeat(fmt):
            raise ValueError(f"{msg.MSG.name}: {name} has {len(v)} values, expected {_repeat(fmt)}")
        values += dataclasses.astuple(v) if fmt == "gains" else (v if _repeat(fmt) else (v,))
    arrays = [tuple(getattr(msg, name)) for name, _ in lay.per_hinge]
    n = len(arrays[0]) if arrays else 0
    if any(len(a) != n for a in arrays):
        raise ValueError(f"{msg.MSG.name}: per-hinge fields of different lengths")
    return [int(v) for v in values] + [int(v) for a in arrays for v in a], n


def _encode_body(msg) -> bytes:
    lay = LAYOUTS[msg.MSG]
    values, n = wire_values(msg)
    codes = "<" + lay.codes + (f"B{''.join(str(n) + c for c in lay.hinge_codes)}" if lay.per_hinge else "")
    k = len(lay.codes)
    return struct.pack(codes, *values[:k], *([n] if lay.per_hinge else []), *values[k:])


def _decode_body(mid: int, body: bytes):
    try:
        m = MsgId(mid)
    except ValueError:
        raise ProtocolError(f"unknown message id 0x{mid:02x}") from None
    lay = LAYOUTS[m]
    n = 0
    if lay.per_hinge:
        n = body[lay.fixed_size - 1] if len(body) >= lay.fixed_size else -1
    size = lay.fixed_size + n * lay.hinge_size
    if n < 0 or len(body) != size:
        raise ProtocolError(f"{m.name}: body of {len(body)} bytes, expected {size}")
    flat = iter(struct.unpack("<" + lay.codes, body[:struct.calcsize("<" + lay.codes)]))
    kwargs = {}
    for name, fmt in lay.fields:
        if fmt == "gains":
            kwargs[name] = Gains(*(next(flat) for _ in GAINS_BLOCK))
        elif _repeat(fmt):
            kwargs[name] = tuple(next(flat) for _ in range(_repeat(fmt)))
        else:
            kwargs[name] = next(flat)
    pos = lay.fixed_size
    for name, fmt in lay.per_hinge:
        kwargs[name] = struct.unpack_from(f"<{n}{fmt}", body, pos)
        pos += n * struct.calcsize(fmt)
    return lay.cls(**kwargs)


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
    if len(payload) > MAX_FRAME:
        raise ProtocolError(f"payload of {len(payload)} bytes is over the {MAX_FRAME}-byte maximum")
    if len(payload) < _HEADER.size + 2:
        raise ProtocolError(f"frame of {len(payload)} bytes is shorter than header and CRC")
    body, (crc,) = payload[:-2], struct.unpack("<H", payload[-2:])
    if crc16(body) != crc:
        raise ProtocolError("CRC mismatch")
    version, mid, seq = _HEADER.unpack(body[:_HEADER.size])
    if version != PROTOCOL_VERSION:
        raise VersionError(version)
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
        self.other_version = None  # the version of the last intact frame of another protocol version

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
                    if isinstance(exc, VersionError):
                        self.other_version = exc.version
            self._buf = bytearray()
            start = end + 1

    def _bad(self, why: str) -> None:
        self.bad_frames += 1
        self.last_error = why
