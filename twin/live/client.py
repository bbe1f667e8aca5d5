"""A Python client of the live service (docs/live.md): the control channel and the datagram socket.

    async with LiveClient("ws://127.0.0.1:8765") as client:
        await client.set_target(shape="cylinder")
        client.send_pose([10, 0, 190], [1, 0, 0, 0])          # mm, quaternion w first
        approximation = await client.datagram("approximation")
        estimates = await client.datagram("estimates")            # its MSD and share estimates, just after
        await client.lock()
        outcome = await client.expect("done", "refused", "stopped", timeout=10)
        client.send_pen([0, 0, 150], [1, 0, 0, 0])
        redirected = await client.datagram("pen_redirected")

Events from the control channel and datagrams from the service are queued as they come
(bounded: the oldest go first when a queue is full); every event is also kept in `history`.
Times put in `t_s` are this process's `time.perf_counter()`, and each datagram reply is
stamped `received_s` when this process takes it off its socket (before it is parsed), so `latency(reply)` is the
round trip of the sample it answers, and `arrived_s` with the kernel's stamp of its arrival in the socket, so
`received_s - arrived_s` is this client's wake-up. The client's own part is kept too (`send_s`: encoding and sending
a sample, from its `t_s` on; `receive_s`: parsing and queueing a reply; the last QUEUE of each, s).
"""

from __future__ import annotations

import asyncio
import collections
import json
import socket
import time
from urllib.parse import urlparse

from websockets.asyncio.client import connect

from twin.live.datagrams import drain, stamped_socket
from twin.live.messages import MAX_FRAME_BYTES, PROTOCOL_VERSION, decode_reply, encode_sample
from twin.live.scheduling import ask_thread_slice

QUEUE = 4096  # datagram replies kept per kind before the oldest are dropped


class LiveError(RuntimeError):
    """The service refused (an "error" event where another was expected), or did not answer in time."""


def _put(queue: asyncio.Queue, item) -> None:
    if queue.full():
        queue.get_nowait()
    queue.put_nowait(item)


class LiveClient:
    """One connection: `role` "control" (streams and locks) or "observer" (events only)."""

    def __init__(self, url: str, role: str = "control", token: str | None = None, protocol: int = PROTOCOL_VERSION,
                 short_slice: bool = False):
        """protocol: the version said in hello (an older one only to measure an older service, with JSON samples:
        benchmarks/bench_live.py); short_slice: the thread that connects (whose event loop takes the replies) asks
        Linux for its shortest scheduler slice (twin/live/scheduling.py): woken by a reply, it preempts a task running
        a longer one. It stays so after the client closes."""
        self.url, self.role, self.token, self.protocol = url, role, token, protocol
        self.short_slice = short_slice
        self.ws = None
        self.welcome = None
        self.history: list[dict] = []
        self.received: collections.Counter = collections.Counter()  # datagrams received, by type
        self._events: asyncio.Queue = asyncio.Queue()
        self._datagram_queues = collections.defaultdict(lambda: asyncio.Queue(QUEUE))
        self._udp: socket.socket | None = None  # the datagram socket (non-blocking), read by the event loop
        self._service = None  # (host, port) every reply comes from
        self._buffer = memoryview(bytearray(1 << 16))  # the largest datagram (an older service's JSON replies too)
        self._drops: collections.Counter = collections.Counter()
        self._ports = {}  # "pen", "pose": the service's address each is sent to
        self._reader = None
        self._seq = {"pose": 0, "pen": 0}
        self.send_s: collections.deque = collections.deque(maxlen=QUEUE)  # s per sample, t_s -> handed to the socket
        self.receive_s: collections.deque = collections.deque(maxlen=QUEUE)  # s per reply, arrival -> queued

    async def __aenter__(self) -> "LiveClient":
        await self.connect()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    async def connect(self, timeout: float = 10.0) -> dict:
        """Open the control channel, say hello, open the datagram socket; the welcome event (LiveError if refused)."""
        self.ws = await connect(self.url, max_size=MAX_FRAME_BYTES, ping_interval=None)
        self._reader = asyncio.create_task(self._read())
        hello = {"type": "hello", "protocol": self.protocol, "role": self.role}
        if self.token is not None:
            hello["token"] = self.token
        await self.send(hello)
        self.welcome = await self.expect("welcome", timeout=timeout)
        if self.role == "control":  # one socket: pens to udp_port, poses to pose_port, every reply from udp_port
            loop = asyncio.get_running_loop()
            host = urlparse(self.url).hostname
            family, *_, service = (await loop.getaddrinfo(host, self.welcome["udp_port"], type=socket.SOCK_DGRAM))[0]
            # a service older than protocol 3 takes its poses on udp_port too (benchmarks/bench_live.py --against)
            self._ports = {"pen": service, "pose": (service[0], self.welcome.get("pose_port", service[1]))}
            self._service = service[:2]
            self._udp = stamped_socket("::" if family == socket.AF_INET6 else "0.0.0.0")
            loop.add_reader(self._udp, self._take_replies)
            if self.short_slice:
                ask_thread_slice()
        return self.welcome

    async def close(self) -> None:
        if self._udp is not None:
            asyncio.get_running_loop().remove_reader(self._udp)
            self._udp.close()
        if self.ws is not None:
            await self.ws.close()
        if self._reader is not None:
            self._reader.cancel()

    async def _read(self) -> None:
        try:
            async for message in self.ws:
                event = json.loads(message)
                self.history.append(event)
                self._events.put_nowait(event)
        finally:
            self._events.put_nowait({"type": "closed", "code": self.ws.close_code, "reason": self.ws.close_reason})

    # ---- control channel --------------------------------------------------------------------
    async def send(self, message) -> None:
        """A control message: a dict (sent as JSON), or text/bytes as they are."""
        await self.ws.send(json.dumps(message) if isinstance(message, dict) else message)

    async def expect(self, *types: str, timeout: float = 10.0) -> dict:
        """The next event of one of `types`, skipping others (they stay in `history`).

        LiveError on an "error" about a control message (unless "error" is asked for; datagram errors are
        only kept in `history`), on the connection closing, or on timeout.
        """
        deadline = time.monotonic() + timeout
        while True:
            try:
                event = await asyncio.wait_for(self._events.get(), max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                raise LiveError(f"no {' or '.join(types)} within {timeout:g} s") from None
            if event["type"] in types:
                return event
            if event["type"] == "closed" or (event["type"] == "error" and event["source"] == "control"):
                raise LiveError(f"{event['type']}: {event.get('code', '')} {event.get('message', event.get('reason'))}")

    async def set_target(self, shape: str | None = None, mesh: dict | None = None, timeout: float = 60.0) -> dict:
        """Name a shape, or send a mesh {vertices_mm, faces}; the target_ready event."""
        await self.send({"type": "target", **({"shape": shape} if shape is not None else {"mesh": mesh})})
        return await self.expect("target_ready", timeout=timeout)

    async def lock(self) -> dict:
        """Lock the newest approximation; the "locked" event (then await done, refused or stopped)."""
        await self.send({"type": "lock"})
        return await self.expect("locked")

    async def status(self) -> dict:
        await self.send({"type": "status"})
        return await self.expect("status")

    # ---- datagrams ------------------------------------------------------------------------------
    def _send_sample(self, kind: str, position_mm, quat_wxyz, **extra) -> int:
        seq = self._seq[kind]
        self._seq[kind] += 1
        t_s = time.perf_counter()
        encode = encode_sample if self.protocol >= 4 else json_sample
        self._udp.sendto(encode(kind, self.welcome["session"], seq, position_mm, quat_wxyz, t_s=t_s, **extra),
                         self._ports[kind])
        self.send_s.append(time.perf_counter() - t_s)
        return seq

    def send_pose(self, position_mm, quat_wxyz) -> int:
        """The tracked device pose (anchor, target's frame): mm and a quaternion w first; returns its seq."""
        return self._send_sample("pose", position_mm, quat_wxyz)

    def send_pen(self, position_mm, quat_wxyz, device_position_mm=None, device_quat_wxyz=None) -> int:
        """A pen sample (tip, mm; orientation w first), optionally with the device pose it was tracked with."""
        return self._send_sample("pen", position_mm, quat_wxyz, device_position_mm=device_position_mm,
                                 device_quat_wxyz=device_quat_wxyz)

    def _take_replies(self) -> None:
        """Every reply waiting on the socket, queued by kind (what the event loop calls when the socket is ready)."""
        drain(self._udp, self._buffer, self._drops, "dropped", self._on_reply)

    def _on_reply(self, n: int, addr, arrived: float, received: float) -> None:
        if addr[:2] != self._service:
            return
        try:
            obj = decode_reply(bytes(self._buffer[:n]))
        except ValueError:
            return
        obj["received_s"], obj["arrived_s"] = received, arrived
        self.received[obj["type"]] += 1
        _put(self._datagram_queues[obj["type"]], obj)
        self.receive_s.append(time.perf_counter() - received)

    def spin(self, kind: str, limit_s: float) -> bool:
        """Wait for a `kind` datagram by polling the socket, on this core, for at most limit_s s (a VR frame's
        reply taken the moment it arrives, with no wake-up; the CPU it costs is the wait); whether one came. What
        comes meanwhile is queued as the event loop would (read with `datagram` or `drain`)."""
        before, deadline = self.received[kind], time.perf_counter() + limit_s
        while self.received[kind] == before and time.perf_counter() < deadline:
            self._take_replies()
        return self.received[kind] != before

    def send_raw_datagram(self, data: bytes, to: str = "pen") -> None:
        """Any bytes, to the port pens ("pen") or poses ("pose") go to."""
        self._udp.sendto(data, self._ports[to])

    async def datagram(self, kind: str, timeout: float = 2.0) -> dict:
        """The next "approximation", "estimates" or "pen_redirected" datagram; LiveError after `timeout` s."""
        try:
            return await asyncio.wait_for(self._datagram_queues[kind].get(), timeout)
        except TimeoutError:
            raise LiveError(f"no {kind} datagram within {timeout:g} s") from None

    def drain(self, kind: str) -> list[dict]:
        """Every queued datagram of `kind`, oldest first."""
        queue, out = self._datagram_queues[kind], []
        while not queue.empty():
            out.append(queue.get_nowait())
        return out

    @property
    def session(self) -> str:
        return self.welcome["session"]


def latency(reply: dict) -> float:
    """s from sending the sample (its t_s) to receiving the reply."""
    return reply["received_s"] - reply["t_s"]


def json_sample(kind: str, session: str, seq: int, position_mm, quat_wxyz, t_s: float | None = None,
                device_position_mm=None, device_quat_wxyz=None) -> bytes:
    """A sample as protocols 1-3 sent it (one JSON object), for measuring an older service against this one."""
    obj = {"type": kind, "session": session, "seq": int(seq),
           "position_mm": [float(v) for v in position_mm], "quat_wxyz": [float(v) for v in quat_wxyz]}
    if t_s is not None:
        obj["t_s"] = float(t_s)
    if device_position_mm is not None:
        obj["device_position_mm"] = [float(v) for v in device_position_mm]
        obj["device_quat_wxyz"] = [float(v) for v in device_quat_wxyz]
    return json.dumps(obj, separators=(",", ":")).encode()
