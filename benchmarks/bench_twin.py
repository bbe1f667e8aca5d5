"""Speed of the twin: real-time factor with the full drive train (backlash, LuGre friction, pack, drivers,
gearbox efficiency; the C firmware core in the loop) beside the previous model (issue 12's: joint friction,
no backlash, duty x 6 V straight to the motor; kept here only as the baseline) and raw physics in the same
run; where a step's time goes (MuJoCo's per-stage timers, data.timer); the batch twin's throughput.

    python benchmarks/bench_twin.py [--repeats 20] [--nsim 64] [--threads 2]

Prints medians over repeats, all measured in this one run. Figures are ratios of
simulated to wall time, so they read the same on any machine, but they are
measured, not asserted: shared machines are noisy (the load average is printed).
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

from controllers.encoder import counts_from_motor_angle, target_counts  # noqa: E402
from twin.device.mjcf import load_model  # noqa: E402
from twin.sim.simulation import Twin, TwinBatch, _mj_step, _mj_step1, _mj_step2, _vrs_tick, start_core  # noqa: E402

MORPH_DEG = [60.0, -45.0, 20.0, 30.0, 90.0, -100.0]  # all six hinges move
DURATION = 2.0  # s
STAGES = ("POSITION", "VELOCITY", "ACTUATION", "CONSTRAINT", "ADVANCE")  # a step's parts (mjTIMER_*)
POSITION_PARTS = ("POS_KINEMATICS", "POS_INERTIA", "POS_COLLISION", "POS_MAKE", "POS_PROJECT")


# ---- the baseline: issue 12's model and loop, kept for comparison only --------------------------------------

def previous_model(spec) -> mujoco.MjModel:
    """Issue 12's model: the motors on the flaps' joints, Coulomb friction as joint frictionloss (a constraint
    row per hinge), viscous loss as joint damping, the gearbox's loss folded into the motor's resistance."""
    m = load_model(spec.replace(backlash=0.0, friction_stiffness=0.0, gear_damping=0.0))
    loss = (spec.gear_friction + spec.gear_damping * spec.no_load_speed) / spec.stall_torque
    k = spec.rated_voltage * (1.0 - loss) / (spec.no_load_speed * spec.gear_ratio)
    m.actuator_gainprm[:, :2] = [k * spec.rated_voltage * spec.gear_ratio / spec.stall_torque, k]
    m.dof_frictionloss[:] = spec.gear_friction
    m.dof_damping[:] = spec.gear_damping
    return m


@numba.njit(cache=False)
def _previous_loop(m, d, fw, sensordata, qpos, ctrl, enc_adr, qadr, cpr_motor, cap, counts, duty, decay,
                   max_ticks, rec_angle):
    for i in range(max_ticks):
        _mj_step1(m, d)
        for h in range(counts.shape[0]):
            counts[h] = counts_from_motor_angle(sensordata[enc_adr[h]], cpr_motor)
        _vrs_tick(fw, i * 1000, counts.ctypes.data, 0, duty.ctypes.data, decay.ctypes.data)
        for h in range(counts.shape[0]):
            ctrl[h] = duty[h] * cap
            rec_angle[i, h] = qpos[qadr[h]]
        _mj_step2(m, d)
    return max_ticks


def previous_wall(twin: Twin, model: mujoco.MjModel, targets, ticks: int) -> float:
    """Wall time (s) of issue 12's loop on its model for `ticks` ticks from flat."""
    s, h = twin.spec, twin.hinges
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, model.key("flat").id)
    mujoco.mj_forward(model, d)
    n = s.n_hinges
    fw = start_core(s, twin.gains, np.zeros(n, np.int32))
    fw.set_targets(target_counts(s, targets), 0)
    counts, duty, decay = np.zeros(n, np.int32), np.zeros(n, np.float32), np.zeros(n, np.uint8)
    enc = np.array([model.sensor(f"encoder{k}").adr[0] for k in range(n)], np.int64)
    rec = np.zeros((ticks, n))
    start = time.perf_counter()
    _previous_loop(model._address, d._address, fw.address, d.sensordata, d.qpos, d.ctrl, enc, h.qadr,
                   float(s.counts_per_motor_rev), s.drive_cap, counts, duty, decay, ticks, rec)
    return time.perf_counter() - start


def stage_times(model: mujoco.MjModel, ctrl: np.ndarray) -> dict:
    """Mean us per step of each of MuJoCo's stages (data.timer), the recorded drive voltages replayed."""
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, model.key("flat").id)
    mujoco.set_mjcb_time(time.perf_counter)
    try:
        for row in ctrl:
            d.ctrl[:] = row
            mujoco.mj_step(model, d)
    finally:
        mujoco.set_mjcb_time(None)
    out = {}
    for name in ("STEP",) + STAGES + POSITION_PARTS:
        t = d.timer[getattr(mujoco.mjtTimer, f"mjTIMER_{name}")]
        out[name] = t.duration / max(t.number, 1) * 1e6 * t.number / len(ctrl)
    out["nefc"] = int(d.nefc)
    return out


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
    spec = twin.spec
    previous = previous_model(spec)
    ticks = int(round(DURATION / spec.firmware_dt))
    previous_wall(twin, previous, targets, 10)  # compile
    walls, previous_walls, traces = [], [], []
    for _ in range(args.repeats):  # interleaved, so both see the same machine
        twin.reset()
        trace = twin.move_to(targets, max_time=DURATION, stop_when_settled=False)
        walls.append(trace.wall_time)
        traces.append(trace)
        previous_walls.append(previous_wall(twin, previous, targets, ticks))
    full, prev = statistics.median(walls), statistics.median(previous_walls)

    # the same physics with no controller: replay the recorded drive voltages, open loop
    m, d = twin.model, mujoco.MjData(twin.model)
    volts = np.ascontiguousarray(traces[0].duty * spec.drive_cap)  # the firmware's compensated drive, about
    _open_loop(m._address, d._address, d.ctrl, volts[:1])  # compile
    phys_walls = []
    for _ in range(args.repeats):
        mujoco.mj_resetDataKeyframe(m, d, m.key("flat").id)
        start = time.perf_counter()
        _open_loop(m._address, d._address, d.ctrl, volts)
        phys_walls.append(time.perf_counter() - start)
    phys = statistics.median(phys_walls)
    steps = len(volts)

    print(f"2 s morph of all six hinges, firmware at {spec.loop_rate:.0f} Hz, one core (median of {args.repeats}):")
    print(f"  full drive train (backlash, LuGre friction, pack, drivers, efficiency), C core in the loop: "
          f"{full * 1e3:.2f} ms wall -> {DURATION / full:.0f}x real time (goal >= 200x)")
    print(f"  previous model (issue 12: joint friction, no backlash, duty x 6 V), C core in the loop: "
          f"{prev * 1e3:.2f} ms wall -> {DURATION / prev:.0f}x real time")
    print(f"  raw mj_step on the full model, duty x 6 V replayed, no controller or drive model: "
          f"{phys / steps * 1e6:.2f} us/step "
          f"-> {steps / phys:.0f} steps/s, {DURATION / phys:.0f}x real time")
    print(f"  controller and drive model overhead / physics: {(full - phys) / phys:.2f}")
    print("  where a step's time goes (data.timer, us per step, duty x 6 V replayed; the timers' own calls included):")
    for label, model in (("full", m), ("previous", previous)):
        t = stage_times(model, volts)
        parts = ", ".join(f"{k.lower()} {t[k]:.2f}" for k in STAGES)
        inside = ", ".join(f"{k[4:].lower()} {t[k]:.2f}" for k in POSITION_PARTS)
        print(f"    {label:<8} step {t['STEP']:.2f}: {parts} (position: {inside}); constraint rows at the end "
              f"{t['nefc']}")

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
