"""The approximation worker: a child process that holds the target and approximates.

An approximation takes 1-4 ms and a redirection field ~100 ms of compiled code that holds
Python's interpreter lock, so they run in their own process, and the service's event loop
stays free for the pen stream (5 us per redirected sample). The two talk over a pipe;
requests are answered in order, one at a time:

    ("target", shape name or None, vertices (V, 3) m, faces (F, 3))  -> target info (mm, s)
    ("approximate", pose 4x4)  -> (Approximation, MSD estimate m, share-within estimate)
    ("field", root pose 4x4, angles rad, widths m)  -> (RedirectionField, threshold summary)

Errors come back as ("error", one line) and the worker carries on.
"""

from __future__ import annotations

import asyncio
import collections
import multiprocessing
import sys
import time

import numpy as np
import trimesh

from twin.device.spec import DeviceSpec
from twin.morphpatch.approximation import approximate
from twin.morphpatch.fields import build_fields
from twin.morphpatch.frame_metrics import frame_estimates
from twin.morphpatch.redirection import build_field, threshold_summary
from twin.morphpatch.shapes import check_mesh, load_shape
from twin.perception.thresholds import load_thresholds


class WorkerError(RuntimeError):
    """The worker refused a request (bad mesh, no target) or has gone."""


def _serve(conn, spec: DeviceSpec, variant: str) -> None:
    """The child's loop: one request in, one reply out, until the pipe closes."""
    thresholds = load_thresholds()
    mesh = fields = None
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        kind = request[0]
        try:
            if kind == "target":
                t0 = time.perf_counter()
                name, vertices, faces = request[1:]
                mesh = load_shape(name) if name else check_mesh(trimesh.Trimesh(vertices, faces), "mesh")
                fields = build_fields(mesh)
                approximate(fields, np.eye(4), spec, variant)  # loads the compiled code now, not on the first pose
                reply = {"name": name or "mesh", "bounds_mm": (mesh.bounds * 1e3).round(3).tolist(),
                         "faces": len(mesh.faces), "build_s": round(time.perf_counter() - t0, 3)}
            elif fields is None:
                raise WorkerError("no target yet")
            elif kind == "approximate":
                result = approximate(fields, request[1], spec, variant)
                msd, share = frame_estimates(spec, fields, thresholds, result.root_pose, result.angles, result.widths)
                reply = (result, msd, share)
            else:  # "field"
                field = build_field(spec, *request[1:], mesh, fields)
                reply = (field, threshold_summary(field, thresholds))
            conn.send(("ok", reply))
        except Exception as exc:  # a process boundary: report it to the service, stay alive for the next request
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


class Worker:
    """The service's end of the worker process; `call` is awaited on the service's event loop."""

    def __init__(self, spec: DeviceSpec, variant: str):
        self.spec = spec
        self.variant = variant
        self._conn = self._proc = None
        self._waiting: collections.deque[asyncio.Future] = collections.deque()
        self._target = None  # the last target request it took, sent again to a restarted worker
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

    def _readable(self) -> None:
        try:
            status, value = self._conn.recv()
        except (EOFError, OSError):
            asyncio.get_running_loop().remove_reader(self._conn.fileno())
            while self._waiting:
                self._waiting.popleft().set_exception(WorkerError("the approximation worker died on this request; "
                                                                  "it is restarted for the next"))
            return
        future = self._waiting.popleft()
        if not future.cancelled():
            future.set_result((status, value))

    async def call(self, *request):
        """Send one request and await its reply; WorkerError if refused. A worker that died (a crash of
        compiled code on some input) is started again first, with the last target it took."""
        if self._proc is None:
            raise WorkerError("the approximation worker is not running")
        if not self._proc.is_alive():
            await self._restart()
        value = await self._send(request)
        if request[0] == "target":
            self._target = request
        return value

    async def _send(self, request):
        future = asyncio.get_running_loop().create_future()
        self._waiting.append(future)
        self._conn.send(request)
        status, value = await future
        if status == "error":
            raise WorkerError(value)
        return value

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
