"""The service's datagram sockets: each datagram read into a preallocated buffer, stamped with its arrival in the
kernel (SO_TIMESTAMPNS), with the count of those the kernel dropped (SO_RXQ_OVFL).

The stamp turns the time a datagram waited in its socket (the process busy, or waiting for a core) into a stage
of its path (twin/live/stages.py) for the poses (the worker's socket) and the pens (the service's) alike.
"""

from __future__ import annotations

import collections
import math
import socket
import struct
import time

from twin.live.messages import ERROR_INTERVAL

DRAIN_MAX = 256  # datagrams taken off a socket in one go: a flood cannot keep the process's other work waiting
# Linux's socket options (asm-generic/socket.h; Python names neither), each in a datagram's ancillary data:
SO_TIMESTAMPNS = 35  # its arrival time in the kernel (CLOCK_REALTIME, a struct timespec)
SO_RXQ_OVFL = 40  # how many datagrams the kernel has dropped on this socket so far (its buffer full: a flood)
_TIMESPEC = struct.Struct("@qq")  # s, ns
_DROPS = struct.Struct("@I")
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size) + socket.CMSG_SPACE(_DROPS.size)


def stamped_socket(host: str, port: int = 0) -> socket.socket:
    """A non-blocking datagram socket bound to host:port (0: any free one) whose datagrams carry their arrival
    stamp and the count of those the kernel dropped so far."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
    sock.setblocking(False)
    sock.bind((host, port))
    return sock


def receive(sock: socket.socket, into: memoryview, realtime_offset: float) -> tuple | None:
    """One datagram from the non-blocking socket into `into` (one byte past the size limit: a longer datagram fills
    it): (bytes, sender, arrived, taken s on time.perf_counter's clock, the kernel's drops so far or None); None when
    none waits. realtime_offset: time.time() - time.perf_counter(), s (the kernel stamps on CLOCK_REALTIME)."""
    while True:
        try:
            n, ancillary, _, addr = sock.recvmsg_into((into,), _ANCILLARY)
            break
        except (BlockingIOError, InterruptedError):
            return None
        except OSError:  # an ICMP error queued on the socket (a client gone): nothing to take
            continue
    taken = arrived = time.perf_counter()
    drops = None
    for level, kind, value in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            s, ns = _TIMESPEC.unpack_from(value)
            arrived = min(s + ns * 1e-9 - realtime_offset, taken)
        elif level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL:
            drops = _DROPS.unpack_from(value)[0]
    return n, addr, arrived, taken, drops


def drain(sock: socket.socket, into: memoryview, counts: dict, dropped: str, handle) -> None:
    """Take what waits on the non-blocking socket, at most DRAIN_MAX datagrams, each into `into` and handed to
    handle(bytes, sender, arrived, taken) (`receive`'s); counts[dropped]: the kernel's drops since the socket was
    made."""
    realtime_offset = time.time() - time.perf_counter()
    for _ in range(DRAIN_MAX):
        got = receive(sock, into, realtime_offset)
        if got is None:
            return
        n, addr, arrived, taken, drops = got
        if drops is not None:
            counts[dropped] = drops
        handle(n, addr, arrived, taken)


class ErrorReports:
    """A datagram stream's errors, let through at most once per ERROR_INTERVAL per code, with the count since the
    last one let through: a flood cannot make the service send more messages than it receives."""

    def __init__(self):
        self._reported: dict[str, float] = {}
        self._unreported: collections.Counter = collections.Counter()

    def due(self, code: str, count: int = 1) -> int:
        """count more errors of `code`; how many to report now (0: none yet)."""
        self._unreported[code] += count
        now = time.monotonic()
        if now - self._reported.get(code, -math.inf) < ERROR_INTERVAL:
            return 0
        self._reported[code] = now
        return self._unreported.pop(code)
