"""Short scheduler slices for the processes on a live sample's way (Linux's EEVDF scheduler, 6.12 and later).

A process woken by a datagram waits for a core while another runs out its slice: 1.4 ms by default on this
2-core machine (`se.slice` in /proc/PID/sched: 0.7 ms times 1 + log2 of the cores), and the approximation worker,
the emulator and everything else running here take theirs. A task may ask for a shorter slice for itself
(`sched_setattr`, `sched_runtime` under SCHED_OTHER: no privilege needed); the kernel then gives it an earlier
deadline, and once woken it preempts a task running a longer slice (the scheduler's PREEMPT_SHORT), while over a
second it still gets only its fair share. The pen process asks for the shortest the kernel takes (0.1 ms) as it
starts (twin/live/pens.py): its work per pen is ~15 us, it is woken 360 times a second, and every wake-up is on a
pen's way. The approximation worker does not: on a short slice its 1-2 ms approximation was cut into 0.1 ms pieces
between which the client's and the emulator's threads ran, and the C# client's pose p99 rose from 2.3-2.6 to
4.2-5.2 ms (pens short in both, the worker's alternating, load ~2).

Measured (docs/live.md, "Measured"): one service, pens at 360 Hz and poses at 90 Hz, short slices on and off in turn
every 5.5 s (benchmarks/bench_live_slices.py), load 1.1-1.3: the pen process's wait for a core per wake-up 52-65 ->
3-8 us, its own path's p99 0.59-0.79 -> 0.29-0.39 ms, the pen's end-to-end p99 1.54-2.16 -> 0.61-1.23 ms.

The Python client may ask the same for the thread that takes its replies (`LiveClient(short_slice=True)`): a reply
wakes it, and it then preempts a task running a longer slice, where on the default slice it waited behind the
approximation, the emulator or another engineer's test (docs/live.md, "The clients' waits").

Elsewhere (another OS, an older kernel, a process under a real-time policy, which needs no slice) nothing is
changed.
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
import threading
from pathlib import Path

SLICE_S = 1e-4  # the shortest slice Linux takes (its range is 0.1-100 ms)
_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}.get(platform.machine())  # the syscall's number
_SCHED_ATTR = struct.Struct("IIQiIQQQ")  # size, policy, flags, nice, priority, runtime ns, deadline, period
_FAIR = (os.SCHED_OTHER, getattr(os, "SCHED_BATCH", 3))


def ask_short_slice(slice_s: float = SLICE_S, pid: int = 0) -> bool:
    """Every thread of process pid (0: this one) asks for a scheduler slice of slice_s under its present policy and
    nice; whether each took it (False where the kernel or the platform has no such request, or the process runs
    under a real-time policy)."""
    if _SCHED_SETATTR is None or not Path("/proc/self/task").is_dir():
        return False
    taken = True
    for task in Path(f"/proc/{pid or 'self'}/task").iterdir():
        taken &= ask_thread_slice(slice_s, int(task.name)) is not False
    return taken


def ask_thread_slice(slice_s: float = SLICE_S, tid: int | None = None) -> bool | None:
    """Thread tid (None: the calling one) asks for a scheduler slice of slice_s under its present policy and nice;
    whether it took it (None: a thread that has ended)."""
    if _SCHED_SETATTR is None or not Path("/proc/self/task").is_dir():
        return False
    tid = threading.get_native_id() if tid is None else tid
    try:
        policy, nice = os.sched_getscheduler(tid), os.getpriority(os.PRIO_PROCESS, tid)
    except OSError:
        return None
    if policy not in _FAIR:
        return False
    attr = ctypes.create_string_buffer(_SCHED_ATTR.pack(_SCHED_ATTR.size, policy, 0, nice, 0, round(slice_s * 1e9),
                                                        0, 0))
    return ctypes.CDLL(None, use_errno=True).syscall(_SCHED_SETATTR, tid, attr, 0) == 0


def slice_s(pid: int = 0) -> float | None:
    """The scheduler slice of process pid's main thread (0: this one), s; None where Linux does not say."""
    try:
        text = Path(f"/proc/{pid or 'self'}/sched").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith("se.slice"):
            return int(line.split()[-1]) / 1e9
    return None
