"""The pose stream, taken by the approximation worker straight off its own socket (the welcome's `pose_port`).

A pose that came to the service first and was then handed to the worker over a pipe woke two processes
on its way in, each waiting for a core on a loaded machine; taken here, it wakes one. This is the part
of the worker that decides which pose is approximated next:

- each datagram is stamped with its arrival in the kernel (SO_TIMESTAMPNS), so the time it waited in
  the socket (the worker busy, or waiting for a core) is measured too;
- it is parsed and checked as the service checks a pen (`parse_datagram`), then against the session the
  service named (the controlling client's secret) and the stream's newest sequence number;
- the newest valid pose is kept (memory: one pose) and goes when the rate limit lets it (a token bucket:
  at most APPROXIMATION_RATE_HZ on average, RATE_BURST back to back);
- datagrams the kernel dropped (the socket's buffer full, in a flood) are counted too (SO_RXQ_OVFL);
- errors are counted, and reported (to the service, which tells the controlling client) at most once per
  ERROR_INTERVAL per code, with the count since the last report, and only for datagrams from where the
  controller's valid poses come from.
"""

from __future__ import annotations

import collections
import hmac
import math
import socket
import struct
import time

from twin.live.messages import APPROXIMATION_RATE_HZ, ERROR_INTERVAL, MAX_DATAGRAM_BYTES, ProtocolError, parse_datagram

RATE_BURST = 2.0  # approximations the rate limit lets through back to back (poses at 90 Hz jitter)
DRAIN_MAX = 256  # datagrams taken off the socket in one go: a flood cannot keep the pipe's requests waiting
# Linux's socket options (asm-generic/socket.h; Python names neither), each in a datagram's ancillary data:
SO_TIMESTAMPNS = 35  # its arrival time in the kernel (CLOCK_REALTIME, a struct timespec)
SO_RXQ_OVFL = 40  # how many datagrams the kernel has dropped on this socket so far (its buffer full: a flood)
_TIMESPEC = struct.Struct("@qq")  # s, ns
_DROPS = struct.Struct("@I")
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size) + socket.CMSG_SPACE(_DROPS.size)


class PoseIntake:
    """The controller's pose stream: which pose goes next, counts, and the errors to report."""

    def __init__(self, rate_hz: float = APPROXIMATION_RATE_HZ, burst: float = RATE_BURST):
        self.rate_hz, self.burst = rate_hz, burst
        self.session: bytes | None = None  # the controller's secret; None: no controller, every pose dropped
        self.last_seq = -1
        self.addr = None  # where the controller's valid poses come from
        self.pending = None  # (Sample, addr, arrived, taken, parsed s): the newest pose not yet approximated
        self.tokens, self.filled = burst, time.perf_counter()
        self.counts: collections.Counter = collections.Counter()
        self.reports: list[tuple] = []  # (session, code, message, count) for the service, taken by the worker
        self._reported: dict[str, float] = {}
        self._unreported: collections.Counter = collections.Counter()

    def set_session(self, session: str | None) -> None:
        """A new controller (its secret), or none: the stream starts again."""
        self.session = None if session is None else session.encode()
        self.last_seq, self.addr, self.pending = -1, None, None

    def take(self, data: bytes, addr, arrived: float, taken: float) -> None:
        """One datagram from addr that reached the socket at `arrived` and was taken off it at `taken`
        (perf_counter s)."""
        self.counts["pose_datagrams"] += 1
        try:
            sample = parse_datagram(data, "pose")
        except ProtocolError as exc:
            self.counts[exc.code] += 1
            if addr == self.addr:
                self.report(exc.code, str(exc))
            return
        if self.session is None or not hmac.compare_digest(sample.session.encode(), self.session):
            self.counts["unknown_session"] += 1
            return
        self.addr = addr
        if sample.seq <= self.last_seq:
            self.counts["stale"] += 1
            self.report("stale", f"pose seq {sample.seq} after {self.last_seq}: dropped (the newest wins)")
            return
        if self.last_seq >= 0:
            self.counts["missing"] += sample.seq - self.last_seq - 1
        self.last_seq = sample.seq
        self.counts["pose"] += 1
        if self.pending is not None:
            self.counts["superseded"] += 1
        self.pending = (sample, addr, arrived, taken, time.perf_counter())

    def drain(self, sock: socket.socket) -> None:
        """Take what waits on the (non-blocking) socket, at most DRAIN_MAX datagrams."""
        realtime_offset = time.time() - time.perf_counter()  # CLOCK_REALTIME -> perf_counter s
        for _ in range(DRAIN_MAX):
            try:
                data, ancillary, _, addr = sock.recvmsg(MAX_DATAGRAM_BYTES + 1, _ANCILLARY)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # an ICMP error queued on the socket (a client gone): nothing to take
                continue
            taken = arrived = time.perf_counter()
            for level, kind, value in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    s, ns = _TIMESPEC.unpack_from(value)
                    arrived = min(s + ns * 1e-9 - realtime_offset, taken)
                elif level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL:
                    self.counts["pose_dropped"] = _DROPS.unpack_from(value)[0]  # since the socket was made
            self.take(data, addr, arrived, taken)

    def wait_s(self, now: float) -> float | None:
        """s until the pending pose may go (0: now); None when no pose is pending."""
        if self.pending is None:
            return None
        tokens = min(self.burst, self.tokens + (now - self.filled) * self.rate_hz)
        return max(0.0, (1.0 - tokens) / self.rate_hz)

    def next(self, now: float) -> tuple | None:
        """The pending pose (Sample, addr, arrived, taken, parsed) if the rate limit lets it go now (a token spent)."""
        self.tokens, self.filled = min(self.burst, self.tokens + (now - self.filled) * self.rate_hz), now
        if self.pending is None or self.tokens < 1.0:
            return None
        self.tokens -= 1.0
        pose, self.pending = self.pending, None
        return pose

    def drop_pending(self, code: str, message: str) -> None:
        """The pending pose cannot be approximated (no target yet): dropped, its sender told."""
        if self.pending is not None:
            self.pending = None
            self.report(code, message)

    def report(self, code: str, message: str) -> None:
        """An error for the controlling client, rate-limited per code; the count says how many since the last."""
        self._unreported[code] += 1
        now = time.monotonic()
        if now - self._reported.get(code, -math.inf) >= ERROR_INTERVAL:
            self._reported[code] = now
            session = None if self.session is None else self.session.decode()
            self.reports.append((session, code, message, self._unreported.pop(code)))


def pose_socket(host: str) -> socket.socket:
    """A datagram socket on host (any free port) for the worker's pose stream: non-blocking, each datagram
    stamped with its arrival in the kernel and the count of those the kernel dropped so far."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
    sock.setblocking(False)
    sock.bind((host, 0))
    return sock

