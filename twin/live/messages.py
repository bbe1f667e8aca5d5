"""The live service's wire format (docs/live.md): limits, message checks, datagram encoding.

Control channel: WebSocket text frames, one JSON object each, with a "type".
Datagrams: UDP, at most MAX_DATAGRAM_BYTES, binary: samples (SAMPLE), the pen's reply (PEN_REPLY), the
approximation's (APPROXIMATION_HEAD) and its estimates' (ESTIMATES).
Units at this edge: mm, degrees, seconds, quaternions w first; SI once parsed.
Anything wrong raises ProtocolError(code, message): the service answers it with an
"error" message and keeps the connection.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
import sys

import numba
import numpy as np

from twin.checks import REACH_M, parse_json
from twin.device.kinematics import matrix_quat, pose_matrix, quat_matrix

PROTOCOL_VERSION = 4  # 2: the frame estimates in their own datagram; 3: poses to the worker's own port; 4: samples
# and the pen's reply binary
DEFAULT_LISTEN_PORT = 8765  # TCP for the control channel, UDP for the pens (same number); poses: the welcome's
# pose_port
MAX_CONTROL_BYTES = 1 << 20  # a control message above this gets "oversized" (the connection stays)
MAX_FRAME_BYTES = 4 << 20  # the WebSocket layer closes (1009) above this, before the message is read
MAX_DATAGRAM_BYTES = 1200  # fits one Ethernet frame with room to spare
APPROXIMATION_RATE_HZ = 90.0  # VR frame rate: at most this many approximations per second
ESTIMATES_RATE_HZ = 30.0  # frame estimates per second at most, each for the newest approximation, sent when no pose
# waits: a readout of the fit's quality, not what bends the model (docs/live.md, "The pose's path")
PROGRESS_HZ = 30.0  # morph progress events per second
ERROR_INTERVAL = 0.1  # s: the same datagram error is reported at most this often (with a count)
POSITION_LIMIT_MM = REACH_M * 1e3  # a pose or pen farther from the target's origin is refused
QUAT_LIMIT = 1e3  # a quaternion's components, before it is normalised (no overflow in its norm)
ROLES = ("control", "observer")
CLIENT_TYPES = ("hello", "target", "lock", "status")


class ProtocolError(ValueError):
    """A message the service refuses; `code` is one of docs/live.md's error codes."""

    def __init__(self, code: str, message: str):
        self.code = code
        super().__init__(message)


def error(code: str, message: str, source: str = "control", count: int = 1) -> dict:
    """An "error" event; source: "control" (a control message) or "datagram"; count: how many since the last."""
    return {"type": "error", "code": code, "message": message, "source": source, "count": count}


# ---- control channel ------------------------------------------------------------------


def _typed_object(text, what: str, types) -> tuple[dict, str]:
    """(object, its type) from one JSON message; ProtocolError("malformed" | "unknown_type") if not one."""
    try:
        obj = parse_json(text, what)
    except ValueError as exc:
        raise ProtocolError("malformed", str(exc)) from None
    if not isinstance(obj, dict):
        raise ProtocolError("malformed", f"a {what} is a JSON object with a 'type'")
    kind = obj.get("type")
    if kind not in types:
        raise ProtocolError("unknown_type", f"{what} type {kind!r}; the service takes {', '.join(types)}")
    return obj, kind

def parse_control(message) -> dict:
    """A client's control message as a dict, checked against its type's schema; ProtocolError if not."""
    if isinstance(message, bytes):
        raise ProtocolError("malformed", "binary frame: the control channel takes JSON text")
    size = len(message.encode())
    if size > MAX_CONTROL_BYTES:
        raise ProtocolError("oversized", f"control message of {size} bytes, limit {MAX_CONTROL_BYTES}")
    obj, kind = _typed_object(message, "control message", CLIENT_TYPES)
    if kind == "hello":
        if obj.get("protocol") != PROTOCOL_VERSION:
            raise ProtocolError("malformed", f"hello: 'protocol' must be {PROTOCOL_VERSION}")
        if obj.get("role") not in ROLES:
            raise ProtocolError("malformed", f"hello: 'role' must be one of {', '.join(ROLES)}")
        if not isinstance(obj.get("token", ""), str):
            raise ProtocolError("malformed", "hello: 'token' must be a string")
    if kind == "target" and ("shape" in obj) == ("mesh" in obj):
        raise ProtocolError("malformed", "target: give exactly one of 'shape' (a name) or 'mesh'")
    if kind == "target" and "shape" in obj and not isinstance(obj["shape"], str):
        raise ProtocolError("malformed", "target: 'shape' must be a string")
    return obj


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) m, faces (F, 3) int) from a target message's 'mesh' {vertices_mm, faces}."""
    if not isinstance(mesh, dict):
        raise ProtocolError("malformed", "target: 'mesh' is an object {vertices_mm, faces}")
    try:
        vertices = np.asarray(mesh["vertices_mm"], float) / 1e3
        faces = np.asarray(mesh["faces"])
    except KeyError as exc:
        raise ProtocolError("malformed", f"target: mesh needs {exc.args[0]!r}") from None
    except (TypeError, ValueError):
        raise ProtocolError("malformed", "target: mesh.vertices_mm must be [x, y, z] numbers") from None
    if vertices.ndim != 2 or vertices.shape[1:] != (3,) or not np.all(np.isfinite(vertices)):
        raise ProtocolError("malformed", "target: mesh.vertices_mm must be a list of [x, y, z] finite numbers")
    if (faces.ndim != 2 or faces.shape[1:] != (3,) or faces.dtype.kind not in "iu"
            or faces.min(initial=0) < 0 or faces.max(initial=0) >= len(vertices)):
        raise ProtocolError("malformed", f"target: mesh.faces must be [i, j, k] vertex indices below {len(vertices)}")
    return vertices, faces.astype(np.int64)


# ---- datagrams -------------------------------------------------------------------------
# Every datagram is binary (protocol 4), little-endian, one fixed layout per kind (docs/live.md, "Datagrams"):
# samples are read into one preallocated buffer and checked by compiled code, replies written into preallocated
# buffers, with no JSON and no Python objects per field. Why: the pen's 0.5 ms budget held ~20 us of JSON parsing
# and ~17 us of JSON encoding per sample on a warm core, several times that on a loaded one; a pose's reply's JSON
# was ~0.1 ms of its CPU.

MAGIC = b"VS"
KINDS = {"pose": 1, "pen": 2, "pen_redirected": 3, "approximation": 4, "estimates": 5}  # a datagram's kind byte
HAS_T = 1  # flag: t_s given (else none, echoed as none)
HAS_DEVICE = 2  # sample flag (pens only): the device pose given
WITHIN = 2  # reply flag: the redirection is within both perception thresholds
SAMPLE = struct.Struct("<2sBBB3x16sQd3d4d3d4d")
"""A sample, 152 bytes: magic "VS", version (PROTOCOL_VERSION), kind (1 pose, 2 pen), flags (HAS_T | HAS_DEVICE),
3 zero bytes, session (the welcome's 32 hex digits as 16 bytes), seq (uint64 < 2^53), t_s (s), position_mm (3),
quat_wxyz (4), device_position_mm (3), device_quat_wxyz (4) (float64; zeros unless HAS_DEVICE)."""
PEN_REPLY = struct.Struct("<2sBBBB2xQd3d4d3d")
"""A pen's reply, 104 bytes: magic "VS", version, kind 3, flags (HAS_T | WITHIN), flap (uint8), 2 zero bytes, seq
(uint64), t_s, position_mm (3), quat_wxyz (4), offset_mm, rotation_deg, height_mm (float64)."""
APPROXIMATION_HEAD = struct.Struct("<2sBBBBBxQd")
"""An approximation's reply: magic "VS", version, kind 4, flags (HAS_T), n_hinges, n_flaps (uint8), a zero byte, seq
(uint64), t_s, then float64: root_position_mm (3), root_quat_wxyz (4), angles_deg (n_hinges), widths_mm (n_flaps),
time_ms."""
ESTIMATES = struct.Struct("<2sBBB3xQd2d")
"""Its frame estimates' reply, 40 bytes: magic "VS", version, kind 5, flags (HAS_T), 3 zero bytes, seq (uint64), t_s,
msd_estimate_mm, share_within_estimate (float64)."""
SESSION_BYTES = slice(8, 24)  # where the session lies in a sample
BUFFER_WORDS = (MAX_DATAGRAM_BYTES + 1 + 7) // 8  # a receive buffer (float64 words) one byte past the limit
VALUES = 18
"""A checked sample in SI (float64): seq, t_s (NaN: none), position m (3), quat (4, unit), device position m (3),
device quat (4, unit), kind (1, 2), has the device pose (0, 1)."""
DATAGRAM_PORTS = {"pose": "pose_port", "pen": "udp_port"}  # the welcome's port each kind of datagram goes to
_ERRORS = (  # the compiled check's codes: (error code, message); 0 is a valid sample
    (None, ""),
    ("oversized", f"datagram over the limit of {MAX_DATAGRAM_BYTES} bytes"),
    ("malformed", f"a JSON sample: protocol {PROTOCOL_VERSION}'s samples are binary (docs/live.md, Datagrams)"),
    ("malformed", f"a sample is {SAMPLE.size} bytes"),
    ("malformed", f"not a sample: one starts with {MAGIC.decode()!r}"),
    ("malformed", f"sample version: this service takes {PROTOCOL_VERSION}"),
    ("unknown_type", "sample kind: 1 (pose) or 2 (pen)"),
    ("unknown_type", f"pose datagrams go to the welcome's {DATAGRAM_PORTS['pose']}, pens to its "
                     f"{DATAGRAM_PORTS['pen']}"),
    ("malformed", "flags: 1 (t_s), 2 (device pose, pens only); the reserved bytes zero"),
    ("malformed", "'seq' must be an integer in [0, 2^53)"),
    ("malformed", "'t_s' must be a finite number"),
    ("malformed", f"'position_mm' must be 3 finite numbers within +-{POSITION_LIMIT_MM:g}"),
    ("malformed", f"'quat_wxyz' must be 4 finite numbers within +-{QUAT_LIMIT:g}"),
    ("malformed", "'quat_wxyz' is a zero quaternion"),
    ("malformed", f"'device_position_mm' must be 3 finite numbers within +-{POSITION_LIMIT_MM:g}"),
    ("malformed", f"'device_quat_wxyz' must be 4 finite numbers within +-{QUAT_LIMIT:g}"),
    ("malformed", "'device_quat_wxyz' is a zero quaternion"),
)
if sys.byteorder != "little":  # the buffers are read as native float64 (x86, ARM: little-endian)
    raise ImportError("the live service's datagrams are read on little-endian machines only")


@dataclasses.dataclass(frozen=True)
class Sample:
    """One pose or pen datagram, in SI."""

    kind: str  # "pose" (the tracked device) or "pen"
    session: str  # 32 hex digits
    seq: int
    position: np.ndarray  # (3,) m
    quat: np.ndarray  # (4,) w, x, y, z, unit
    device_pose: np.ndarray | None  # pen only, optional: the tracked device pose at the sample, 4x4
    t_s: float | None  # the client's clock, echoed in the reply


@numba.njit(cache=True)
def _vector(words, at, n, limit, unit, out, to):
    """words[at:at+n] finite and within +-limit, divided by unit into out[to:to+n]; their norm (-1: not valid)."""
    total = 0.0
    for k in range(n):
        v = words[at + k]
        if not (abs(v) <= limit):  # NaN fails too
            return -1.0
        out[to + k] = v / unit
        total += v * v
    return math.sqrt(total)


@numba.njit(cache=True)
def check_sample(raw, words, longs, n, port, out):
    """The sample in raw[:n] (uint8; words and longs: the same buffer as float64 and uint64), checked and written
    to out (VALUES, SI); port: the kind expected (0: either). 0, or the code of what is wrong (sample_error)."""
    if n > MAX_DATAGRAM_BYTES:
        return 1
    if n > 0 and raw[0] == 123:  # "{"
        return 2
    if n != 152:
        return 3
    if raw[0] != 86 or raw[1] != 83:  # "VS"
        return 4
    if raw[2] != PROTOCOL_VERSION:
        return 5
    kind, flags = raw[3], raw[4]
    if kind != 1 and kind != 2:
        return 6
    if port != 0 and kind != port:
        return 7
    if flags > 3 or ((flags & 2) != 0 and kind == 1) or raw[5] != 0 or raw[6] != 0 or raw[7] != 0:
        return 8
    seq = longs[3]
    if seq >= np.uint64(2 ** 53):
        return 9
    out[0] = seq
    out[1] = np.nan
    if flags & 1:
        if not math.isfinite(words[4]):
            return 10
        out[1] = words[4]
    wrong = _pose(words, 5, out, 2)
    if wrong:
        return 10 + wrong
    out[16], out[17] = kind, 0.0
    if flags & 2:
        wrong = _pose(words, 12, out, 9)
        if wrong:
            return 13 + wrong
        out[17] = 1.0
    return 0


@numba.njit(cache=True)
def _pose(words, at, out, to):
    """A position (mm) at words[at:at+3] and a quaternion at words[at+3:at+7] into out[to:to+3] (m) and
    out[to+3:to+7] (made unit): 0, or 1 (a position not finite or out of range), 2 (the same for the quaternion),
    3 (a quaternion of no length)."""
    if _vector(words, at, 3, POSITION_LIMIT_MM, 1e3, out, to) < 0:
        return 1
    norm = _vector(words, at + 3, 4, QUAT_LIMIT, 1.0, out, to + 3)
    if norm < 0:
        return 2
    if norm < 1e-6:
        return 3
    for k in range(to + 3, to + 7):
        out[k] /= norm
    return 0


def sample_error(code: int, n: int) -> ProtocolError:
    """The ProtocolError of check_sample's code for a datagram of n bytes."""
    name, message = _ERRORS[code]
    return ProtocolError(name, f"datagram of {n} bytes: {message}")


class SampleBuffer:
    """One datagram's bytes as received (`view`, for recvmsg_into) and the checked sample's values in SI
    (`values`): allocated once, reused for every datagram."""

    def __init__(self):
        self.words = np.zeros(BUFFER_WORDS)
        self.raw = self.words.view(np.uint8)
        self.longs = self.words.view(np.uint64)
        self.view = memoryview(self.raw)[:MAX_DATAGRAM_BYTES + 1]
        self.session = memoryview(self.raw)[SESSION_BYTES]
        self.values = np.zeros(VALUES)
        self.check(0)  # the compiled check loaded (or compiled, once per checkout) now, not on the first datagram

    def check(self, n: int, port: str | None = None) -> int:
        """0 when the n bytes received hold a valid sample of the kind that goes to `port` (None: either), its values
        then in `values`; else the code of what is wrong (`sample_error`)."""
        return check_sample(self.raw, self.words, self.longs, n, KINDS[port] if port else 0, self.values)

    def load(self, data: bytes) -> int:
        """Copy bytes in as if received (at most one byte past the limit); how many there were."""
        kept = min(len(data), len(self.view))
        self.view[:kept] = data[:kept]
        return len(data)

    def sample(self) -> Sample:
        """The checked sample as a Sample (allocated: for the tests and the rare paths)."""
        v = self.values
        kind = "pose" if v[16] == 1 else "pen"
        device = pose_matrix(v[9:12], quat_matrix(v[12:16])) if v[17] else None
        return Sample(kind, self.session.hex(), int(v[0]), v[2:5].copy(), v[5:9].copy(), device,
                      None if math.isnan(v[1]) else float(v[1]))


def parse_sample(data: bytes, port: str | None = None) -> Sample:
    """A pose or pen datagram; ProtocolError("oversized" | "malformed" | "unknown_type") if not one, or not of
    the kind that goes to `port` (a DATAGRAM_PORTS kind; None: either)."""
    buffer = SampleBuffer()
    code = buffer.check(buffer.load(data), port)
    if code:
        raise sample_error(code, len(data))
    return buffer.sample()


def encode_sample(kind: str, session: str, seq: int, position_mm, quat_wxyz, t_s: float | None = None,
                  device_position_mm=None, device_quat_wxyz=None) -> bytes:
    """A pose or pen datagram (a client's side); session: the welcome's 32 hex digits."""
    device = device_position_mm is not None
    flags = (HAS_T if t_s is not None else 0) | (HAS_DEVICE if device else 0)
    return SAMPLE.pack(MAGIC, PROTOCOL_VERSION, KINDS[kind], flags, bytes.fromhex(session), int(seq),
                       0.0 if t_s is None else float(t_s), *map(float, position_mm), *map(float, quat_wxyz),
                       *(map(float, device_position_mm) if device else (0.0,) * 3),
                       *(map(float, device_quat_wxyz) if device else (0.0,) * 4))


@numba.njit(cache=True)
def encode_pen_reply(values, position, quat, info, position_threshold, rotation_threshold, raw, words, longs):
    """The reply to the pen sample `values` (check_sample's) from its redirection (one row of `redirect`'s kernel:
    position (1, 3) m, quat (1, 4), info (1, 6): offset m, angle rad, height m, flap, s, y) into raw[:104] (words,
    longs: the same buffer as float64, uint64); whether it is within both thresholds."""
    within = info[0, 0] <= position_threshold and info[0, 1] <= rotation_threshold
    raw[0], raw[1], raw[2], raw[3] = 86, 83, PROTOCOL_VERSION, 3
    raw[4] = (0 if math.isnan(values[1]) else 1) | (2 if within else 0)
    raw[5], raw[6], raw[7] = int(info[0, 3]), 0, 0
    longs[1] = np.uint64(values[0])
    words[2] = 0.0 if math.isnan(values[1]) else values[1]
    for k in range(3):
        words[3 + k] = position[0, k] * 1e3
    for k in range(4):
        words[6 + k] = quat[0, k]
    words[10], words[11], words[12] = info[0, 0] * 1e3, math.degrees(info[0, 1]), info[0, 2] * 1e3
    return within


class ApproximationReply:
    """An approximation's reply datagram for a device of n_hinges and n_flaps, written into one buffer allocated
    once (`encode`)."""

    def __init__(self, n_hinges: int, n_flaps: int):
        self._words = np.zeros(APPROXIMATION_HEAD.size // 8 + 8 + n_hinges + n_flaps)
        self._raw, self._longs = self._words.view(np.uint8), self._words.view(np.uint64)
        APPROXIMATION_HEAD.pack_into(self._raw, 0, MAGIC, PROTOCOL_VERSION, KINDS["approximation"], 0, n_hinges,
                                     n_flaps, 0, 0.0)
        self._reply = memoryview(self._raw)

    def encode(self, seq: int, t_s: float | None, approximation) -> memoryview:
        """The reply to pose `seq` (its t_s) from an Approximation (SI); the buffer, valid until the next encode."""
        w, x, y, z = matrix_quat(approximation.root_pose[:3, :3])  # scipy's Rotation to the last bit
        _encode_approximation(self._raw, self._words, self._longs, seq, math.nan if t_s is None else t_s,
                              approximation.root_pose, w, x, y, z, approximation.angles, approximation.widths,
                              approximation.time)
        return self._reply


@numba.njit(cache=True)
def _encode_approximation(raw, words, longs, seq, t_s, root_pose, w, x, y, z, angles, widths, time_s):
    raw[4] = 0 if math.isnan(t_s) else 1
    longs[1] = seq
    words[2] = 0.0 if math.isnan(t_s) else t_s
    for k in range(3):
        words[3 + k] = root_pose[k, 3] * 1e3
    words[6], words[7], words[8], words[9] = w, x, y, z
    at = 10
    for k in range(angles.shape[0]):
        words[at + k] = math.degrees(angles[k])
    at += angles.shape[0]
    for k in range(widths.shape[0]):
        words[at + k] = widths[k] * 1e3
    words[at + widths.shape[0]] = time_s * 1e3


def estimates_datagram(seq: int, t_s: float | None, msd_estimate: float, share_estimate: float) -> bytes:
    """The frame estimates of the approximation of pose `seq` (m, 0..1), sent after it."""
    return ESTIMATES.pack(MAGIC, PROTOCOL_VERSION, KINDS["estimates"], 0 if t_s is None else HAS_T, seq,
                          0.0 if t_s is None else t_s, msd_estimate * 1e3, share_estimate)


def decode_reply(data: bytes) -> dict:
    """A reply datagram as a dict of the fields docs/live.md names (a client's side; a JSON one as it is: protocols
    1-3 sent JSON); ValueError if it is neither."""
    if data[:1] == b"{":
        return json.loads(data)
    if len(data) < 8 or data[:2] != MAGIC or data[2] != PROTOCOL_VERSION:
        raise ValueError(f"a reply of {len(data)} bytes that is neither JSON nor protocol {PROTOCOL_VERSION}'s")
    kind, flags = data[3], data[4]
    if kind == KINDS["pen_redirected"] and len(data) == PEN_REPLY.size:
        _, _, _, _, flap, seq, t_s, *v = PEN_REPLY.unpack(data)
        fields = {"position_mm": v[:3], "quat_wxyz": v[3:7], "offset_mm": v[7], "rotation_deg": v[8],
                  "height_mm": v[9], "flap": flap, "within_thresholds": bool(flags & WITHIN)}
    elif kind == KINDS["approximation"] and len(data) == APPROXIMATION_HEAD.size + 8 * (8 + data[5] + data[6]):
        *_, n_h, n_f, seq, t_s = APPROXIMATION_HEAD.unpack_from(data)
        v = struct.unpack_from(f"<{8 + n_h + n_f}d", data, APPROXIMATION_HEAD.size)
        fields = {"root_position_mm": list(v[:3]), "root_quat_wxyz": list(v[3:7]), "angles_deg": list(v[7:7 + n_h]),
                  "widths_mm": list(v[7 + n_h:-1]), "time_ms": v[-1]}
    elif kind == KINDS["estimates"] and len(data) == ESTIMATES.size:
        *_, seq, t_s, msd, share = ESTIMATES.unpack(data)
        fields = {"msd_estimate_mm": msd, "share_within_estimate": share}
    else:
        raise ValueError(f"a reply of {len(data)} bytes, kind {kind}: not one of protocol {PROTOCOL_VERSION}'s")
    return {"type": next(name for name, k in KINDS.items() if k == kind), "seq": seq,
            "t_s": t_s if flags & HAS_T else None, **fields}
