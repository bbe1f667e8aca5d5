"""The approximation worker: a child process that holds the target, takes the poses and approximates.

An approximation takes 0.5-4 ms and a redirection field ~100 ms of compiled code that holds
Python's interpreter lock, so they run in their own process, and the service's event loop
stays free for the pen stream (~40 us per redirected sample).

Poses come to the worker straight from the client, on a datagram socket of its own (the welcome's
`pose_port`; the service binds it and hands it over with SCM_RIGHTS, so it outlives a worker that
dies): a pose wakes this one process on its way in and nothing is handed over per pose
(twin/live/poses.py decides which pose goes next). The answer goes straight back to the client from
the service's own datagram socket (handed over the same way), so the client sees every reply come
from the port it sends its pens to: the `approximation` datagram first, then its frame estimates'
`estimates` datagram (~0.3 ms later, off the pose's path). The service is woken by no pose: it asks
for the newest approximation when it locks, and for the counts and stage times when it reports
`status`.

The service talks to the worker over a pipe, in frames of bytes whose first byte says what follows;
requests are answered in order, one at a time:

    b"s" + the service's datagram socket, the replies' (its descriptor, passed alongside)  -> no reply
    b"q" + the pose socket (its descriptor, passed alongside)  -> no reply
    b"p" + pickle(("target", shape name or None, vertices (V, 3) m, faces (F, 3)))  -> b"p" + pickle(target info)
    b"p" + pickle(("session", the controller's secret or None))  -> b"p" + pickle(None)
    b"p" + pickle(("latest",))  -> b"p" + pickle((seq, approximation doubles) or None): the newest approximation
        sent to the present controller for the present target
    b"p" + pickle(("stats",))  -> b"p" + pickle({"counts", "pose_path_ms", "pose_cpu_ms", "estimates_ms"})
    b"p" + pickle(("field", root pose 4x4, angles rad, widths m))  -> b"p" + pickle((RedirectionField, summary))

Errors come back as b"e" + one line, and the worker carries on. Unasked, between replies, the
worker reports the pose stream's errors for the controlling client: b"r" + pickle((session, code,
message, count)), at most one per code every ERROR_INTERVAL. Python's garbage collection runs once
a request or a pose is answered and nothing else waits (twin/live/collection.py).
"""

from __future__ import annotations

import asyncio
import collections
import math
import multiprocessing
from multiprocessing import reduction
import pickle
import selectors
import socket
import sys
import time

import numpy as np
import trimesh

from twin.device.kinematics import pose_matrix, quat_matrix
from twin.device.spec import DeviceSpec
from twin.live.collection import collect_if_due, hold_collection
from twin.live.messages import ApproximationReply, estimates_datagram
from twin.live.poses import PoseIntake
from twin.live.stages import LATENCY_WINDOW, POSE_CPU_STAGES, POSE_STAGES, StageTimes, percentiles_ms
from twin.morphpatch.approximation import approximate
from twin.morphpatch.fields import build_fields
from twin.morphpatch.frame_metrics import frame_estimates
from twin.morphpatch.redirection import build_field, threshold_summary
from twin.morphpatch.sampling import SAMPLE_SPACING, grid_layout
from twin.morphpatch.shapes import check_mesh, load_shape
from twin.perception.thresholds import load_thresholds
from twin.records.approximation import Approximation


class WorkerError(RuntimeError):
    """The worker refused a request (bad mesh, no target) or has gone."""


def approximation_values(a: Approximation) -> tuple:
    """An approximation as doubles: root pose (16), angles rad (n_hinges), widths m (n_flaps), time s."""
    return (*a.root_pose.ravel().tolist(), *a.angles.tolist(), *a.widths.tolist(), a.time)


def decode_approximation(spec: DeviceSpec, variant: str, values: tuple) -> Approximation:
    """The Approximation from its doubles (`approximation_values`)."""
    v = np.asarray(values)
    n_h = spec.n_hinges
    return Approximation(v[:16].reshape(4, 4), v[16:16 + n_h], v[16 + n_h:-1], float(v[-1]), variant)


class _Poses:
    """The worker's side of the pose stream: which pose is next (PoseIntake), where the time went, the newest
    approximation sent."""

    def __init__(self, spec: DeviceSpec, variant: str):
        self.spec, self.variant = spec, variant
        self.intake = PoseIntake()
        self.times = StageTimes(POSE_STAGES, LATENCY_WINDOW)  # s per stage, kernel arrival -> approximation sent
        self.cpu = StageTimes(POSE_CPU_STAGES, LATENCY_WINDOW)  # CPU s per stage of the answer
        self.estimates = collections.deque(maxlen=LATENCY_WINDOW)  # s, estimates' datagram after the reply's
        self.thresholds = load_thresholds()
        self.layout = grid_layout(spec, SAMPLE_SPACING)
        self.reply = ApproximationReply(spec.n_hinges, spec.n_flaps)
        self.latest = None  # (seq, approximation doubles): the newest sent to this controller for this target

    def answer(self, pose: tuple, fields, udp: socket.socket) -> None:
        """Approximate a pose (its values as SampleBuffer's, addr, arrived, taken, parsed) and send its datagram to
        its sender, then its frame estimates' datagram."""
        values, addr, arrived, taken, parsed = pose
        started, cpu_started = time.perf_counter(), time.thread_time()
        seq, t_s = int(values[0]), None if math.isnan(values[1]) else float(values[1])
        pose_4x4 = pose_matrix(values[2:5], quat_matrix(values[5:9]))
        try:
            approx = approximate(fields, pose_4x4, self.spec, self.variant)
        except Exception as exc:  # the compiled code refused this pose: the client is told, the worker goes on
            self.intake.report("approximation_failed", f"{type(exc).__name__}: {exc}")
            return
        approximated, cpu_approximated = time.perf_counter(), time.thread_time()
        udp.sendto(self.reply.encode(seq, t_s, approx), addr)
        sent, cpu_sent = time.perf_counter(), time.thread_time()
        msd, share = frame_estimates(self.spec, fields, self.thresholds, approx.root_pose, approx.angles,
                                     approx.widths, self.layout)
        udp.sendto(estimates_datagram(seq, t_s, msd, share), addr)
        self.times.record((arrived, taken, parsed, started, approximated, sent))
        self.cpu.record((cpu_started, cpu_approximated, cpu_sent, time.thread_time()))
        self.estimates.append(time.perf_counter() - sent)
        self.intake.counts["approximations"] += 1
        self.latest = (seq, approximation_values(approx))

    def stats(self) -> dict:
        return {"counts": dict(self.intake.counts), "pose_path_ms": self.times.summary(),
                "pose_cpu_ms": self.cpu.summary(), "estimates_ms": percentiles_ms(self.estimates)}


def _request(request: bytes, conn, state: dict, poses: _Poses, selector) -> bytes | None:
    """One request from the service; the reply frame, or None for none."""
    if request[:1] == b"s":
        state["udp"] = socket.socket(fileno=reduction.recv_handle(conn))
        return None
    if request[:1] == b"q":
        state["poses"] = socket.socket(fileno=reduction.recv_handle(conn))
        state["poses"].setblocking(False)
        selector.register(state["poses"], selectors.EVENT_READ)
        return None
    kind, *args = pickle.loads(request[1:])
    if kind == "session":
        poses.intake.set_session(*args)
        poses.latest = None
        reply = None
    elif kind == "latest":
        reply = poses.latest
    elif kind == "stats":
        reply = poses.stats()
    elif kind == "target":
        t0 = time.perf_counter()
        name, vertices, faces = args
        mesh = load_shape(name) if name else check_mesh(trimesh.Trimesh(vertices, faces), "mesh")
        fields = build_fields(mesh)
        approximate(fields, np.eye(4), poses.spec, poses.variant)  # loads the compiled code now, not on a pose
        state["mesh"], state["fields"], poses.latest = mesh, fields, None
        reply = {"name": name or "mesh", "bounds_mm": (mesh.bounds * 1e3).round(3).tolist(),
                 "faces": len(mesh.faces), "build_s": round(time.perf_counter() - t0, 3)}
    elif state["fields"] is None:
        raise WorkerError("no target yet")
    else:  # "field"
        field = build_field(poses.spec, *args, state["mesh"], state["fields"])
        reply = (field, threshold_summary(field, poses.thresholds))
    return b"p" + pickle.dumps(reply)


def _serve(conn, spec: DeviceSpec, variant: str) -> None:
    """The child's loop: requests from the pipe, poses from their socket, until the pipe closes."""
    poses = _Poses(spec, variant)
    state = {"udp": None, "poses": None, "mesh": None, "fields": None}
    selector = selectors.DefaultSelector()
    selector.register(conn, selectors.EVENT_READ)
    hold_collection()
    while True:
        wait = poses.intake.wait_s(time.perf_counter())
        ready = selector.select(0)
        if not ready and wait != 0.0:  # nothing to do now: collect the garbage, then sleep until something comes
            collect_if_due()
            ready = selector.select(wait)
        # the pipe's requests first, all of them: a session named there comes before the poses it admits
        while any(key.fileobj is conn for key, _ in ready) and conn.poll():
            try:
                request = conn.recv_bytes()
            except (EOFError, OSError):
                return
            try:
                reply = _request(request, conn, state, poses, selector)
            except Exception as exc:  # a process boundary: report it to the service, stay alive for the next
                reply = b"e" + f"{type(exc).__name__}: {exc}".encode()
            if reply is not None:
                conn.send_bytes(reply)
        if state["poses"] is not None and any(key.fileobj is state["poses"] for key, _ in ready):
            poses.intake.drain(state["poses"])
        if state["fields"] is None:
            poses.intake.drop_pending("out_of_order", "pose before a target: send target first")
        elif state["udp"] is not None:
            pose = poses.intake.next(time.perf_counter())
            if pose is not None:
                poses.answer(pose, state["fields"], state["udp"])
        for report in poses.intake.reports:
            conn.send_bytes(b"r" + pickle.dumps(report))
        poses.intake.reports.clear()


class Worker:
    """The service's end of the worker process: `call` (awaited) and `tell` (no reply awaited) send requests;
    the worker's reports on the pose stream go to on_report(session, code, message, count). A worker that dies (a
    crash of compiled code on some input) is started again at once, with the sockets, the target and the session
    it had, after on_death()."""

    def __init__(self, spec: DeviceSpec, variant: str, on_report=lambda *report: None, on_death=lambda: None):
        self.spec = spec
        self.variant = variant
        self.on_report, self.on_death = on_report, on_death
        self._conn = self._proc = None
        self._waiting: collections.deque = collections.deque()  # per request sent: a Future, or a callable
        self._sockets: dict[bytes, socket.socket] = {}  # b"s" (replies), b"q" (poses): handed to every worker
        self._replay: dict[str, tuple] = {}  # "target", "session": the last it took, sent again after a restart
        self._restarting: asyncio.Task | None = None
        self.restarts = 0
        self._exitcode = None

    def start(self) -> None:
        context = multiprocessing.get_context("spawn")  # no copy of the service's threads and sockets
        self._conn, child = context.Pipe()
        self._proc = context.Process(target=_serve, args=(child, self.spec, self.variant), daemon=True,
                                     name="vrscroll-live-worker")
        self._proc.start()
        child.close()
        asyncio.get_running_loop().add_reader(self._conn.fileno(), self._readable)
        for kind in self._sockets:
            self._hand_socket(kind)

    def share_sockets(self, replies: socket.socket, poses: socket.socket) -> None:
        """The socket the worker sends its answers from (the service's datagram socket: the client sees them come
        from the port it sends its pens to) and the one it takes poses from, handed to this worker and every
        restarted one."""
        self._sockets = {b"s": replies, b"q": poses}
        if self._proc is not None:
            for kind in self._sockets:
                self._hand_socket(kind)

    def _hand_socket(self, kind: bytes) -> None:
        self._conn.send_bytes(kind)
        reduction.send_handle(self._conn, self._sockets[kind].fileno(), self._proc.pid)

    def _readable(self) -> None:
        try:
            frame = self._conn.recv_bytes()
        except (EOFError, OSError):
            asyncio.get_running_loop().remove_reader(self._conn.fileno())
            self._fail_waiting(WorkerError("the approximation worker died on this request; it is restarted"))
            self.on_death()
            self._restarting = asyncio.get_running_loop().create_task(self._restart())
            return
        kind = frame[:1]
        if kind == b"r":
            return self.on_report(*pickle.loads(frame[1:]))
        value = pickle.loads(frame[1:]) if kind == b"p" else WorkerError(frame[1:].decode(errors="replace"))
        waiter = self._waiting.popleft()
        if not isinstance(waiter, asyncio.Future):
            waiter(value)
        elif not waiter.cancelled():
            if isinstance(value, WorkerError):
                waiter.set_exception(value)
            else:
                waiter.set_result(value)

    def _fail_waiting(self, error: WorkerError) -> None:
        """Requests it will never answer: nobody waits on them for ever."""
        while self._waiting:
            waiter = self._waiting.popleft()
            if isinstance(waiter, asyncio.Future) and not waiter.done():
                waiter.set_exception(error)

    def _post(self, request: tuple, waiter) -> None:
        try:
            self._conn.send_bytes(b"p" + pickle.dumps(request))
        except OSError:  # it died; the pipe's end is read next, and it is restarted then
            raise WorkerError("the approximation worker has gone; it is being restarted") from None
        self._waiting.append(waiter)

    def tell(self, *request) -> None:
        """Send a request whose reply nobody awaits ("session": sent before this returns, so before anything the
        caller sends next); a restarted worker gets it too."""
        self._replay[request[0]] = request
        if self._proc is not None:
            try:
                self._post(request, lambda value: None)
            except WorkerError:
                pass  # it died: the restart replays it

    async def call(self, *request):
        """Send one request ("target", "latest", "stats", "field") and await its reply; WorkerError if refused, or
        if the worker was never started, has been stopped, or died on it."""
        if self._proc is None:
            raise WorkerError("the approximation worker is not running")
        if self._restarting is not None:
            await asyncio.shield(self._restarting)
        value = await self._send(request)
        if request[0] == "target":
            self._replay["target"] = request
        return value

    async def _send(self, request: tuple):
        future = asyncio.get_running_loop().create_future()
        self._post(request, future)
        return await future

    async def _restart(self) -> None:
        try:
            self._close()
            self.restarts += 1
            print(f"vrscroll serve: the approximation worker died (exit {self._exitcode}); restart {self.restarts}",
                  file=sys.stderr, flush=True)
            self.start()
            for kind in list(self._replay):  # each as it is when sent: a newer one told meanwhile is not undone
                await self._send(self._replay[kind])
        except WorkerError as exc:
            print(f"vrscroll serve: the restarted approximation worker refused its state: {exc}", file=sys.stderr,
                  flush=True)
        finally:
            self._restarting = None

    def approximation(self, values: tuple) -> Approximation:
        return decode_approximation(self.spec, self.variant, values)

    def stop(self) -> None:
        if self._restarting is not None:
            self._restarting.cancel()
            self._restarting = None
        self._close()

    def _close(self) -> None:
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
        self._fail_waiting(WorkerError("the approximation worker was stopped"))
