"""Speed of the twin: real-time factor with the firmware in the loop, raw physics, batch throughput.

    python benchmarks/bench_twin.py [--repeats 20] [--nsim 64] [--threads 2]

Prints medians over repeats. Figures are ratios of simulated to wall time, so
they read the same on any machine, but they are measured, not asserted:
shared machines are noisy.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import mujoco  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

from twin.sim.simulation import Twin, TwinBatch, _mj_step  # noqa: E402

@numba.njit
def _open_loop(m, d, ctrl_buf, ctrl):
    """The twin loop's physics alone: the same compiled mj_step calls, controls replayed."""
    for i in range(ctrl.shape[0]):
        ctrl_buf[:] = ctrl[i]
        _mj_step(m, d)


MORPH_DEG = [60.0, -45.0, 20.0, 30.0, 90.0, -100.0]  # all six hinges move
DURATION = 2.0  # s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--nsim", type=int, default=64)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    targets = np.radians(MORPH_DEG)

    twin = Twin()
    loop_walls, traces = [], []
    for _ in range(args.repeats):
        twin.reset()
        trace = twin.move_to(targets, max_time=DURATION, stop_when_settled=False)
        loop_walls.append(trace.wall_time)
        traces.append(trace)
    loop = statistics.median(loop_walls)

    # the same physics with no controller: replay the recorded drive voltages, open loop
    m, d = twin.model, mujoco.MjData(twin.model)
    ctrl = np.ascontiguousarray(traces[0].duty * twin.spec.drive_cap)
    _open_loop(m._address, d._address, d.ctrl, ctrl[:1])  # compile
    phys_walls = []
    for _ in range(args.repeats):
        mujoco.mj_resetDataKeyframe(m, d, m.key("flat").id)
        start = time.perf_counter()
        _open_loop(m._address, d._address, d.ctrl, ctrl)
        phys_walls.append(time.perf_counter() - start)
    phys = statistics.median(phys_walls)
    steps = len(ctrl)

    print(f"2 s morph of all six hinges, firmware at {twin.spec.loop_rate:.0f} Hz, one core "
          f"(median of {args.repeats}):")
    print(f"  with firmware PID in the loop: {loop * 1e3:.2f} ms wall -> {DURATION / loop:.0f}x real time (goal >= 200x)")
    print(f"  raw mj_step, same model and controls, no controller: {phys / steps * 1e6:.2f} us/step "
          f"-> {steps / phys:.0f} steps/s, {DURATION / phys:.0f}x real time")
    print(f"  controller loop overhead / physics: {(loop - phys) / phys:.2f} (goal < 0.5)")

    batch = TwinBatch(args.nsim, nthread=args.threads)
    walls = []
    for _ in range(max(3, args.repeats // 5)):
        batch.reset()
        out = batch.run(targets, DURATION)
        walls.append(out["wall_time"])
    bw = statistics.median(walls)
    print(f"batch: {args.nsim} simulations x {DURATION} s on {args.threads} threads: {bw:.3f} s wall -> "
          f"{args.nsim * DURATION / bw:.0f} simulated s per wall s (goal >= 400)")


if __name__ == "__main__":
    main()
