"""Speed of the twin: real-time factor with the C firmware core in the loop, against the numba PID loop it
replaced (kept here only, as the baseline), beside raw physics; and the batch twin's throughput.

    python benchmarks/bench_twin.py [--repeats 20] [--nsim 64] [--threads 2]

Prints medians over repeats, all measured in this one run. Figures are ratios of
simulated to wall time, so they read the same on any machine, but they are
measured, not asserted: shared machines are noisy (the load average is printed).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import mujoco  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

from controllers.encoder import counts_from_motor_angle, target_counts  # noqa: E402
from controllers.pid import PidGains  # noqa: E402
from twin.sim.simulation import Twin, TwinBatch, _mj_step, _mj_step1, _mj_step2  # noqa: E402

MORPH_DEG = [60.0, -45.0, 20.0, 30.0, 90.0, -100.0]  # all six hinges move
DURATION = 2.0  # s


# ---- the baseline: the twin's loop before the C core (numba PID, float64), kept for comparison only ----------

def _baseline_row(g: PidGains, dt: float) -> np.ndarray:
    tau = 1.0 / (2.0 * math.pi * g.derivative_cutoff)
    return np.array([g.kp, g.ki, g.kd, dt / (dt + tau), g.integral_limit, g.deadband_duty, g.hold_band], float)


@numba.njit(cache=False)
def _baseline_pid(target, counts, prev, rate, integral, gains, dt, duty):
    for i in range(target.shape[0]):
        g = gains[i]
        e = target[i] - counts[i]
        rate[i] += g[3] * ((counts[i] - prev[i]) / dt - rate[i])
        prev[i] = counts[i]
        on_target = abs(e) <= g[6]
        u_free = g[0] * e + integral[i] - g[2] * rate[i]
        if not on_target and not (abs(u_free) >= 1.0 and u_free * e > 0):
            integral[i] = min(max(integral[i] + g[1] * e * dt, -g[4]), g[4])
        u = g[0] * e + integral[i] - g[2] * rate[i]
        if not on_target and u != 0.0:
            u = math.copysign(g[5] + (1.0 - g[5]) * abs(u), u)
        duty[i] = min(max(u, -1.0), 1.0)


@numba.njit(cache=False)
def _baseline_loop(m, d, substeps, sensordata, qpos, qvel, ctrl, qfrc, enc_adr, qadr, dadr, cpr_motor, cap,
                   back_emf, resistance, target, prev, rate, integral, gains, dt, max_ticks, settle_band, hold_ticks,
                   stop_when_settled, rec_angle, rec_counts, rec_duty, rec_current, rec_torque):
    n = target.shape[0]
    counts = np.zeros(n, np.int64)
    duty = np.zeros(n)
    in_band = 0
    for i in range(max_ticks):
        _mj_step1(m, d)
        settled = True
        for h in range(n):
            counts[h] = counts_from_motor_angle(sensordata[enc_adr[h]], cpr_motor)
            if abs(target[h] - counts[h]) > settle_band:
                settled = False
        _baseline_pid(target, counts, prev, rate, integral, gains, dt, duty)
        for h in range(n):
            v = duty[h] * cap
            ctrl[h] = v
            rec_angle[i, h] = qpos[qadr[h]]
            rec_counts[i, h] = counts[h]
            rec_duty[i, h] = duty[h]
            rec_current[i, h] = (v - back_emf * qvel[dadr[h]]) / resistance
        _mj_step2(m, d)
        for h in range(n):
            rec_torque[i, h] = qfrc[dadr[h]]
        for _ in range(substeps - 1):
            _mj_step(m, d)
        in_band = in_band + 1 if settled else 0
        if stop_when_settled and in_band >= hold_ticks:
            return i + 1
    return max_ticks


def baseline_wall(twin: Twin, targets, ticks: int) -> float:
    """Wall time (s) of the numba-PID loop for `ticks` ticks from flat, on the twin's model."""
    s, m, d, h = twin.spec, twin.model, mujoco.MjData(twin.model), twin.hinges
    mujoco.mj_resetDataKeyframe(m, d, m.key("flat").id)
    mujoco.mj_forward(m, d)
    n = s.n_hinges
    gains = np.stack([_baseline_row(PidGains.from_spec(s), s.firmware_dt)] * n)
    rec = [np.zeros((ticks, n)), np.zeros((ticks, n), np.int64)] + [np.zeros((ticks, n)) for _ in range(3)]
    prev = np.zeros(n, np.int64)
    start = time.perf_counter()
    _baseline_loop(m._address, d._address, twin.substeps, d.sensordata, d.qpos, d.qvel, d.ctrl, d.qfrc_actuator,
                   h.enc, h.qadr, h.dadr, float(s.counts_per_motor_rev), s.drive_cap, s.motor_constant * s.gear_ratio,
                   s.resistance, target_counts(s, targets), prev, np.zeros(n), np.zeros(n), gains, s.firmware_dt,
                   ticks, s.settle_band, int(round(s.settle_hold / s.firmware_dt)), False, *rec)
    return time.perf_counter() - start


@numba.njit
def _open_loop(m, d, ctrl_buf, ctrl):
    """The twin loop's physics alone: the same compiled mj_step calls, controls replayed."""
    for i in range(ctrl.shape[0]):
        ctrl_buf[:] = ctrl[i]
        _mj_step(m, d)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--nsim", type=int, default=64)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    targets = np.radians(MORPH_DEG)
    print(f"load average at start: {os.getloadavg()[0]:.2f}")

    twin = Twin()
    ticks = int(round(DURATION / twin.spec.firmware_dt))
    baseline_wall(twin, targets, 10)  # compile
    c_walls, numba_walls, traces = [], [], []
    for _ in range(args.repeats):  # interleaved, so both see the same machine
        twin.reset()
        trace = twin.move_to(targets, max_time=DURATION, stop_when_settled=False)
        c_walls.append(trace.wall_time)
        traces.append(trace)
        numba_walls.append(baseline_wall(twin, targets, ticks))
    c_loop, numba_loop = statistics.median(c_walls), statistics.median(numba_walls)

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
    print(f"  C firmware core (vrs_tick) in the loop: {c_loop * 1e3:.2f} ms wall -> "
          f"{DURATION / c_loop:.0f}x real time")
    print(f"  baseline, the numba PID loop it replaced: {numba_loop * 1e3:.2f} ms wall -> "
          f"{DURATION / numba_loop:.0f}x real time (goal: C no slower)")
    print(f"  raw mj_step, same model and controls, no controller: {phys / steps * 1e6:.2f} us/step "
          f"-> {steps / phys:.0f} steps/s, {DURATION / phys:.0f}x real time")
    print(f"  controller loop overhead / physics: C {(c_loop - phys) / phys:.2f}, "
          f"numba baseline {(numba_loop - phys) / phys:.2f}")

    batch = TwinBatch(args.nsim, nthread=args.threads)
    walls = []
    for _ in range(max(3, args.repeats // 5)):
        batch.reset()
        out = batch.run(targets, DURATION)
        walls.append(out["wall_time"])
    bw = statistics.median(walls)
    # the same batch's physics alone: the recorded drive voltages replayed, no cores
    volts = out["duty"] * batch.spec.drive_cap
    vel = mujoco.mjtStage.mjSTAGE_VEL.value
    phys_walls = []
    for _ in range(max(3, args.repeats // 5)):
        batch.reset()
        start = time.perf_counter()
        for i in range(len(volts)):
            batch.ctrl[:] = volts[i]
            batch.batch.step(nstep=batch.substeps, stage=vel)
        phys_walls.append(time.perf_counter() - start)
    bp = statistics.median(phys_walls)
    print(f"batch: {args.nsim} simulations x {DURATION} s on {args.threads} threads, one C core each: {bw:.3f} s "
          f"wall -> {args.nsim * DURATION / bw:.0f} simulated s per wall s (goal >= 400)")
    print(f"  the same batch's physics alone (voltages replayed): {bp:.3f} s wall -> "
          f"{args.nsim * DURATION / bp:.0f} simulated s per wall s; cores and records add {(bw - bp) / bp:.2f}")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
