"""The C core's wire codec against the Python host's: golden frames both ways, and fuzzing of the
core's parser (in process, and the same corpus under AddressSanitizer and UBSan)."""

import ctypes
import random
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers import core
from controllers.pid import PidGains
from test_protocol import MESSAGES
from twin.link import protocol as P

FUZZ_DRIVER = Path(__file__).parent / "fuzz_driver.c"

# every message of tests/firmware/test_protocol.py, and a few more at the edges of their ranges
GOLDEN = MESSAGES + [
    P.SetGains(3, P.Gains(-1, 2**31 - 1, -(2**31), 65535, 0, 1, 65535)),
    P.Telemetry(0, 0, 0, 0, (7,), (8,), (-32768,), (32767,)),
    P.SetTargets((0,) * 8),
]


def c_encode(msg, seq: int) -> bytes:
    lib = core.library()
    values, n = P.wire_values(msg)
    arr = (ctypes.c_uint32 * max(1, len(values)))(*(v & 0xFFFFFFFF for v in values))
    out = ctypes.create_string_buffer(1024)
    size = lib.vrs_encode(int(msg.MSG), seq, ctypes.addressof(arr), n, ctypes.addressof(out), len(out))
    assert size > 0
    return out.raw[:size]


def c_decode(frame: bytes) -> tuple[int, int, int, list[int], int]:
    """(result, msg id, seq, values as 32-bit patterns, n) from the C decoder; frame without its 0x00."""
    lib = core.library()
    mid, seq, n = ctypes.c_uint8(), ctypes.c_uint16(), ctypes.c_uint8()
    values = (ctypes.c_uint32 * 64)()
    r = lib.vrs_decode(frame, len(frame), ctypes.addressof(mid), ctypes.addressof(seq), ctypes.addressof(values),
                       ctypes.addressof(n))
    return r, mid.value, seq.value, list(values), n.value


def test_golden_frames_cover_every_message():
    assert {m.MSG for m in GOLDEN} == set(P.MsgId)


@pytest.mark.parametrize("seq", [0, 1, 0x1234, 0xFFFF])
@pytest.mark.parametrize("msg", GOLDEN, ids=lambda m: type(m).__name__)
def test_c_and_python_frames_are_byte_identical_and_decode_each_other(msg, seq):
    py = P.encode(msg, seq)
    c = c_encode(msg, seq)
    assert c == py
    assert P.decode_frame(c[:-1]) == (seq, msg)
    r, mid, got_seq, values, n = c_decode(py[:-1])
    want, want_n = P.wire_values(msg)
    assert (r, mid, got_seq, n) == (0, int(msg.MSG), seq, want_n)
    assert values[:len(want)] == [v & 0xFFFFFFFF for v in want]


@settings(max_examples=200)
@given(st.integers(1, 8).flatmap(lambda n: st.tuples(
    st.lists(st.integers(-(2**31), 2**31 - 1), min_size=n, max_size=n),
    st.lists(st.integers(-(2**31), 2**31 - 1), min_size=n, max_size=n),
    st.lists(st.integers(-(2**15), 2**15 - 1), min_size=n, max_size=n),
    st.lists(st.integers(-(2**15), 2**15 - 1), min_size=n, max_size=n))),
    st.integers(0, 2**32 - 1), st.integers(0, 0xFFFF))
def test_random_telemetry_is_byte_identical(arrays, time_us, seq):
    msg = P.Telemetry(time_us, 1, 0x1F, 3, *(tuple(a) for a in arrays))
    assert c_encode(msg, seq) == P.encode(msg, seq)


def test_crc_matches_the_reference():
    assert core.library().vrs_crc16(b"123456789", 9) == 0x29B1 == P.crc16(b"123456789")


# ---- fuzzing the core's parser ------------------------------------------------------------------

def _core(spec) -> core.Core:
    return core.Core(core.config_from_spec(spec), [PidGains.from_spec(spec)] * spec.n_hinges, [0] * spec.n_hinges)


def _damaged(msg, seq: int, rng: random.Random) -> bytes:
    """A frame the parser must drop: a payload byte changed under a valid COBS layer (the CRC catches
    every single-byte error), a payload too short for header and CRC, or an unterminated run longer
    than any frame (dropped at the next 0x00)."""
    payload = bytearray(P.cobs_decode(P.encode(msg, seq)[:-1]))
    kind = rng.randrange(3)
    if kind == 0:
        i = rng.randrange(len(payload))
        payload[i] ^= rng.randrange(1, 256)
        return P.cobs_encode(bytes(payload)) + b"\x00"
    if kind == 1:
        return P.cobs_encode(bytes(payload[:rng.randrange(1, 6)])) + b"\x00"
    return bytes(rng.randrange(1, 256) for _ in range(P.MAX_FRAME + 8 + rng.randrange(200))) + b"\x00"


def corpus(seed: int, count: int) -> list[tuple[bytes, int]]:
    """(stream, damaged frames in it): valid commands, damaged frames and random garbage (closed by
    0x00 before the next frame). Deterministic in seed; the sanitizer build runs the same streams."""
    rng = random.Random(seed)
    commands = [m for m in GOLDEN if m.MSG < 0x80]
    out = []
    for _ in range(count):
        stream, bad = bytearray(), 0
        for _ in range(rng.randrange(1, 12)):
            kind, msg, seq = rng.randrange(3), rng.choice(commands), rng.randrange(65536)
            if kind == 0:
                stream += P.encode(msg, seq)
            elif kind == 1:
                stream += _damaged(msg, seq, rng)
                bad += 1
            else:
                stream += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300))) + b"\x00"
        out.append((bytes(stream), bad))
    return out


def _answers_get_state(c: core.Core, now_us: int) -> bool:
    c.tx()
    c.rx(b"\x00" + P.encode(P.GetState(), 0xBEEF), now_us)
    return any(seq == 0xBEEF and isinstance(m, P.StateMsg) for seq, m in P.Decoder().feed(c.tx()))


def test_damaged_frames_are_counted_and_the_next_good_frame_understood(spec):
    for stream, bad in corpus(1, 100):
        c = _core(spec)
        c.rx(stream, 0)
        assert c.rx_bad_frames >= bad
        before = c.rx_bad_frames
        assert _answers_get_state(c, 1000)
        assert c.rx_bad_frames == before
    c = _core(spec)
    frames = [_damaged(P.GetState(), 5, random.Random(i)) for i in range(50)]
    c.rx(b"".join(frames), 0)
    assert c.rx_bad_frames == 50 and c.tx() == b""


@settings(max_examples=300)
@given(st.lists(st.one_of(st.binary(max_size=600), st.sampled_from([m for m in GOLDEN if m.MSG < 0x80])),
                max_size=10),
       st.lists(st.integers(1, 80), max_size=20), st.integers(0, 2**32 - 1))
def test_parser_survives_any_bytes_in_any_chunks(spec, parts, cuts, now_us):
    c = _core(spec)
    stream = b"".join(p if isinstance(p, bytes) else P.encode(p, 7) for p in parts)
    pos = 0
    for k, cut in enumerate(cuts + [len(stream)]):
        c.rx(stream[pos:pos + cut], now_us)
        c.tick(now_us, [k % 3] * spec.n_hinges)
        pos += cut
    assert _answers_get_state(c, now_us)


def test_the_corpus_under_address_and_undefined_behaviour_sanitizers(tmp_path):
    flags = (*core.WARNINGS, "-g", "-O1", "-fsanitize=address,undefined", "-fno-sanitize-recover=all",
             "-fno-omit-frame-pointer")
    probe = tmp_path / "probe.c"
    probe.write_text("int main(void) { return 0; }\n")
    r = subprocess.run([core.compiler(), *flags, str(probe), "-o", str(tmp_path / "probe")], capture_output=True)
    if r.returncode != 0 or subprocess.run([str(tmp_path / "probe")]).returncode != 0:
        pytest.skip(f"{core.compiler()} cannot build or run -fsanitize=address,undefined here")
    driver = core.build(flags, [FUZZ_DRIVER], name="fuzz_driver", suffix="")
    files = []
    for i, (stream, _) in enumerate(corpus(1, 100) + corpus(2, 100)):
        files.append(tmp_path / f"case{i}.bin")
        files[-1].write_bytes(stream)
    rng = random.Random(3)
    for i in range(50):
        files.append(tmp_path / f"noise{i}.bin")
        files[-1].write_bytes(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 5000))))
    r = subprocess.run([str(driver), *map(str, files)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-4000:]


@pytest.mark.parametrize("size", [512, 513])
def test_a_payload_over_512_bytes_is_garbage_on_both_ends(spec, size):
    """docs/protocol.md: at most 512 bytes of payload (513 were once taken); one over is a bad frame, counted,
    not a message answered."""
    import struct

    body = bytes(size - 6)
    payload = struct.pack("<BBH", P.PROTOCOL_VERSION, int(P.MsgId.GET_STATE), 9) + body
    frame = P.cobs_encode(payload + struct.pack("<H", P.crc16(payload)))
    c = _core(spec)
    c.rx(b"\x00" + frame + b"\x00", 0)
    if size > P.MAX_FRAME:
        assert c.rx_bad_frames == 1 and c.tx() == b""
        with pytest.raises(P.ProtocolError, match="over the 512-byte maximum"):
            P.decode_frame(frame)
    else:  # the right size for a frame: understood as one, refused for its length
        assert c.rx_bad_frames == 0 and any(isinstance(m, P.NackMsg) for _, m in P.Decoder().feed(c.tx()))
