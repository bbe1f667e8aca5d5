"""The pens, served by a process of their own (the pen process): the controller's pen stream taken off the service's
datagram socket (`udp_port`) and each sample redirected and answered there, on state allocated once: the datagram's
buffer, the sample's values, the redirection's inputs and outputs, the reply's bytes.

Why a process that does nothing else: in the service's own process a pen woke an event loop that also served the
control channel and shared its interpreter lock with the device link's threads (a reader woken ~100 times a
second, a heartbeat ~50 times, ~15 ms of CPU a second between them, holding the lock while they ran); a pen that
came while one of them held it, or while the loop handled something else, waited for it (and, on a loaded machine,
for that thread to get a core back). Here a pen waits for nothing but a core: one thread, one socket and a pipe
from the service that carries a request only when a controller comes or goes, a lock starts or ends, or `status`
asks (twin/live/child.py; docs/live.md, "Measured").

Per sample, three compiled calls and no JSON: the check (`SampleBuffer.check`), the redirection's kernel
(`twin.morphpatch.redirection`'s, the one `redirect` runs, called here on the preallocated arrays) and the reply's
encoding with the thresholds' verdict (`encode_pen_reply`). `redirect` itself, for one sample, allocated its
outputs and a Redirected, and the JSON on either side of it was most of a pen's time in the service
(docs/live.md, "Measured"). A pen that carries the tracked device's pose has its correction (the approximation's
root pose times the inverse of the device's) computed in numpy, as `redirect` does: that variant allocates.
"""

from __future__ import annotations

import collections
import hmac
import pickle
import selectors
import socket
import time

import numpy as np

from twin.device.kinematics import pose_matrix, quat_matrix
from twin.live.child import ChildProcess, name_process, take_socket
from twin.live.collection import collect_if_due, hold_collection
from twin.live.datagrams import ErrorReports, drain
from twin.live.messages import PEN_REPLY, SampleBuffer, encode_pen_reply, sample_error
from twin.live.scheduling import ask_short_slice
from twin.live.stages import LATENCY_WINDOW, PEN_STAGES, StageTimes
from twin.morphpatch.redirection import RedirectionField, redirect_kernel
from twin.perception.thresholds import Thresholds, load_thresholds


class PenRedirection:
    """The service's pens: `buffer` receives a datagram; once checked, `redirect()` writes the reply to `reply`."""

    def __init__(self, thresholds: Thresholds):
        self.thresholds = thresholds
        self.buffer = SampleBuffer()
        values = self.buffer.values
        self._position, self._quat = values[2:5].reshape(1, 3), values[5:9].reshape(1, 4)  # views: SI, unit
        self._out_p, self._out_q, self._info = np.zeros((1, 3)), np.zeros((1, 4)), np.zeros((1, 6))
        self._carry, self._no_carry = np.zeros((1, 4, 4)), np.zeros((0, 4, 4))
        self._words = np.zeros(PEN_REPLY.size // 8)
        self._raw, self._longs = self._words.view(np.uint8), self._words.view(np.uint64)
        self.reply = memoryview(self._raw)  # the reply datagram, PEN_REPLY.size bytes
        self._field = None  # the kernel's arguments from the field
        self._root = None

    def set_field(self, field: RedirectionField | None) -> None:
        """The field pens are redirected with from now on (None: none); the compiled code loaded now, not on a pen."""
        if field is None:
            self._field = self._root = None
            return
        self._root = field.root_pose
        self._field = (np.ascontiguousarray(field.frames[:, :3, :3]), np.ascontiguousarray(field.frames[:, :3, 3]),
                       field.s_edges, field.s0, field.ds, field.y0, field.dy, field.offset, field.rotation)
        self.buffer.values[:] = 0.0
        self.buffer.values[5] = 1.0
        self.redirect()

    def redirect(self) -> bool:
        """The checked pen sample in `buffer` redirected, its reply in `reply`; whether within both thresholds."""
        values = self.buffer.values
        carry = self._no_carry
        if values[17]:  # the pen relative to the tracked device, put where the approximation has the device
            carry = self._carry
            carry[:] = self._root @ np.linalg.inv(pose_matrix(values[9:12], quat_matrix(values[12:16]))[None])
        redirect_kernel(*self._field, self._position, self._quat, carry, self._out_p, self._out_q, self._info)
        return encode_pen_reply(values, self._out_p, self._out_q, self._info, self.thresholds.position,
                                self.thresholds.rotation, self._raw, self._words, self._longs)


class PenStream:
    """The controlling client's pen stream: its session and sequence numbers, the field (None: not locked), the
    counts, each sample's stage times, and the errors to report (session, code, message, count)."""

    def __init__(self, thresholds: Thresholds):
        self.pens = PenRedirection(thresholds)
        self.udp: socket.socket | None = None  # the service's datagram socket: pens in, replies out
        self.session: bytes | None = None  # the controller's secret; None: no controller, every pen dropped
        self.addr = None  # where the controller's valid pens come from
        self.last_seq = -1
        self.locked = False
        self.counts: collections.Counter = collections.Counter()
        self.times = StageTimes(PEN_STAGES, LATENCY_WINDOW)  # s per stage, pen arrival -> redirected sent
        self.reports: list[tuple] = []
        self._due = ErrorReports()

    def set_session(self, session: str | None) -> None:
        """A new controller (its secret, 32 hex digits), or none: the stream starts again."""
        self.session = None if session is None else bytes.fromhex(session)
        self.addr, self.last_seq = None, -1

    def set_field(self, field: RedirectionField | None) -> None:
        """The field of the device's shape once a lock's morph is done (pens redirected), or None (not)."""
        self.pens.set_field(field)
        self.locked = field is not None

    def report(self, code: str, message: str) -> None:
        count = self._due.due(code)
        if count:
            self.reports.append((None if self.session is None else self.session.hex(), code, message, count))

    def drain(self) -> None:
        """Every pen waiting on the socket, at most DRAIN_MAX (twin.live.datagrams.drain)."""
        drain(self.udp, self.pens.buffer.view, self.counts, "pen_dropped", self.on_pen)

    def on_pen(self, n: int, addr, arrived: float, taken: float) -> None:
        """The n bytes in the pens' buffer from addr, that reached the socket at `arrived` and were taken off it at
        `taken` (perf_counter s): checked, and redirected and answered once locked."""
        self.counts["datagrams"] += 1
        buffer = self.pens.buffer
        code = buffer.check(n, "pen")
        if code:
            exc = sample_error(code, n)
            self.counts[exc.code] += 1
            if self.session is not None and addr == self.addr:
                self.report(exc.code, str(exc))
            return
        if self.session is None or not hmac.compare_digest(buffer.session, self.session):
            self.counts["unknown_session"] += 1
            return
        self.addr = addr
        seq, last = int(buffer.values[0]), self.last_seq
        if seq <= last:
            self.counts["stale"] += 1
            self.report("stale", f"pen seq {seq} after {last}: dropped (the newest wins)")
            return
        if last >= 0:
            self.counts["missing"] += seq - last - 1
        self.last_seq = seq
        self.counts["pen"] += 1
        if not self.locked:
            self.counts["pen_not_locked"] += 1
            self.report("out_of_order", "pen sample before a lock's morph is done: not redirected")
            return
        checked = time.perf_counter()
        self.pens.redirect()
        redirected = time.perf_counter()
        try:
            self.udp.sendto(self.pens.reply, addr)
        except OSError:  # the socket's send buffer full (a flood of replies): this one is lost, as on the network
            self.counts["reply_not_sent"] += 1
            return
        self.counts["pen_redirected"] += 1
        self.times.record((arrived, taken, checked, redirected, time.perf_counter()))

    def request(self, kind: str, *args):
        """One request from the service ("session", "field", "stats"); its reply."""
        if kind == "session":
            return self.set_session(*args)
        if kind == "field":
            return self.set_field(*args)
        return {"counts": dict(self.counts), "pen_path_ms": self.times.summary()}


def _serve(conn) -> None:
    """The pen process's loop: requests from the pipe, pens from the service's socket, until the pipe closes."""
    name_process("vrscroll-pens")
    ask_short_slice()  # woken by a datagram, it preempts a task running a longer slice (twin/live/scheduling.py)
    stream = PenStream(load_thresholds())
    selector = selectors.DefaultSelector()
    selector.register(conn, selectors.EVENT_READ)
    hold_collection()
    while True:
        ready = selector.select(0)
        if not ready:  # nothing waits: collect the garbage now, then sleep until something comes
            collect_if_due()
            ready = selector.select()
        # the pipe first: a session or a field named there comes before the pens it admits
        while any(key.fileobj is conn for key, _ in ready) and conn.poll():
            try:
                request = conn.recv_bytes()
            except (EOFError, OSError):
                return
            if request[:1] == b"s":
                stream.udp = take_socket(conn)
                selector.register(stream.udp, selectors.EVENT_READ)
                continue
            try:
                reply = b"p" + pickle.dumps(stream.request(*pickle.loads(request[1:])))
            except Exception as exc:  # a process boundary: report it to the service, stay alive for the next
                reply = b"e" + f"{type(exc).__name__}: {exc}".encode()
            conn.send_bytes(reply)
        if stream.udp is not None and any(key.fileobj is stream.udp for key, _ in ready):
            stream.drain()
        for report in stream.reports:
            conn.send_bytes(b"r" + pickle.dumps(report))
        stream.reports.clear()


class PenProcess(ChildProcess):
    """The service's end of the pen process (twin/live/child.py): requests "session" (the controller's secret or
    None), "field" (a RedirectionField once a lock is done, None otherwise), "stats" ({"counts", "pen_path_ms"});
    its reports of errors in the pen stream go to on_report(session, code, message, count). One that dies is started
    again with the socket, the session and the field it had."""

    def __init__(self, on_report=lambda *report: None, on_death=lambda: None):
        super().__init__("the pen process", "vrscroll-pens", _serve, (), on_report, on_death, replayed=("field",))

    def share_socket(self, udp: socket.socket) -> None:
        """The service's datagram socket (`udp_port`): the pens come in on it and their replies go out from it."""
        self.share_sockets({b"s": udp})
