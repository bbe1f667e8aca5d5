"""The pose stream, taken by the approximation worker straight off its own socket (the welcome's `pose_port`).

A pose that came to the service first and was then handed to the worker over a pipe woke two processes
on its way in, each waiting for a core on a loaded machine; taken here, it wakes one. This is the part
of the worker that decides which pose is approximated next:

- each datagram is read into one preallocated buffer and stamped with its arrival in the kernel
  (twin/live/datagrams.py), so the time it waited in the socket (the worker busy, or waiting for a core) is
  measured too;
- it is checked as the service checks a pen (`SampleBuffer.check`, compiled), then against the session the
  service named (the controlling client's secret) and the stream's newest sequence number;
- the newest valid pose is kept (memory: one pose, in a preallocated array) and goes when the rate limit lets
  it (a token bucket:
  at most APPROXIMATION_RATE_HZ on average, RATE_BURST back to back);
- datagrams the kernel dropped (the socket's buffer full, in a flood) are counted too (SO_RXQ_OVFL);
- errors are counted, and reported (to the service, which tells the controlling client) at most once per
  ERROR_INTERVAL per code, with the count since the last report, and only for datagrams from where the
  controller's valid poses come from.
"""

from __future__ import annotations

import collections
import hmac
import socket
import time

import numpy as np

from twin.live.datagrams import ErrorReports, drain
from twin.live.messages import APPROXIMATION_RATE_HZ, VALUES, SampleBuffer, sample_error

RATE_BURST = 2.0  # approximations the rate limit lets through back to back (poses at 90 Hz jitter)


class PoseIntake:
    """The controller's pose stream: which pose goes next, counts, and the errors to report."""

    def __init__(self, rate_hz: float = APPROXIMATION_RATE_HZ, burst: float = RATE_BURST):
        self.rate_hz, self.burst = rate_hz, burst
        self.session: bytes | None = None  # the controller's secret; None: no controller, every pose dropped
        self.last_seq = -1
        self.addr = None  # where the controller's valid poses come from
        self.buffer = SampleBuffer()  # each datagram as it is received and checked
        self.pose = np.zeros(VALUES)  # the newest valid pose not yet approximated (SampleBuffer.values' layout)
        self.pending = None  # (addr, arrived, taken, parsed s) of it; None: none pending
        self.tokens, self.filled = burst, time.perf_counter()
        self.counts: collections.Counter = collections.Counter()
        self.reports: list[tuple] = []  # (session, code, message, count) for the service, taken by the worker
        self._due = ErrorReports()

    def set_session(self, session: str | None) -> None:
        """A new controller (its secret), or none: the stream starts again."""
        self.session = None if session is None else bytes.fromhex(session)
        self.last_seq, self.addr, self.pending = -1, None, None

    def take(self, data: bytes, addr, arrived: float, taken: float) -> None:
        """Bytes from addr, as if received (`received`)."""
        self.received(self.buffer.load(data), addr, arrived, taken)

    def received(self, n: int, addr, arrived: float, taken: float) -> None:
        """The n bytes in `buffer` from addr, that reached the socket at `arrived` and were taken off it at `taken`
        (perf_counter s)."""
        self.counts["pose_datagrams"] += 1
        code = self.buffer.check(n, "pose")
        if code:
            exc = sample_error(code, n)
            self.counts[exc.code] += 1
            if addr == self.addr:
                self.report(exc.code, str(exc))
            return
        if self.session is None or not hmac.compare_digest(self.buffer.session, self.session):
            self.counts["unknown_session"] += 1
            return
        self.addr = addr
        seq = int(self.buffer.values[0])
        if seq <= self.last_seq:
            self.counts["stale"] += 1
            self.report("stale", f"pose seq {seq} after {self.last_seq}: dropped (the newest wins)")
            return
        if self.last_seq >= 0:
            self.counts["missing"] += seq - self.last_seq - 1
        self.last_seq = seq
        self.counts["pose"] += 1
        if self.pending is not None:
            self.counts["superseded"] += 1
        self.pose[:] = self.buffer.values
        self.pending = (addr, arrived, taken, time.perf_counter())

    def drain(self, sock: socket.socket) -> None:
        """Take what waits on the (non-blocking) socket, at most DRAIN_MAX datagrams (twin.live.datagrams.drain)."""
        drain(sock, self.buffer.view, self.counts, "pose_dropped", self.received)

    def wait_s(self, now: float) -> float | None:
        """s until the pending pose may go (0: now); None when no pose is pending."""
        if self.pending is None:
            return None
        tokens = min(self.burst, self.tokens + (now - self.filled) * self.rate_hz)
        return max(0.0, (1.0 - tokens) / self.rate_hz)

    def next(self, now: float) -> tuple | None:
        """The pending pose (its values, addr, arrived, taken, parsed) if the rate limit lets it go now (a token
        spent); the values are `pose`'s, until the next datagram is taken."""
        self.tokens, self.filled = min(self.burst, self.tokens + (now - self.filled) * self.rate_hz), now
        if self.pending is None or self.tokens < 1.0:
            return None
        self.tokens -= 1.0
        pending, self.pending = self.pending, None
        return (self.pose, *pending)

    def drop_pending(self, code: str, message: str) -> None:
        """The pending pose cannot be approximated (no target yet): dropped, its sender told."""
        if self.pending is not None:
            self.pending = None
            self.report(code, message)

    def report(self, code: str, message: str) -> None:
        """An error for the controlling client, rate-limited per code; the count says how many since the last."""
        count = self._due.due(code)
        if count:
            self.reports.append((None if self.session is None else self.session.hex(), code, message, count))
