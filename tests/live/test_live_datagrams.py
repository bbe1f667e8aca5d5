"""The binary datagrams of protocol 4 (twin/live/messages.py) and the service's pen redirection on preallocated state
(twin/live/pens.py): the sample reader fed what a careless or hostile client might send, checked against a reading of
docs/live.md's layout written here with `struct`; the pen's reply against `redirect` itself."""

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.formats.target import approximation_json
from twin.live.messages import (MAX_DATAGRAM_BYTES, ApproximationReply, ProtocolError, SampleBuffer, decode_reply,
                                encode_sample, estimates_datagram, parse_sample)
from twin.live.pens import PenRedirection
from twin.morphpatch.approximation import approximate, pose_from_mm_deg
from twin.morphpatch.fields import build_fields
from twin.morphpatch.redirection import build_field, redirect, within_samples
from twin.morphpatch.shapes import load_shape
from twin.perception.thresholds import load_thresholds

LAYOUT = struct.Struct("<2sBBB3s16sQd3d4d3d4d")  # docs/live.md's sample, read independently of the service's code
SESSION = "0f" * 16


def expected_error(data: bytes) -> str | None:
    """The error code docs/live.md gives for these bytes as a sample (None: a valid one)."""
    if len(data) > MAX_DATAGRAM_BYTES:
        return "oversized"
    if len(data) != LAYOUT.size:
        return "malformed"
    magic, version, kind, flags, reserved, _, seq, t_s, *v = LAYOUT.unpack(data)
    if magic != b"VS" or version != 4:
        return "malformed"
    if kind not in (1, 2):
        return "unknown_type"
    if flags > 3 or (flags & 2 and kind == 1) or reserved != bytes(3) or seq >= 2 ** 53 or \
            (flags & 1 and not math.isfinite(t_s)):
        return "malformed"
    vectors = [(v[0:3], 1e5), (v[3:7], 1e3)] + ([(v[7:10], 1e5), (v[10:14], 1e3)] if flags & 2 else [])
    for values, limit in vectors:
        if not all(abs(x) <= limit for x in values):  # NaN fails too
            return "malformed"
        if len(values) == 4 and math.sqrt(sum(x * x for x in values)) < 1e-6:
            return "malformed"
    return None


floats = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                   st.sampled_from([0.0, 1e3, -1e3, 1e5, -1e5, 1e5 * (1 + 1e-15), 1e-7, 1e308, 5e-324]))
samples = st.builds(
    lambda magic, version, kind, flags, reserved, seq, values, cut: LAYOUT.pack(
        magic, version, kind, flags, reserved, bytes.fromhex(SESSION), seq, *values)[:cut],
    st.sampled_from([b"VS", b"VS", b"SV"]), st.sampled_from([4, 4, 4, 3, 255]), st.sampled_from([1, 2, 2, 0, 3, 200]),
    st.one_of(st.integers(0, 3), st.integers(0, 255)), st.sampled_from([bytes(3), bytes(3), b"\x00\x01\x00"]),
    st.one_of(st.integers(0, 2 ** 53 + 1), st.integers(0, 2 ** 64 - 1)), st.lists(floats, min_size=15, max_size=15),
    st.one_of(st.just(None), st.integers(0, 160)))


@settings(max_examples=400, deadline=None)
@given(data=st.one_of(samples, st.binary(max_size=MAX_DATAGRAM_BYTES + 50)))
def test_the_sample_reader_refuses_what_the_layout_refuses_and_reads_the_rest(data):
    code = expected_error(data)
    try:
        sample = parse_sample(data)
    except ProtocolError as exc:
        assert exc.code == code, (exc.code, code, str(exc))
        return
    assert code is None
    _, _, kind, flags, _, session, seq, t_s, *v = LAYOUT.unpack(data)
    assert (sample.kind, sample.session, sample.seq) == ({1: "pose", 2: "pen"}[kind], SESSION, seq)
    assert sample.t_s == (t_s if flags & 1 else None)
    assert np.array_equal(sample.position, np.array(v[0:3]) / 1e3)
    assert np.allclose(sample.quat, np.array(v[3:7]) / np.linalg.norm(v[3:7]), rtol=1e-12, atol=1e-15)
    assert (sample.device_pose is None) == (not flags & 2)


def test_a_reused_buffer_reads_each_datagram_alone():
    """A short datagram after a long one: the long one's bytes still lie in the buffer, and count for nothing."""
    buffer = SampleBuffer()
    long = encode_sample("pen", SESSION, 3, [1, 2, 3], [1, 0, 0, 0], t_s=1.0)
    assert buffer.check(buffer.load(long + b"x"), "pen") != 0
    assert buffer.check(buffer.load(long[:-1]), "pen") != 0
    assert buffer.check(buffer.load(long), "pose") != 0  # a pen where poses go
    assert buffer.check(buffer.load(long), "pen") == 0 and buffer.sample().seq == 3


@settings(max_examples=300, deadline=None)
@given(data=st.one_of(st.binary(max_size=300), st.builds(
    lambda kind, flags, n, rest: b"VS\x04" + bytes([kind, flags, n, n]) + rest,
    st.integers(0, 6), st.integers(0, 255), st.integers(0, 12), st.binary(min_size=0, max_size=300))))
def test_a_client_reads_any_reply_or_refuses_it(data):
    try:
        reply = decode_reply(data)
    except ValueError:  # json.JSONDecodeError is one
        return
    assert isinstance(reply, (dict, list, str, int, float, bool, type(None)))  # JSON, or one of the replies
    if data[:1] != b"{":
        assert reply["type"] in ("pen_redirected", "approximation", "estimates") and reply["seq"] >= 0


def test_the_approximations_reply_carries_what_its_json_did(field, spec):
    """Each number of `approximation_json` (the `locked` event's), from the reply's doubles before its rounding."""
    fields = build_fields(load_shape("cylinder"))
    reply = ApproximationReply(spec.n_hinges, spec.n_flaps)
    for k, start in enumerate(([14, -9, 185, 4, -6, 23], [-30, 20, 170, -10, 5, 140])):
        a = approximate(fields, pose_from_mm_deg(start), spec)
        got = decode_reply(bytes(reply.encode(7 + k, None if k else 2.5, a)))
        want = approximation_json(a)
        assert (got["type"], got["seq"], got["t_s"]) == ("approximation", 7 + k, None if k else 2.5)
        for key, digits in (("root_position_mm", 3), ("root_quat_wxyz", 6), ("angles_deg", 3), ("widths_mm", 3)):
            assert [round(v, digits) for v in got[key]] == want[key], key
        assert round(got["time_ms"], 4) == want["time_ms"]
    estimates = decode_reply(estimates_datagram(9, 1.25, 0.0021, 0.75))
    assert estimates == {"type": "estimates", "seq": 9, "t_s": 1.25, "msd_estimate_mm": 2.1,
                         "share_within_estimate": 0.75}


@pytest.fixture(scope="module")
def field(spec):
    """The redirection field of the device approximating the cylinder from a start nobody tuned for."""
    mesh = load_shape("cylinder")
    fields = build_fields(mesh)
    a = approximate(fields, pose_from_mm_deg([14, -9, 185, 4, -6, 23]), spec)
    return build_field(spec, a.root_pose, a.angles, a.widths, mesh, fields)


def test_the_services_pen_reply_is_what_redirect_gives(field):
    thresholds = load_thresholds()
    pens = PenRedirection(thresholds)
    pens.set_field(field)
    rng = np.random.default_rng(40)
    anchor = field.root_pose[:3, 3] * 1e3
    for k in range(200):
        position = anchor + rng.normal(0, 60 if k % 2 else 10, 3)  # on the device and well off it
        quat = rng.normal(size=4) * rng.uniform(0.1, 10)  # unnormalised on the wire
        device = (anchor + rng.normal(0, 20, 3), rng.normal(size=4)) if k % 3 == 0 else (None, None)
        t_s = None if k % 5 == 0 else rng.uniform(0, 1e4)
        data = encode_sample("pen", SESSION, k, position, quat, t_s, *device)
        assert pens.buffer.check(pens.buffer.load(data), "pen") == 0
        within = pens.redirect()
        reply = decode_reply(bytes(pens.reply))
        sample = parse_sample(data)  # the same values in SI (the reader's own test is the fuzz test above)
        r = redirect(field, sample.position[None], sample.quat[None],
                     None if sample.device_pose is None else sample.device_pose[None])
        assert (reply["type"], reply["seq"], reply["t_s"], reply["flap"]) == ("pen_redirected", k, t_s, r.flap[0])
        assert reply["within_thresholds"] == within == bool(within_samples(r, thresholds)[0])
        assert reply["position_mm"] == (r.position[0] * 1e3).tolist() and reply["quat_wxyz"] == r.orientation[0].tolist()
        assert [reply["offset_mm"], reply["rotation_deg"], reply["height_mm"]] == \
            [r.offset[0] * 1e3, math.degrees(r.angle[0]), r.height[0] * 1e3]
