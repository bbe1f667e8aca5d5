"""The sketch in the loop's cost per tick on this host, and how much of it is the peripherals' stand-ins.

One firmware tick of the emulator's firmware, without the plant (the encoders turned by a
fixed pattern, as a moving device turns them):

- core: `Core.run_tick`, the C core alone as the emulator runs it (Python → ctypes);
- sketch: `Sketch.run_tick`, the whole sketch (Python → the encoders' edges, the board's 1 ms
  with its timer interrupt, loop(), vrs_control, vrs_service, the bridges read back);
- in C: `host_advance(1000)` alone (the sketch's tick and its stand-ins, no Python), beside a copy
  of the sketch's own core's `vrs_tick` called directly: their difference is the sketch's glue and
  the stand-ins.

    python benchmarks/bench_sketch.py [--ticks 20000] [--repeats 5]

Medians of the repeats, one run; a ratio, not an assertion (shared machines differ 2x).
"""

from __future__ import annotations

import argparse
import ctypes
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from controllers import core, sketch  # noqa: E402
from controllers.pid import PidGains  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402
from twin.link import protocol as P  # noqa: E402


def per_tick(fn, ticks: int, repeats: int) -> float:
    """Median over repeats of the wall time per call, us."""
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        for i in range(ticks):
            fn(i)
        out.append((time.perf_counter() - t) / ticks * 1e6)
    return float(np.median(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ticks", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    spec = load_spec()
    n = spec.n_hinges
    pattern = (np.sin(np.arange(args.ticks)[:, None] / 200.0 + np.arange(n)) * 150).astype(np.int64)  # +-150 counts

    cfg = core.config_from_spec(spec)
    bare = core.Core(cfg, [PidGains.from_spec(spec)] * n, [0] * n)
    bare.mark_zero_confirmed()
    bare.set_targets([60] * n, 0)
    board = sketch.Sketch(np.zeros(n))
    board.confirm_zero()
    board.rx(P.encode(P.SetTargets((60,) * n), 1))
    heartbeat = P.encode(P.Heartbeat(), 2)

    def core_tick(i):
        bare.run_tick(i * 1000, pattern[i], None, 8000)

    def sketch_tick(i):
        if i % 50 == 0:
            board.rx(heartbeat)
        board.run_tick(0, pattern[i], None, 8000)
        board.tx()

    lib = board.lib

    def advance_tick(i):
        if i % 50 == 0:
            board.rx(heartbeat)  # ACTIVE throughout: the watchdog fed
        lib.host_advance(1000)

    c_core = per_tick(core_tick, args.ticks, args.repeats)
    c_sketch = per_tick(sketch_tick, args.ticks, args.repeats)
    assert board.state == P.State.ACTIVE, P.enum_name(P.State, board.state)
    advance = per_tick(advance_tick, args.ticks, args.repeats)
    assert board.state == P.State.ACTIVE, P.enum_name(P.State, board.state)
    own = ctypes.c_uint8.in_dll(lib, "core")
    counts, duty, decay = np.zeros(8, np.int32), np.zeros(8, np.float32), np.zeros(8, np.uint8)
    tick_fn = lib.vrs_tick
    tick_fn.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                        ctypes.c_void_p]
    scratch = (ctypes.c_uint8 * core.library().vrs_core_size())()
    ctypes.memmove(scratch, ctypes.addressof(own), len(scratch))  # a copy (ACTIVE): the board's own is left alone
    at = ctypes.addressof(scratch)
    c_addr, d_addr, k_addr = counts.ctypes.data, duty.ctypes.data, decay.ctypes.data
    vrs_tick = per_tick(lambda i: tick_fn(at, i * 1000, c_addr, None, d_addr, k_addr), args.ticks, args.repeats)
    empty = per_tick(lambda i: lib.host_now_us(), args.ticks, args.repeats)
    advance -= per_tick(lambda i: i % 50 == 0 and None, args.ticks, args.repeats)  # the loop's own cost
    inside = advance - empty
    core_part = vrs_tick - empty
    print(f"one firmware tick on this host ({os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}), "
          f"median of {args.repeats} x {args.ticks} ticks:")
    print(f"  emulator's firmware, C core alone (Core.run_tick):      {c_core:7.2f} us")
    print(f"  emulator's firmware, whole sketch (Sketch.run_tick):    {c_sketch:7.2f} us  ({c_sketch / c_core:.1f}x)")
    print(f"  in C, an empty ctypes call's {empty:.2f} us taken off: the board's 1 ms (host_advance: timer interrupt, "
          f"loop(), vrs_control through the stand-ins, vrs_service) {inside:.2f} us; the core's vrs_tick alone "
          f"{core_part:.2f} us (six arguments through ctypes); difference {inside - core_part:+.2f} us")
    print("  (the stand-ins' share is the difference; within about 0.1 us it is below what timing through ctypes "
          "resolves. The whole sketch's extra cost per tick is Python's: 12 ctypes calls for encoders and bridges)")


if __name__ == "__main__":
    main()
