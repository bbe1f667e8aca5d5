"""The approximation worker: a child process that holds the target, takes the poses and approximates.

An approximation takes 0.5-4 ms and a redirection field ~100 ms of compiled code that holds
Python's interpreter lock, so they run in their own process, and the service's event loop
stays free for the pen stream (~40 us per redirected sample).

Poses come to the worker straight from the client, on a datagram socket of its own (the welcome's
`pose_port`; the service binds it and hands it over with SCM_RIGHTS, so it outlives a worker that
dies): a pose wakes this one process on its way in and nothing is handed over per pose
(twin/live/poses.py decides which pose goes next). The answer goes straight back to the client from
the service's own datagram socket (handed over the same way), so the client sees every reply come
from the port it sends its pens to: the `approximation` datagram; then, when no pose waits and at most
ESTIMATES_RATE_HZ times a second, the newest approximation's frame estimates in an `estimates` datagram (off the
pose's path: a readout of the fit's quality needs no estimate of every approximation, and each took ~0.5 ms of
the worker's CPU, a third of a pose's). The service is woken by no pose: it asks
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
    b"p" + pickle(("stats",))  -> b"p" + pickle({"counts", "pose_path_ms", "pose_cpu_ms", "estimates_ms",
        "estimates_cpu_ms"})
    b"p" + pickle(("field", root pose 4x4, angles rad, widths m))  -> b"p" + pickle((RedirectionField, summary))

Errors come back as b"e" + one line, and the worker carries on. Unasked, between replies, the
worker reports the pose stream's errors for the controlling client: b"r" + pickle((session, code,
message, count)), at most one per code every ERROR_INTERVAL. Python's garbage collection runs once
a request or a pose is answered and nothing else waits (twin/live/collection.py).
"""

from __future__ import annotations

import collections
import math
import pickle
import selectors
import socket
import time

import numpy as np
import trimesh

from twin.device.kinematics import pose_matrix, quat_matrix
from twin.device.spec import DeviceSpec
from twin.live.child import ChildProcess, WorkerError, name_process, take_socket
from twin.live.collection import collect_if_due, hold_collection
from twin.live.messages import ESTIMATES_RATE_HZ, ApproximationReply, estimates_datagram
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
    approximation sent, and the one whose frame estimates are still to go."""

    def __init__(self, spec: DeviceSpec, variant: str):
        self.spec, self.variant = spec, variant
        self.intake = PoseIntake()
        self.times = StageTimes(POSE_STAGES, LATENCY_WINDOW)  # s per stage, kernel arrival -> approximation sent
        self.cpu = StageTimes(POSE_CPU_STAGES, LATENCY_WINDOW)  # CPU s per stage of the answer
        self.estimates = collections.deque(maxlen=LATENCY_WINDOW)  # s, estimates' datagram after the reply's
        self.estimates_cpu = collections.deque(maxlen=LATENCY_WINDOW)  # CPU s of each estimates' datagram
        self.thresholds = load_thresholds()
        self.layout = grid_layout(spec, SAMPLE_SPACING)
        self.reply = ApproximationReply(spec.n_hinges, spec.n_flaps)
        self.latest = None  # (seq, Approximation): the newest sent to this controller for this target
        self.unestimated = None  # (seq, t_s, addr, Approximation, sent s) of it, while its estimates are to go
        self.estimated = -math.inf  # perf_counter s of the last estimates' datagram

    def forget(self) -> None:
        """A new target or controller: nothing sent before it is locked or estimated."""
        self.latest = self.unestimated = None

    def answer(self, pose: tuple, fields, udp: socket.socket) -> None:
        """Approximate a pose (its values as SampleBuffer's, addr, arrived, taken, parsed) and send its datagram to
        its sender; its frame estimates go later (`send_estimates`)."""
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
        reply = self.reply.encode(seq, t_s, approx)
        encoded = time.perf_counter()
        udp.sendto(reply, addr)
        sent = time.perf_counter()
        self.times.record((arrived, taken, parsed, started, approximated, encoded, sent))
        self.cpu.record((cpu_started, cpu_approximated, time.thread_time()))
        self.intake.counts["approximations"] += 1
        self.latest = (seq, approx)
        self.unestimated = (seq, t_s, addr, approx, sent)

    def estimates_due_s(self, now: float) -> float | None:
        """s until the frame estimates of the newest approximation may go (0: now); None when they have gone."""
        if self.unestimated is None:
            return None
        return max(0.0, self.estimated + 1.0 / ESTIMATES_RATE_HZ - now)

    def send_estimates(self, fields, udp: socket.socket) -> None:
        """The frame estimates of the newest approximation, in a datagram to its pose's sender."""
        seq, t_s, addr, approx, sent = self.unestimated
        self.unestimated = None
        cpu_started = time.thread_time()
        msd, share = frame_estimates(self.spec, fields, self.thresholds, approx.root_pose, approx.angles,
                                     approx.widths, self.layout)
        udp.sendto(estimates_datagram(seq, t_s, msd, share), addr)
        self.estimated = time.perf_counter()
        self.estimates.append(self.estimated - sent)
        self.estimates_cpu.append(time.thread_time() - cpu_started)
        self.intake.counts["estimates"] += 1

    def stats(self) -> dict:
        return {"counts": dict(self.intake.counts), "pose_path_ms": self.times.summary(),
                "pose_cpu_ms": self.cpu.summary(), "estimates_ms": percentiles_ms(self.estimates),
                "estimates_cpu_ms": percentiles_ms(self.estimates_cpu)}


def _request(request: bytes, conn, state: dict, poses: _Poses, selector) -> bytes | None:
    """One request from the service; the reply frame, or None for none."""
    if request[:1] == b"s":
        state["udp"] = take_socket(conn)
        return None
    if request[:1] == b"q":
        state["poses"] = take_socket(conn)
        selector.register(state["poses"], selectors.EVENT_READ)
        return None
    kind, *args = pickle.loads(request[1:])
    if kind == "session":
        poses.intake.set_session(*args)
        poses.forget()
        reply = None
    elif kind == "latest":
        reply = poses.latest and (poses.latest[0], approximation_values(poses.latest[1]))
    elif kind == "stats":
        reply = poses.stats()
    elif kind == "target":
        t0 = time.perf_counter()
        name, vertices, faces = args
        mesh = load_shape(name) if name else check_mesh(trimesh.Trimesh(vertices, faces), "mesh")
        fields = build_fields(mesh)
        approximate(fields, np.eye(4), poses.spec, poses.variant)  # loads the compiled code now, not on a pose
        state["mesh"], state["fields"] = mesh, fields
        poses.forget()
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
    name_process("vrscroll-worker")
    poses = _Poses(spec, variant)
    state = {"udp": None, "poses": None, "mesh": None, "fields": None}
    selector = selectors.DefaultSelector()
    selector.register(conn, selectors.EVENT_READ)
    hold_collection()
    while True:
        now = time.perf_counter()
        wait = poses.intake.wait_s(now)
        ready = selector.select(0)
        if not ready and wait != 0.0:  # no pose to answer now: its frame estimates if due, else sleep until due
            due = poses.estimates_due_s(now)
            if due == 0.0:
                poses.send_estimates(state["fields"], state["udp"])
                continue  # a pose that came meanwhile goes before anything else
            collect_if_due()  # the garbage collected, then sleep until something comes
            ready = selector.select(min((w for w in (wait, due) if w is not None), default=None))
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


class Worker(ChildProcess):
    """The service's end of the worker process (twin/live/child.py): requests "target", "session", "latest",
    "stats", "field"; the worker's reports on the pose stream go to on_report(session, code, message, count). A
    worker that dies (a crash of compiled code on some input) is started again at once, with the sockets, the target
    and the session it had, after on_death()."""

    def __init__(self, spec: DeviceSpec, variant: str, on_report=lambda *report: None, on_death=lambda: None):
        super().__init__("the approximation worker", "vrscroll-worker", _serve, (spec, variant), on_report, on_death,
                         replayed=("target",))
        self.spec, self.variant = spec, variant

    def share_sockets(self, replies: socket.socket, poses: socket.socket) -> None:
        """The socket the worker sends its answers from (the service's datagram socket: the client sees them come
        from the port it sends its pens to) and the one it takes poses from, handed to this worker and every
        restarted one."""
        super().share_sockets({b"s": replies, b"q": poses})

    def approximation(self, values: tuple) -> Approximation:
        return decode_approximation(self.spec, self.variant, values)
