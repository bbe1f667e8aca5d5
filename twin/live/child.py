"""A child process of the live service, from both ends: the service's (`ChildProcess`: requests, replies,
reports, restart after a death) and the child's (`name_process`, `take_socket`).

The service runs two: the approximation worker (twin/live/worker.py: the poses) and the pen process
(twin/live/pens.py: the pens). Each waits on its own datagram socket and its pipe to the service, and nothing
else: no other thread holds its interpreter lock, no other work stands before a datagram that comes in.

Over the pipe, frames of bytes whose first byte says what follows; requests are answered in order, one at a time:

    b"s" / b"q" + a socket (its descriptor, passed alongside with SCM_RIGHTS)  -> no reply
    b"p" + pickle((kind, *args))  -> b"p" + pickle(reply), or b"e" + one line (refused; the child carries on)

and, unasked, between replies: b"r" + pickle((session, code, message, count)), an error in a datagram stream for
the controller holding `session` (the child rate-limits them).
"""

from __future__ import annotations

import asyncio
import collections
import ctypes
import multiprocessing
from multiprocessing import reduction
import pickle
import socket
import sys

PR_SET_NAME = 15  # Linux's prctl: the calling thread's name (/proc/PID/comm, what top and ps show), 15 bytes


class WorkerError(RuntimeError):
    """A child process refused a request (bad mesh, no target) or has gone."""


def name_process(name: str) -> None:
    """The calling process's name as ps and /proc/PID/comm show it (Linux; elsewhere nothing): the service's
    children are told apart by it (`vrscroll-worker`, `vrscroll-pens`)."""
    try:
        ctypes.CDLL(None).prctl(PR_SET_NAME, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError):
        pass


def take_socket(conn) -> socket.socket:
    """The socket the service hands over after a b"s" or b"q" frame, non-blocking."""
    sock = socket.socket(fileno=reduction.recv_handle(conn))
    sock.setblocking(False)
    return sock


class ChildProcess:
    """The service's end of one child process (`serve(conn, *args)` in a spawned process named `name`): `call`
    (awaited) and `tell` (no reply awaited) send requests; its reports go to on_report(session, code, message,
    count). A child that dies is started again at once, with the sockets and the last request of each kind `tell`
    sent (and of the `replayed` kinds `call` sent) sent again, after on_death()."""

    def __init__(self, what: str, name: str, serve, args: tuple, on_report=lambda *report: None,
                 on_death=lambda: None, replayed: tuple[str, ...] = ()):
        """what: the child in a sentence ("the approximation worker"); name: its process name; replayed: the kinds of
        request that `call` sends whose last one a restarted child gets again (every kind `tell` sends is)."""
        self.what, self.name, self._serve, self._args, self.replayed = what, name, serve, args, replayed
        self.on_report, self.on_death = on_report, on_death
        self._conn = self._proc = None
        self._waiting: collections.deque = collections.deque()  # per request sent: a Future, or a callable
        self._sockets: dict[bytes, socket.socket] = {}  # frame kind -> socket, handed to every child started
        self._replay: dict[str, tuple] = {}  # request kind -> the last sent, sent again after a restart
        self._restarting: asyncio.Task | None = None
        self.restarts = 0
        self._exitcode = None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def start(self) -> None:
        context = multiprocessing.get_context("spawn")  # no copy of the service's threads and sockets
        self._conn, child = context.Pipe()
        self._proc = context.Process(target=self._serve, args=(child, *self._args), daemon=True, name=self.name)
        self._proc.start()
        child.close()
        asyncio.get_running_loop().add_reader(self._conn.fileno(), self._readable)
        for kind in self._sockets:
            self._hand_socket(kind)

    def share_sockets(self, sockets: dict[bytes, socket.socket]) -> None:
        """Sockets for this child and every restarted one ({frame kind: socket})."""
        self._sockets = dict(sockets)
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
            self._fail_waiting(WorkerError(f"{self.what} died on this request; it is restarted"))
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
            raise WorkerError(f"{self.what} has gone; it is being restarted") from None
        self._waiting.append(waiter)

    def tell(self, *request) -> None:
        """Send a request whose reply nobody awaits (sent before this returns, so before anything the caller sends
        next); a restarted child gets the last of each kind too."""
        self._replay[request[0]] = request
        if self._proc is not None:
            try:
                self._post(request, lambda value: None)
            except WorkerError:
                pass  # it died: the restart replays it

    async def call(self, *request):
        """Send one request and await its reply; WorkerError if refused, or if the child was never started, has been
        stopped, or died on it. One of the `replayed` kinds that it took is sent to a restarted child too."""
        if self._proc is None:
            raise WorkerError(f"{self.what} is not running")
        if self._restarting is not None:
            await asyncio.shield(self._restarting)
        value = await self._send(request)
        if request[0] in self.replayed:
            self._replay[request[0]] = request
        return value

    async def _send(self, request: tuple):
        future = asyncio.get_running_loop().create_future()
        self._post(request, future)
        return await future

    async def _restart(self) -> None:
        try:
            self._close()
            self.restarts += 1
            print(f"vrscroll serve: {self.what} died (exit {self._exitcode}); restart {self.restarts}",
                  file=sys.stderr, flush=True)
            self.start()
            for kind in list(self._replay):  # each as it is when sent: a newer one told meanwhile is not undone
                await self._send(self._replay[kind])
        except WorkerError as exc:
            print(f"vrscroll serve: the restarted {self.what.removeprefix('the ')} refused its state: {exc}",
                  file=sys.stderr, flush=True)
        finally:
            self._restarting = None

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
        self._fail_waiting(WorkerError(f"{self.what} was stopped"))
