"""The wire protocol's codec: round trips, CRC and COBS, and a decoder that survives any bytes."""

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.pid import PidGains
from twin.link import protocol as P

MESSAGES = [
    P.Hello(), P.Heartbeat(), P.GetState(), P.EStop(), P.ClearFault(), P.ConfirmZero(),
    P.SetTargets((1, -2, 3, 2**31 - 1, -(2**31), 0)),
    P.SetGains(P.BROADCAST, P.Gains(200000, 200000, 4000, 500, 9830, 983, 2)),
    P.SetTelemetryRate(500), P.GetGains(5), P.Pulse(2, -13107, 150), P.GetWiring(),
    P.SetWiring((0, 3, 2, 1, 4, 5), (0, 0, 1, 2, 3, 0), (1, 0, 2, 3, 4, 5)),
    P.WiringReply((5, 4, 3, 2, 1, 0), (3, 0, 0, 0, 0, 1), (0, 1, 2, 3, 5, 4)),
    P.Ack(P.MsgId.SET_TARGETS, 2**32 - 1), P.NackMsg(P.MsgId.SET_TARGETS, P.Nack.OUT_OF_RANGE, 3),
    P.HelloReply((1, 2, 3), 1, 6, 1000, 200, 500, P.ResetReason.BROWNOUT, P.SetupStep.PWM_TIMER, 1, 0, 0b010001),
    P.StateMsg((0, 1, 0), P.State.HOLDING, P.Fault.STALL | P.Fault.HARDWARE, 2, 123456, 7, (1,) * 6, (-1,) * 6,
               (32767, -32767, 0, 1, -1, 9830), 1, 0b100101, 0b001010),
    P.SetWiring((0, 1, 2, 3, 4, 5), (0, P.WIRING_DISABLED, 0, 0, 0, P.WIRING_DISABLED | 1), (0, 1, 2, 3, 4, 5)),
    P.GainsReply(0, P.Gains(1, 2, 3, 4, 5, 6, 7)),
    P.Telemetry(999, P.State.FAULT, P.Fault.ESTOP, 255, (1, 2, 3, 4, 5, 6), (6, 5, 4, 3, 2, 1),
                (32767, -32767, 0, 1, -1, 100), (1600, -1600, 0, 0, 5, -5)),
    P.Program(3, -300, 2**31 - 1, P.PROGRAM_MAX_MS, 2, (26214, -32768) + (0,) * (P.PROGRAM_MAX_SEGMENTS - 2),
              (65535, 1) + (0,) * (P.PROGRAM_MAX_SEGMENTS - 2)),
    P.Program(2, -376, 376, 400, 3, (9830, 0, -26214) + (0,) * (P.PROGRAM_MAX_SEGMENTS - 3),
              (200, 50, 150) + (0,) * (P.PROGRAM_MAX_SEGMENTS - 3)),  # one the core runs (the fuzz corpus has it)
    P.GetProgram(), P.ProgramStatus(255, P.ProgramEnd.HOST_QUIET, 2**32 - 1, 7, 7400, -(2**31)),
    P.ProgramSample(-376, -26214),
]


def test_crc_and_cobs_reference_values():
    assert P.crc16(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE check value
    assert P.cobs_encode(b"\x00") == b"\x01\x01"
    assert P.cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert P.cobs_encode(bytes(range(1, 255))) == b"\xff" + bytes(range(1, 255)) + b"\x01"


@given(st.binary(max_size=700))
def test_cobs_round_trip_has_no_zeros(data):
    enc = P.cobs_encode(data)
    assert 0 not in enc
    assert P.cobs_decode(enc) == data


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: type(m).__name__)
def test_every_message_round_trips(msg):
    frame = P.encode(msg, 4242)
    assert frame.endswith(b"\x00") and 0 not in frame[:-1]
    assert P.decode_frame(frame[:-1]) == (4242, msg)


def test_wire_layout_is_little_endian_with_version_id_seq_header():
    payload = P.cobs_decode(P.encode(P.SetTargets((1, -1)), 0x1234)[:-1])
    assert payload[:4] == bytes([P.PROTOCOL_VERSION, 0x03, 0x34, 0x12])
    assert payload[4:-2] == b"\x02" + struct.pack("<ii", 1, -1)
    assert struct.unpack("<H", payload[-2:])[0] == P.crc16(payload[:-2])


def test_gains_fixed_point_round_trip(spec):
    g = PidGains.from_spec(spec)
    back = P.Gains.from_pid(g).to_pid()
    for name in ("kp", "ki", "kd", "derivative_cutoff", "integral_limit", "deadband_duty"):
        assert getattr(back, name) == pytest.approx(getattr(g, name), rel=1e-3, abs=1e-7), name
    assert back.hold_band == g.hold_band


@pytest.mark.parametrize("damage", ["flip", "truncate", "version", "unknown_id", "short_body"])
def test_decoder_rejects_and_counts_damaged_frames(damage):
    good = P.encode(P.SetTargets((1, 2, 3, 4, 5, 6)), 7)
    payload = bytearray(P.cobs_decode(good[:-1]))
    if damage == "flip":
        bad = bytearray(good)
        bad[5] ^= 0x40
        bad = bytes(bad)
    else:
        if damage == "truncate":
            payload = payload[:3]
        elif damage == "version":
            payload[0] = 9
        elif damage == "unknown_id":
            payload[1] = 0x55
        elif damage == "short_body":
            payload = payload[:-6]
        if damage in ("version", "unknown_id", "short_body"):
            payload = payload[:-2] if damage != "short_body" else payload
            payload += struct.pack("<H", P.crc16(bytes(payload)))
        bad = P.cobs_encode(bytes(payload)) + b"\x00"
    d = P.Decoder()
    out = d.feed(bad + good)
    assert out == [(7, P.SetTargets((1, 2, 3, 4, 5, 6)))]  # resynced on the next frame
    assert d.bad_frames == 1 and d.good_frames == 1


def test_decoder_drops_overlong_garbage_without_growing():
    d = P.Decoder()
    assert d.feed(b"\x01" * 100_000) == []
    assert len(d._buf) <= P.MAX_FRAME + 10
    good = P.encode(P.GetState(), 1)
    assert d.feed(b"\x00" + good) == [(1, P.GetState())]
    assert d.bad_frames == 1


@settings(max_examples=300)
@given(st.lists(st.one_of(st.binary(max_size=300), st.sampled_from(MESSAGES)), max_size=12),
       st.lists(st.integers(1, 64), max_size=20))
def test_decoder_never_crashes_and_finds_every_intact_frame(parts, cuts):
    """Valid frames mixed with random garbage, delivered in random chunks: every frame
    that follows a delimiter comes out, garbage is counted, nothing raises."""
    stream, expected = bytearray(), []
    for i, part in enumerate(parts):
        if isinstance(part, bytes):
            stream += part
        else:
            stream += b"\x00" + P.encode(part, i)  # the leading 0x00 ends any garbage before it
            expected.append((i, part))
    d = P.Decoder()
    got, pos = [], 0
    for c in cuts + [len(stream)]:
        got += d.feed(bytes(stream[pos:pos + c]))
        pos += c
    got += d.feed(bytes(stream[pos:]))
    # garbage may itself hold a valid frame only with ~2^-16 odds per candidate: compare the intact ones
    assert [g for g in got if g in expected] == expected
    assert d.good_frames == len(got)


@given(st.binary(max_size=2000))
def test_decoder_on_pure_noise(data):
    d = P.Decoder()
    d.feed(data)
    assert d.bad_frames + d.good_frames <= data.count(0) + 1


def test_a_newer_devices_states_and_faults_are_named_by_number_not_a_traceback():
    from twin.hil.mirror import faults_text

    assert P.enum_name(P.State, P.State.HOLDING) == "HOLDING" and P.enum_name(P.State, 9) == "9"
    assert faults_text(P.Fault.WATCHDOG | P.Fault.HARDWARE | 0x8000) == "WATCHDOG|HARDWARE|0x8000"
    assert faults_text(0) == "none"


@pytest.mark.parametrize("since_us, now_us, seconds", [(1_000, 251_000, 0.25),
                                                        (0xFFFF_FF00, 0x100, 512e-6),  # across the u32 wrap
                                                        (5_000, 4_000, (2**32 - 1_000) / 1e6)])  # before: ~71 min
def test_the_devices_clock_is_read_across_its_wrap(since_us, now_us, seconds):
    """One reading of the device's u32 microsecond clock for telemetry, ACKs and bring-up's waits (issue 39: the
    unwrap was written out four times)."""
    assert P.elapsed_s(since_us, now_us) == pytest.approx(seconds, abs=1e-9)
