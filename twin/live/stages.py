"""Where a live sample's time goes: its path stamped stage by stage, kept for `status`.

Every stamp of a path is `time.perf_counter()` (s). On Linux that is CLOCK_MONOTONIC, one clock for every
process on the machine, so the worker's stamps and the service's can be subtracted. A pose's CPU is stamped
too (`time.thread_time()`, ~2 us a call: three per pose, two per frame estimates, none per pen, whose whole work is
~15 us).
"""

from __future__ import annotations

import collections

import numpy as np

LATENCY_WINDOW = 2000  # samples kept per stage for `status` (the most recent)
POSE_STAGES = ("socket", "parse", "wait", "approximate", "encode", "send", "total")
"""A pose's path, all in the worker (twin/live/poses.py): in the worker's socket (the kernel's arrival stamp ->
taken off it: the worker busy, or waiting for a core), parsed and checked, waiting for the rate limit or the pose
before it, the approximation, the reply datagram built, sent (the `sendto` call: on loopback it delivers the
datagram and wakes the client, which often runs before the worker gets its core back, so this stage's tail is
mostly after the client has its reply: docs/live.md, "Measured"). (Its frame estimates follow, off this path: the
service's `estimates_ms`.)"""
POSE_CPU_STAGES = ("approximate", "send", "total")
"""A pose's CPU time in the worker (time.thread_time: on a core, not waiting for one), from the start of its answer:
the pose's matrix and the approximation, the reply built and sent. (Its frame estimates' CPU: `estimates_cpu_ms`.)"""
PEN_STAGES = ("socket", "check", "redirect", "send", "total")
"""A pen sample's path, all in the pen process (twin/live/pens.py): in the service's socket (the kernel's arrival
stamp -> taken off it: the pen process's wake-up, or it busy with the pens before), checked (the datagram, the session,
the sequence number), redirected and its reply encoded (with the thresholds' verdict), sent."""


class StageTimes:
    """The last `window` samples' durations per stage, from stamps taken along their path."""

    def __init__(self, stages: tuple[str, ...], window: int):
        self.stages = stages
        self._times = {name: collections.deque(maxlen=window) for name in stages}

    def record(self, stamps) -> None:
        """stamps: len(stages) times, s: the arrival, then the end of each stage but the last ("total")."""
        for name, start, end in zip(self.stages, stamps, stamps[1:]):
            self._times[name].append(end - start)
        self._times["total"].append(stamps[-1] - stamps[0])

    def total(self) -> collections.deque:
        return self._times["total"]

    def summary(self) -> dict:
        """{stage: {"p50", "p99"} ms, or None before any sample}."""
        return {name: percentiles_ms(values) for name, values in self._times.items()}


def percentiles_ms(values) -> dict | None:
    """{"p50", "p99"} of durations in s, as ms (3 decimals); None for no values."""
    if not values:
        return None
    p50, p99 = np.percentile(np.fromiter(values, float), [50, 99]) * 1e3
    return {"p50": round(float(p50), 3), "p99": round(float(p99), 3)}
