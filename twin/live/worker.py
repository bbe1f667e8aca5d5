"""The approximation worker: a child process that holds the target and approximates.

An approximation takes 0.5-4 ms and a redirection field ~100 ms of compiled code that holds
Python's interpreter lock, so they run in their own process, and the service's event loop
stays free for the pen stream (~40 us per redirected sample). The two talk over a pipe, in
frames of bytes whose first byte says what follows; requests are answered in order, one at
a time:

    b"s" + the service's datagram socket (its descriptor, passed alongside)  -> no reply
    b"a" + POSE_REQUEST (seq, t_s or NaN, position m, unit quaternion w first, port) + the client's host
        -> the "approximation" datagram (docs/live.md), built here and sent to the client from the
           service's socket (so from the service's port), then its frame estimates and their
           "estimates" datagram, then
           b"a" + stamps (4 doubles: received, approximated, approximation sent, estimates sent;
                  perf_counter s)
                + the approximation (root pose 16, angles, widths, time s: doubles)
    b"p" + pickle(("target", shape name or None, vertices (V, 3) m, faces (F, 3)))  -> b"p" + pickle(target info)
    b"p" + pickle(("field", root pose 4x4, angles rad, widths m))  -> b"p" + pickle((RedirectionField, summary))

Errors come back as b"e" + one line, and the worker carries on. A pose, at 90 Hz, goes as
fixed-size packed doubles and its answer goes straight to the client, so nothing is pickled per
pose and the service's process is not on the way back (one process wake-up fewer per pose);
the rare requests keep pickling. Nothing but the approximation stands between a pose and its
answer: the frame estimates (~0.3 ms) follow in their own datagram, the report to the service
after them, and Python's garbage collection runs once the request is answered
(twin/live/collection.py).
"""

from __future__ import annotations

import asyncio
import collections
import math
import multiprocessing
from multiprocessing import reduction
import pickle
import socket
import struct
import sys
import time

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from twin.device.kinematics import pose_matrix
from twin.device.spec import DeviceSpec
from twin.formats.target import approximation_json
from twin.live.collection import collect_if_due, hold_collection
from twin.live.messages import approximation_datagram, estimates_datagram
from twin.morphpatch.approximation import approximate
from twin.morphpatch.fields import build_fields
from twin.morphpatch.frame_metrics import frame_estimates
from twin.morphpatch.redirection import build_field, threshold_summary
from twin.morphpatch.sampling import SAMPLE_SPACING, grid_layout
from twin.morphpatch.shapes import check_mesh, load_shape
from twin.perception.thresholds import load_thresholds
from twin.records.approximation import Approximation

POSE_REQUEST = struct.Struct("<qd3d4dH")  # seq, t_s (NaN: none), position m, unit quaternion w first, UDP port
STAMPS = struct.Struct("<4d")  # the worker's perf_counter s: received, approximated, approximation sent, estimates sent


class WorkerError(RuntimeError):
    """The worker refused a request (bad mesh, no target) or has gone."""


def _result_struct(spec: DeviceSpec) -> struct.Struct:
    """An approximation as doubles: root pose (16), angles rad (n_hinges), widths m (n_flaps), time s."""
    return struct.Struct(f"<{16 + spec.n_hinges + spec.n_flaps + 1}d")


def pose_request(seq: int, t_s: float | None, position: np.ndarray, quat: np.ndarray, addr) -> bytes:
    """The frame that asks the worker to approximate a pose (position m, unit quaternion w first) for the pose
    datagram `seq` (its t_s echoed) and send the answer to addr (host, port, ...)."""
    return (b"a" + POSE_REQUEST.pack(seq, math.nan if t_s is None else t_s, *position.tolist(), *quat.tolist(),
                                     addr[1]) + addr[0].encode())


def decode_approximation(spec: DeviceSpec, variant: str, values: tuple) -> Approximation:
    """The Approximation from the doubles of a pose reply (`PoseReply.values`)."""
    v = np.asarray(values)
    n_h = spec.n_hinges
    return Approximation(v[:16].reshape(4, 4), v[16:16 + n_h], v[16 + n_h:-1], float(v[-1]), variant)


class PoseReply:
    """A pose reply as it came off the pipe: `stamps` (the worker's, s), `values` (doubles)."""

    __slots__ = ("stamps", "values")

    def __init__(self, frame: bytes, result: struct.Struct):
        self.stamps = STAMPS.unpack_from(frame, 1)
        self.values = result.unpack_from(frame, 1 + STAMPS.size)


def _approximate(request: bytes, received: float, spec, variant, fields, thresholds, layout, result, udp) -> bytes:
    """Approximate the requested pose and send its datagram to the client, then its frame estimates' datagram;
    the report frame for the service."""
    seq, t_s, *values, port = POSE_REQUEST.unpack_from(request, 1)
    client = (request[1 + POSE_REQUEST.size:].decode(), port)
    t_s = None if math.isnan(t_s) else t_s
    pose = pose_matrix(np.array(values[:3]), Rotation.from_quat(values[3:7], scalar_first=True).as_matrix())
    approx = approximate(fields, pose, spec, variant)
    approximated = time.perf_counter()
    udp.sendto(approximation_datagram(seq, t_s, approximation_json(approx)), client)
    sent = time.perf_counter()
    msd, share = frame_estimates(spec, fields, thresholds, approx.root_pose, approx.angles, approx.widths, layout)
    udp.sendto(estimates_datagram(seq, t_s, msd, share), client)
    estimated = time.perf_counter()
    values = result.pack(*approx.root_pose.ravel().tolist(), *approx.angles.tolist(), *approx.widths.tolist(),
                         approx.time)
    return b"a" + STAMPS.pack(received, approximated, sent, estimated) + values


def _serve(conn, spec: DeviceSpec, variant: str) -> None:
    """The child's loop: one request in, one reply out, until the pipe closes."""
    thresholds = load_thresholds()
    layout = grid_layout(spec, SAMPLE_SPACING)
    result = _result_struct(spec)
    mesh = fields = udp = None
    hold_collection()
    while True:
        if not conn.poll():  # the last request answered, the next not here yet
            collect_if_due()
        try:
            request = conn.recv_bytes()
        except (EOFError, OSError):
            return
        received = time.perf_counter()
        try:
            if request[:1] == b"s":
                udp = socket.socket(fileno=reduction.recv_handle(conn))
                continue
            if request[:1] == b"a":
                if fields is None or udp is None:
                    raise WorkerError("no target yet" if fields is None else "no datagram socket yet")
                conn.send_bytes(_approximate(request, received, spec, variant, fields, thresholds, layout, result,
                                             udp))
                continue
            kind, *args = pickle.loads(request[1:])
            if kind == "target":
                t0 = time.perf_counter()
                name, vertices, faces = args
                mesh = load_shape(name) if name else check_mesh(trimesh.Trimesh(vertices, faces), "mesh")
                fields = build_fields(mesh)
                approximate(fields, np.eye(4), spec, variant)  # loads the compiled code now, not on the first pose
                reply = {"name": name or "mesh", "bounds_mm": (mesh.bounds * 1e3).round(3).tolist(),
                         "faces": len(mesh.faces), "build_s": round(time.perf_counter() - t0, 3)}
            elif fields is None:
                raise WorkerError("no target yet")
            else:  # "field"
                field = build_field(spec, *args, mesh, fields)
                reply = (field, threshold_summary(field, thresholds))
            conn.send_bytes(b"p" + pickle.dumps(reply))
        except Exception as exc:  # a process boundary: report it to the service, stay alive for the next request
            conn.send_bytes(b"e" + f"{type(exc).__name__}: {exc}".encode())


class Worker:
    """The service's end of the worker process: `call` (awaited) for targets and fields, `approximate`
    (a callback, no await: called from the pipe's reader on the event loop) for poses."""

    def __init__(self, spec: DeviceSpec, variant: str):
        self.spec = spec
        self.variant = variant
        self._result = _result_struct(spec)
        self._conn = self._proc = None
        self._waiting: collections.deque = collections.deque()  # per request sent: a Future, or a pose's callback
        self._target = None  # the last target request it took, sent again to a restarted worker
        self._udp = None  # the service's datagram socket, handed to every worker started
        self.restarts = 0
        self._exitcode = None

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def start(self) -> None:
        context = multiprocessing.get_context("spawn")  # no copy of the service's threads and sockets
        self._conn, child = context.Pipe()
        self._proc = context.Process(target=_serve, args=(child, self.spec, self.variant), daemon=True,
                                     name="vrscroll-live-worker")
        self._proc.start()
        child.close()
        asyncio.get_running_loop().add_reader(self._conn.fileno(), self._readable)
        if self._udp is not None:
            self._hand_socket()

    def share_socket(self, udp: socket.socket) -> None:
        """The socket the worker sends pose answers from (the service's datagram socket: the client sees them
        come from the port it sends to), handed to this worker and every restarted one."""
        self._udp = udp
        if self._proc is not None:
            self._hand_socket()

    def _hand_socket(self) -> None:
        self._conn.send_bytes(b"s")
        reduction.send_handle(self._conn, self._udp.fileno(), self._proc.pid)

    def _readable(self) -> None:
        received = time.perf_counter()
        try:
            frame = self._conn.recv_bytes()
        except (EOFError, OSError):
            asyncio.get_running_loop().remove_reader(self._conn.fileno())
            died = WorkerError("the approximation worker died on this request; it is restarted for the next")
            while self._waiting:
                self._answer(self._waiting.popleft(), died, received)
            return
        kind = frame[:1]
        if kind == b"a":
            value = PoseReply(frame, self._result)
        elif kind == b"p":
            value = pickle.loads(frame[1:])
        else:
            value = WorkerError(frame[1:].decode(errors="replace"))
        self._answer(self._waiting.popleft(), value, received)

    @staticmethod
    def _answer(waiter, value, received: float) -> None:
        if isinstance(waiter, asyncio.Future):
            if waiter.cancelled():
                return
            if isinstance(value, WorkerError):
                waiter.set_exception(value)
            else:
                waiter.set_result(value)
        else:
            waiter(value, received)

    def approximate(self, seq: int, t_s: float | None, position: np.ndarray, quat: np.ndarray, addr, done) -> None:
        """Ask for a pose's approximation (position m, unit quaternion w first), its datagram sent by the worker
        to addr; done(PoseReply or WorkerError, perf_counter s at its arrival) is called from the event loop
        when the worker reports back. The worker must be alive (see `ensure_running`)."""
        self._waiting.append(done)
        self._conn.send_bytes(pose_request(seq, t_s, position, quat, addr))

    def approximation(self, reply: PoseReply) -> Approximation:
        return decode_approximation(self.spec, self.variant, reply.values)

    async def ensure_running(self) -> None:
        """A worker that died (a crash of compiled code on some input) is started again, with the last target
        it took. WorkerError if the worker was never started or has been stopped."""
        if self._proc is None:
            raise WorkerError("the approximation worker is not running")
        if not self._proc.is_alive():
            await self._restart()

    async def call(self, *request):
        """Send one pickled request ("target" or "field") and await its reply; WorkerError if refused."""
        await self.ensure_running()
        value = await self._send(request)
        if request[0] == "target":
            self._target = request
        return value

    async def _send(self, request):
        future = asyncio.get_running_loop().create_future()
        self._waiting.append(future)
        self._conn.send_bytes(b"p" + pickle.dumps(request))
        return await future

    async def _restart(self) -> None:
        self.stop()
        self.restarts += 1
        print(f"vrscroll serve: the approximation worker died (exit {self._exitcode}); restart {self.restarts}",
              file=sys.stderr, flush=True)
        self.start()
        if self._target is not None:
            await self._send(self._target)

    def stop(self) -> None:
        if self._proc is None:
            return
        try:
            asyncio.get_running_loop().remove_reader(self._conn.fileno())
        except (RuntimeError, ValueError, OSError):  # no loop running any more, or the pipe already closed
            pass
        self._conn.close()
        self._proc.join(timeout=5)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout=5)
        self._exitcode = self._proc.exitcode
        self._proc = None
        stopped = WorkerError("the approximation worker was stopped")
        while self._waiting:  # requests it never answered: nobody waits on them for ever
            self._answer(self._waiting.popleft(), stopped, time.perf_counter())
