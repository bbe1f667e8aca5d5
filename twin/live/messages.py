"""The live service's wire format (docs/live.md): limits, message checks, datagram encoding.

Control channel: WebSocket text frames, one JSON object each, with a "type".
Datagrams: UDP, one JSON object each (UTF-8), at most MAX_DATAGRAM_BYTES.
Units at this edge: mm, degrees, seconds, quaternions w first; SI once parsed.
Anything wrong raises ProtocolError(code, message): the service answers it with an
"error" message and keeps the connection.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
from scipy.spatial.transform import Rotation

from twin.checks import REACH_M, parse_json
from twin.device.kinematics import pose_matrix

PROTOCOL_VERSION = 3  # 2: the frame estimates in their own datagram; 3: poses to the worker's own port
DEFAULT_LISTEN_PORT = 8765  # TCP for the control channel, UDP for the pens (same number); poses: the welcome's
# pose_port
MAX_CONTROL_BYTES = 1 << 20  # a control message above this gets "oversized" (the connection stays)
MAX_FRAME_BYTES = 4 << 20  # the WebSocket layer closes (1009) above this, before the message is read
MAX_DATAGRAM_BYTES = 1200  # fits one Ethernet frame with room to spare
APPROXIMATION_RATE_HZ = 90.0  # VR frame rate: at most this many approximations per second
PROGRESS_HZ = 30.0  # morph progress events per second
ERROR_INTERVAL = 0.1  # s: the same datagram error is reported at most this often (with a count)
POSITION_LIMIT_MM = REACH_M * 1e3  # a pose or pen farther from the target's origin is refused
QUAT_LIMIT = 1e3  # a quaternion's components, before it is normalised (no overflow in its norm)
ROLES = ("control", "observer")
CLIENT_TYPES = ("hello", "target", "lock", "status")
DATAGRAM_TYPES = ("pose", "pen")


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

@dataclasses.dataclass(frozen=True)
class Sample:
    """One pose or pen datagram, in SI."""

    kind: str  # "pose" (the tracked device) or "pen"
    session: str
    seq: int
    position: np.ndarray  # (3,) m
    quat: np.ndarray  # (4,) w, x, y, z, unit
    device_pose: np.ndarray | None  # pen only, optional: the tracked device pose at the sample, 4x4
    t_s: float | None  # the client's clock, echoed in the reply


def _vector(obj: dict, key: str, n: int, limit: float) -> np.ndarray:
    """n finite numbers, each within +-limit; ProtocolError("malformed") naming the key otherwise."""
    v = obj.get(key)
    if not (isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                      and math.isfinite(x) and abs(x) <= limit for x in v)):
        raise ProtocolError("malformed", f"{obj.get('type')}: {key!r} must be {n} finite numbers within +-{limit:g}")
    return np.array(v, float)


def _position(obj: dict, key: str) -> np.ndarray:
    """A position in mm, within the approximation's reach of the target's origin; m."""
    return _vector(obj, key, 3, POSITION_LIMIT_MM) / 1e3


def _quat(obj: dict, key: str) -> np.ndarray:
    q = _vector(obj, key, 4, QUAT_LIMIT)
    norm = np.linalg.norm(q)
    if norm < 1e-6:
        raise ProtocolError("malformed", f"{obj.get('type')}: {key!r} is a zero quaternion")
    return q / norm


DATAGRAM_PORTS = {"pose": "pose_port", "pen": "udp_port"}  # the welcome's port each kind of datagram goes to


def parse_datagram(data: bytes, port: str | None = None) -> Sample:
    """A pose or pen datagram; ProtocolError("oversized" | "malformed" | "unknown_type") if not one, or not of
    the kind that goes to `port` (a DATAGRAM_PORTS kind; None: either)."""
    if len(data) > MAX_DATAGRAM_BYTES:
        raise ProtocolError("oversized", f"datagram of {len(data)} bytes, limit {MAX_DATAGRAM_BYTES}")
    obj, kind = _typed_object(data, "datagram", DATAGRAM_TYPES)
    session, seq, t_s = obj.get("session"), obj.get("seq"), obj.get("t_s")
    if not isinstance(session, str):
        raise ProtocolError("malformed", f"{kind}: 'session' must be the string the welcome gave")
    if not isinstance(seq, int) or isinstance(seq, bool) or not 0 <= seq < 2 ** 53:
        raise ProtocolError("malformed", f"{kind}: 'seq' must be an integer in [0, 2^53)")
    if t_s is not None and not (isinstance(t_s, (int, float)) and math.isfinite(t_s)):
        raise ProtocolError("malformed", f"{kind}: 't_s' must be a finite number")
    position = _position(obj, "position_mm")
    quat = _quat(obj, "quat_wxyz")
    device = None
    if kind == "pen" and ("device_position_mm" in obj or "device_quat_wxyz" in obj):
        rotation = Rotation.from_quat(_quat(obj, "device_quat_wxyz"), scalar_first=True).as_matrix()
        device = pose_matrix(_position(obj, "device_position_mm"), rotation)
    if port is not None and kind != port:
        raise ProtocolError("unknown_type", f"{kind} datagrams go to the welcome's {DATAGRAM_PORTS[kind]}, {port}s "
                                            f"to its {DATAGRAM_PORTS[port]}")
    return Sample(kind, session, seq, position, quat, device, t_s)


def sample_datagram(kind: str, session: str, seq: int, position_mm, quat_wxyz, t_s: float | None = None,
                    device_position_mm=None, device_quat_wxyz=None) -> bytes:
    """Encode a pose or pen datagram (a client's side)."""
    obj = {"type": kind, "session": session, "seq": int(seq),
           "position_mm": [float(v) for v in position_mm], "quat_wxyz": [float(v) for v in quat_wxyz]}
    if t_s is not None:
        obj["t_s"] = float(t_s)
    if device_position_mm is not None:
        obj["device_position_mm"] = [float(v) for v in device_position_mm]
        obj["device_quat_wxyz"] = [float(v) for v in device_quat_wxyz]
    return json.dumps(obj, separators=(",", ":")).encode()


def approximation_datagram(seq: int, t_s: float | None, approximation: dict) -> bytes:
    """The reply to a pose: `twin.formats.target.approximation_json`."""
    obj = {"type": "approximation", "seq": seq, "t_s": t_s, **approximation}
    return json.dumps(obj, separators=(",", ":")).encode()


def estimates_datagram(seq: int, t_s: float | None, msd_estimate: float, share_estimate: float) -> bytes:
    """The frame estimates of the approximation of pose `seq` (m, 0..1), sent after it."""
    obj = {"type": "estimates", "seq": seq, "t_s": t_s, "msd_estimate_mm": round(msd_estimate * 1e3, 3),
           "share_within_estimate": round(share_estimate, 4)}
    return json.dumps(obj, separators=(",", ":")).encode()


def pen_datagram(seq: int, t_s: float | None, position, quat, offset: float, angle: float, height: float,
                 flap: int, within: bool) -> bytes:
    """The reply to a pen sample: the virtual pen (m, quaternion) and the redirection applied (m, rad)."""
    obj = {"type": "pen_redirected", "seq": seq, "t_s": t_s,
           "position_mm": [round(float(v) * 1e3, 4) for v in position],
           "quat_wxyz": [round(float(v), 6) for v in quat],
           "offset_mm": round(offset * 1e3, 4), "rotation_deg": round(math.degrees(angle), 4),
           "height_mm": round(height * 1e3, 4), "flap": int(flap), "within_thresholds": bool(within)}
    return json.dumps(obj, separators=(",", ":")).encode()
