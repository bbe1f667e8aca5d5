"""The live service: one asyncio loop serving the control channel and the datagram streams.

- Control channel (WebSocket): hello (role, token), target, lock, status; events back to the
  controller and every observer. One controlling client at a time.
- Datagrams (UDP): the controller's pen samples on the service's port (the same number), its
  poses on the worker's (`pose_port`). Each stream keeps only its newest sample: an older
  sequence number is dropped as stale, a pose that arrives before the previous one was
  approximated replaces it. Memory per stream is one sample.
- The pen process (twin/live/pens.py) takes the pens off the service's socket, which the service binds and hands
  over, and redirects and answers each there: no pen wakes the service, and none waits behind its event loop or
  the device link's threads.
- The worker process takes the poses off its own socket (the service binds it and hands it over;
  no pose wakes the service), approximates the newest at most APPROXIMATION_RATE_HZ times a
  second and sends the reply datagram itself, from the service's socket; the newest one's frame
  estimates follow in a datagram of their own when no pose waits, at most ESTIMATES_RATE_HZ a second
  (twin/live/worker.py, twin/live/poses.py). A pose never moves the device.
- Each pose's and pen sample's path is stamped stage by stage (twin/live/stages.py); `status`
  reports where the time went.
- Lock: the newest approximation's hinge angles go through the morpher (gate, then the device or
  the twin) in a thread; once done, the redirection field of the reached shape is built by the
  worker and handed to the pen process, which redirects the pen samples from then on, as they
  arrive (binary in and out, on state allocated once).

Errors in a client's messages are answered with an "error" event; the connection stays open.
Datagram errors are reported at most every ERROR_INTERVAL s per kind, with a count.
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import hmac
import json
import math
import resource
import secrets

import numpy as np
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.protocol import State

from twin.device.spec import DeviceSpec
from twin.formats.target import approximation_json
from twin.live.messages import (
    APPROXIMATION_RATE_HZ,
    DEFAULT_LISTEN_PORT,
    ESTIMATES_RATE_HZ,
    MAX_CONTROL_BYTES,
    MAX_DATAGRAM_BYTES,
    MAX_FRAME_BYTES,
    PROTOCOL_VERSION,
    ProtocolError,
    error,
    mesh_arrays,
    parse_control,
)
from twin.live.datagrams import ErrorReports, stamped_socket
from twin.live.morph import MorphOutcome
from twin.live.pens import PenProcess
from twin.live.stages import PEN_STAGES
from twin.live.worker import Worker, WorkerError
from twin.morphpatch.shapes import shape_names

LOOPBACK = ("127.0.0.1", "::1", "localhost")
EVENT_QUEUE = 256  # events waiting for one slow client; beyond this they are dropped and counted
PING_INTERVAL = 20.0  # s: a client that answers no ping for this long after one is dropped (its role freed)
MAX_CONNECTIONS = 32  # control-channel connections at once: one controller and observers
MAX_UNGREETED = 8  # of them, connections that have not said hello yet
HELLO_TIMEOUT = 5.0  # s a connection may stay without hello before it is closed
# TCP connections the service holds at once, those still in their WebSocket handshake included (the handler's
# limits above count only connections past it): twice MAX_CONNECTIONS, and at most a quarter of the process's file
# descriptors (the rest for the device, the worker, the files it writes, and connections accepted, ACCEPT_BACKLOG
# at a time, before the oldest are dropped). A connection past it drops the oldest one still in its handshake: 400
# half-open connections under `ulimit -n 256` ran the service out of descriptors (an accept error a second), and a
# client waited for their handshake timeout (10 s) to be served
MAX_SOCKETS = 2 * MAX_CONNECTIONS
ACCEPT_BACKLOG = 16  # connections the kernel queues for accept, and asyncio accepts in one go (its default 100)
WRONG_TOKEN_DELAY = 1.0  # s before a wrong token's connection is closed: at most one guess a second per connection


def check_exposure(host: str, allow_remote: bool, token: str | None) -> None:
    """ValueError unless the address is loopback, or remote serving was asked for with a token."""
    if host in LOOPBACK:
        return
    if not allow_remote:
        raise ValueError(f"--host {host}: serving beyond the loopback address (127.0.0.1, ::1) needs "
                         "--allow-remote, and every client must then present the token")
    if not token:
        raise ValueError(f"--host {host}: serving beyond loopback needs a token (--token, or VRSCROLL_TOKEN)")


@dataclasses.dataclass
class ServiceConfig:
    """What `vrscroll serve` starts. spec: the twin's, from the device profile (`profile` names it)."""

    spec: DeviceSpec
    morpher: object  # morph.DeviceMorpher or morph.TwinMorpher
    host: str = "127.0.0.1"
    listen: int = DEFAULT_LISTEN_PORT  # 0: any free port
    token: str | None = None
    allow_remote: bool = False
    variant: str = "full"
    shape: str | None = None  # the initial target: a named shape ...
    mesh: tuple | None = None  # ... or (vertices (V, 3) m, faces (F, 3))
    profile: str = "spec defaults"  # the device profile's name, as every report names it


class _Client:
    """One control-channel connection: its role, its session secret, its event queue and error reports."""

    def __init__(self, ws):
        self.ws = ws
        self.role = None
        self.session = None  # 32 hex digits (the welcome's), and as the 16 bytes a sample carries
        self.secret = None
        self.events: asyncio.Queue = asyncio.Queue(EVENT_QUEUE)
        self.dropped_events = 0
        self._due = ErrorReports()

    def send(self, event: dict) -> None:
        try:
            self.events.put_nowait(event)
        except asyncio.QueueFull:
            self.dropped_events += 1

    def report(self, code: str, message: str, count: int = 1) -> None:
        """A datagram error (count of them), rate-limited per code; the count says how many since the last report."""
        due = self._due.due(code, count)
        if due:
            self.send(error(code, message, "datagram", due))

    async def pump(self) -> None:
        try:
            while True:
                event = await self.events.get()
                await self.ws.send(json.dumps(event))
        except ConnectionClosed:
            pass


def socket_bound() -> int:
    """How many TCP connections the service holds at once: MAX_SOCKETS, or a quarter of the file descriptors it may
    open."""
    return max(1, min(MAX_SOCKETS, resource.getrlimit(resource.RLIMIT_NOFILE)[0] // 4))


def bounded_connections(held: dict, most: int, counts: collections.Counter) -> type:
    """A ServerConnection class whose instances, the TCP connections `serve` accepts, are kept in `held` (oldest
    first), at most `most`: one past it aborts the oldest still in its handshake (a half-open one that never sent
    its request), or itself when every other is past it (counted in counts["evicted_connections"])."""

    class BoundedConnection(ServerConnection):
        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            held[self] = None
            if len(held) > most:
                victim = next(c for c in held if c is self or c.protocol.state is State.CONNECTING)
                del held[victim]
                counts["evicted_connections"] += 1
                victim.transport.abort()

        def connection_lost(self, exc) -> None:
            held.pop(self, None)
            super().connection_lost(exc)

    return BoundedConnection


class LiveService:
    """The service's state; `run()` serves until `stop()`."""

    def __init__(self, config: ServiceConfig):
        check_exposure(config.host, config.allow_remote, config.token)
        self.config = config
        self.spec = config.spec
        self.morpher = config.morpher
        self.worker = Worker(config.spec, config.variant, self._child_report, self._worker_died)
        self.pens = PenProcess(self._child_report, self._pens_died)  # the pens' stream, redirected once locked
        self.port = None
        self.controller: _Client | None = None
        self.observers: set[_Client] = set()
        self.target = None  # info of the target the worker holds
        self.state = "idle"  # "idle", "morphing" or "locked" (pen samples redirected)
        self.counts: collections.Counter = collections.Counter()  # the streams' are the worker's and the pens' (status)
        self._udp = None  # the pens' socket (udp_port), which every reply is sent from
        self._poses = None  # the worker's pose socket: bound here, so that it outlives a worker that dies
        self._stop = None
        self._tasks: set[asyncio.Task] = set()
        self.clients: set[_Client] = set()  # every open control connection

    # ---- running ------------------------------------------------------------------------
    async def run(self, ready=None) -> None:
        """Start the worker, the pen process, the initial target, the morpher and both sockets; ready(port) once
        serving."""
        self._stop = asyncio.Event()
        self._poses = stamped_socket(self.config.host)  # before any client can be welcomed with its port
        self.worker.start()
        self.pens.start()
        try:
            if self.config.shape or self.config.mesh:
                vertices, faces = self.config.mesh or (None, None)
                await self._load_target(self.config.shape, vertices, faces)
            await asyncio.to_thread(self.morpher.open)
            async with serve(self._connection, self.config.host, self.config.listen, max_size=MAX_FRAME_BYTES,
                             ping_interval=PING_INTERVAL, ping_timeout=PING_INTERVAL,
                             create_connection=bounded_connections({}, socket_bound(), self.counts),
                             backlog=ACCEPT_BACKLOG) as server:
                self.port = server.sockets[0].getsockname()[1]
                self._udp = stamped_socket(self.config.host, self.port)
                self.pens.share_socket(self._udp)
                self.worker.share_sockets(self._udp, self._poses)
                if ready:
                    ready(self.port)
                await self._stop.wait()
        finally:
            for task in self._tasks:
                task.cancel()
            self.pens.stop()
            if self._udp is not None:
                self._udp.close()
            self.worker.stop()
            if self._poses is not None:
                self._poses.close()
            await asyncio.to_thread(self.morpher.close)

    def stop(self) -> None:
        """Stop serving (from the loop's thread)."""
        if self._stop is not None:
            self._stop.set()

    def _spawn(self, coroutine) -> asyncio.Task:
        task = asyncio.create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def _broadcast(self, event: dict) -> None:
        for client in ([self.controller] if self.controller else []) + list(self.observers):
            client.send(event)

    # ---- control channel ----------------------------------------------------------------
    async def _connection(self, ws) -> None:
        ungreeted = sum(c.role is None for c in self.clients)
        if len(self.clients) >= MAX_CONNECTIONS or ungreeted >= MAX_UNGREETED:
            self.counts["refused_connections"] += 1
            await ws.close(1013, f"too many connections (at most {MAX_CONNECTIONS}, {MAX_UNGREETED} before hello)")
            return
        client = _Client(ws)
        self.clients.add(client)
        pump = self._spawn(client.pump())
        hello_timer = asyncio.get_running_loop().call_later(HELLO_TIMEOUT, self._no_hello, client)
        try:
            async for message in ws:
                try:
                    await self._dispatch(client, parse_control(message))
                except ProtocolError as exc:
                    self.counts[exc.code] += 1
                    if exc.code == "unauthorized":  # said at once, not queued behind events, then closed
                        await ws.send(json.dumps(error(exc.code, str(exc))))
                        await asyncio.sleep(WRONG_TOKEN_DELAY)
                        await ws.close(1008, "unauthorized")
                        return
                    client.send(error(exc.code, str(exc)))
        except ConnectionClosed:
            pass
        finally:
            hello_timer.cancel()
            pump.cancel()
            self.clients.discard(client)
            self._leave(client)

    def _no_hello(self, client: _Client) -> None:
        """A connection still without hello after HELLO_TIMEOUT is closed (it holds a slot)."""
        if client.role is None:
            self.counts["hello_timeout"] += 1
            self._spawn(client.ws.close(1008, f"no hello within {HELLO_TIMEOUT:g} s"))

    def _leave(self, client: _Client) -> None:
        self.observers.discard(client)
        if client is self.controller:
            self.controller = None
            self.worker.tell("session", None)
            self.pens.tell("session", None)
            self._broadcast({"type": "controller_left", "state": self.state})

    async def _dispatch(self, client: _Client, msg: dict) -> None:
        kind = msg["type"]
        if kind == "hello":
            return self._hello(client, msg)
        if client.role is None:
            raise ProtocolError("out_of_order", f"{kind} before hello: send hello first")
        if kind == "status":
            return client.send(await self._status())
        if client is not self.controller:
            raise ProtocolError("forbidden", f"{kind}: observers only watch; connect with role 'control'")
        if self.state == "morphing":
            raise ProtocolError("out_of_order", f"{kind} during a morph: wait for done, refused or stopped")
        if kind == "target":
            vertices, faces = mesh_arrays(msg["mesh"]) if "mesh" in msg else (None, None)
            if "shape" in msg and msg["shape"] not in shape_names():
                raise ProtocolError("bad_target", f"unknown shape {msg['shape']!r}; known: {', '.join(shape_names())}")
            try:
                await self._load_target(msg.get("shape"), vertices, faces)
            except WorkerError as exc:
                raise ProtocolError("bad_target", str(exc)) from None
            return
        # lock: the newest approximation the worker sent this controller for this target (asked after any it
        # was sending when the lock came: the worker answers its requests between poses)
        if self.target is None:
            raise ProtocolError("out_of_order", "lock before any target: send target, then stream poses")
        try:
            latest = await self.worker.call("latest")
        except WorkerError as exc:
            raise ProtocolError("approximation_failed", str(exc)) from None
        if latest is None:
            raise ProtocolError("out_of_order", "lock before any approximation of this target: stream poses first")
        self.state = "morphing"
        self._spawn(self._lock(*latest))

    def _hello(self, client: _Client, msg: dict) -> None:
        if client.role is not None:
            raise ProtocolError("out_of_order", "hello twice on one connection")
        token = self.config.token
        if token and not hmac.compare_digest(msg.get("token", "").encode(), token.encode()):
            raise ProtocolError("unauthorized", "this service needs a token, and the one given is not it")
        if msg["role"] == "control":
            if self.controller is not None:
                raise ProtocolError("controller_taken", "another client controls the service; connect as 'observer'")
            self.controller = client
            client.secret = secrets.token_bytes(16)
            client.session = client.secret.hex()
            self.worker.tell("session", client.session)  # before the welcome: the worker admits its first pose
            self.pens.tell("session", client.session)
        else:
            self.observers.add(client)
        client.role = msg["role"]
        client.send({"type": "welcome", "protocol": PROTOCOL_VERSION, "role": client.role, "session": client.session,
                     "udp_port": self.port, "pose_port": self._poses.getsockname()[1], "variant": self.config.variant, "device": self.morpher.name,
                     "device_profile": self.config.profile,
                     "target": self.target, "state": self.state, "approximation_rate_hz": APPROXIMATION_RATE_HZ,
                     "estimates_rate_hz": ESTIMATES_RATE_HZ,
                     "max_control_bytes": MAX_CONTROL_BYTES, "max_datagram_bytes": MAX_DATAGRAM_BYTES})

    async def _load_target(self, shape, vertices, faces) -> None:
        self.target, self.state = None, "idle"
        await self.pens.call("field", None)
        self.target = await self.worker.call("target", shape, vertices, faces)
        self._broadcast({"type": "target_ready", "target": self.target})

    async def _status(self) -> dict:
        device = await asyncio.to_thread(self.morpher.status)
        try:
            poses = await self.worker.call("stats")
        except WorkerError:  # restarting: its counts start again
            poses = {"counts": {}, "pose_path_ms": None, "pose_cpu_ms": None, "estimates_ms": None,
                     "estimates_cpu_ms": None}
        try:
            pens = await self.pens.call("stats")
        except WorkerError:
            pens = {"counts": {}, "pen_path_ms": dict.fromkeys(PEN_STAGES)}
        counts = self.counts + collections.Counter(poses["counts"]) + collections.Counter(pens["counts"])
        pose_path = poses["pose_path_ms"]
        return {"type": "status", "state": self.state, "target": self.target, "variant": self.config.variant,
                "controller": self.controller is not None, "observers": len(self.observers), **device,
                "counts": dict(counts),
                "approximation_latency_ms": pose_path and pose_path["total"],
                "pen_latency_ms": pens["pen_path_ms"]["total"],
                "pose_path_ms": pose_path, "pose_cpu_ms": poses["pose_cpu_ms"], "pen_path_ms": pens["pen_path_ms"],
                "estimates_ms": poses["estimates_ms"], "estimates_cpu_ms": poses["estimates_cpu_ms"]}

    def _child_report(self, session: str | None, code: str, message: str, count: int) -> None:
        """The worker's or the pen process's report of errors in the pose or pen stream of the controller holding
        `session`."""
        if self.controller is not None and self.controller.session == session:
            self.controller.report(code, message, count)

    def _worker_died(self) -> None:
        """The worker died (on a pose, or a request): the controller's pose in flight gets no answer."""
        self.counts["worker_restarts"] += 1
        if self.controller is not None:
            self.controller.report("approximation_failed", "the approximation worker died on a pose; it is "
                                                           "restarted with the target for the next")

    def _pens_died(self) -> None:
        """The pen process died: the pen it was answering gets no reply; it is restarted with the field."""
        self.counts["pen_process_restarts"] += 1

    async def _lock(self, seq: int, values: tuple) -> None:
        loop = asyncio.get_running_loop()
        approx = self.worker.approximation(values)
        try:
            await self.pens.call("field", None)  # the last lock's field: no pen is redirected with it from now on
        except WorkerError:
            pass  # restarting: it starts without a field
        self._broadcast({"type": "locked", "seq": seq, **approximation_json(approx)})

        def emit(event):
            loop.call_soon_threadsafe(self._broadcast, event)

        try:
            outcome = await asyncio.to_thread(self.morpher.morph, approx.angles, emit)
        except Exception as exc:  # the morph thread's boundary: report it, and never stay "morphing"
            outcome = MorphOutcome("stopped", None, f"{type(exc).__name__}: {exc}")
        if outcome.status != "done":
            self.state = "idle"
            self._broadcast({"type": outcome.status, "message": outcome.message,
                             "angles_deg": None if outcome.final is None else np.degrees(outcome.final).round(3).tolist()})
            return
        try:
            field, summary = await self.worker.call("field", approx.root_pose, outcome.final, approx.widths)
            await self.pens.call("field", field)  # before `done`: the pens that follow it are redirected
        except WorkerError as exc:
            self.state = "idle"
            self._broadcast({"type": "stopped", "message": f"redirection field: {exc}", "angles_deg": None})
            return
        self.state = "locked"
        settle = outcome.settle_time
        self._broadcast({"type": "done", "message": outcome.message, "seq": seq,
                         "settle_time_s": round(settle, 4) if math.isfinite(settle) else None,
                         "angles_deg": np.degrees(outcome.final).round(3).tolist(), "redirection": summary})
