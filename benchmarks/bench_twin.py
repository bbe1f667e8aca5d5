"""Speed of the twin: real-time factor with the full drive train (backlash, LuGre friction, pack, drivers,
gearbox efficiency; the C firmware core in the loop) beside the previous model (the simple drive model: joint friction,
no backlash, duty x 6 V straight to the motor; kept here only as the baseline) and raw physics in the same
run; where a step's time goes in the closed loop itself (MuJoCo's per-stage timers, data.timer, read
through a C clock, stage_clock.c); the batch twin's throughput.

Raw physics is the closed loop's own trajectory replayed: the drive's voltages and gearbox torques
recorded tick by tick, then stepped with mj_step alone (collision detection on, as MuJoCo steps the
model; and off, as the twin steps it while the flaps are apart); the replay ends where the twin did.

    python benchmarks/bench_twin.py [--repeats 20] [--nsim 64] [--threads 2]

Prints medians over repeats, all measured in this one run. Figures are ratios of
simulated to wall time, so they read the same on any machine, but they are
measured, not asserted: shared machines are noisy (the load average is printed).
"""

from __future__ import annotations

import argparse
import copy
import ctypes
import os
import statistics
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import mujoco  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

from controllers import core  # noqa: E402
from controllers.core import start_core  # noqa: E402
from controllers.encoder import counts_from_motor_angle, target_counts  # noqa: E402
from twin.device.mjcf import load_model  # noqa: E402
from twin.sim.batch import TwinBatch  # noqa: E402
from twin.sim.kernels import mj_step, mj_step1, mj_step2, vrs_tick  # noqa: E402
from twin.sim.twin import Twin  # noqa: E402

MORPH_DEG = [60.0, -45.0, 20.0, 30.0, 90.0, -100.0]  # all six hinges move
DURATION = 2.0  # s
STAGES = ("POSITION", "VELOCITY", "ACTUATION", "CONSTRAINT", "ADVANCE")  # a step's parts (mjTIMER_*)
POSITION_PARTS = ("POS_KINEMATICS", "POS_INERTIA", "POS_COLLISION", "POS_MAKE", "POS_PROJECT")
CLOCK_SOURCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "stage_clock.c")


# ---- the baseline: the simple drive model and loop, kept for comparison only --------------------------------------

def previous_model(spec) -> mujoco.MjModel:
    """The simple drive model: the motors on the flaps' joints, Coulomb friction as joint frictionloss (a constraint
    row per hinge), viscous loss as joint damping, the gearbox's loss folded into the motor's resistance,
    MuJoCo's default solver options."""
    m = load_model(spec.replace(backlash=0.0, friction_stiffness=0.0, gear_damping=0.0))
    loss = (spec.gear_friction + spec.gear_damping * spec.no_load_speed) / spec.stall_torque
    k = spec.rated_voltage * (1.0 - loss) / (spec.no_load_speed * spec.gear_ratio)
    m.actuator_gainprm[:, :2] = [k * spec.rated_voltage * spec.gear_ratio / spec.stall_torque, k]
    m.dof_frictionloss[:] = spec.gear_friction
    m.dof_damping[:] = spec.gear_damping
    m.opt.disableflags = 0  # its solver: MuJoCo's defaults (warm start, islands)
    return m


@numba.njit(cache=False)
def _previous_loop(m, d, fw, sensordata, qpos, ctrl, enc_adr, qadr, cpr_motor, cap, counts, duty, decay,
                   max_ticks, rec_angle):
    for i in range(max_ticks):
        mj_step1(m, d)
        for h in range(counts.shape[0]):
            counts[h] = counts_from_motor_angle(sensordata[enc_adr[h]], cpr_motor)
        vrs_tick(fw, i * 1000, counts.ctypes.data, 0, duty.ctypes.data, decay.ctypes.data)
        for h in range(counts.shape[0]):
            ctrl[h] = duty[h] * cap
            rec_angle[i, h] = qpos[qadr[h]]
        mj_step2(m, d)
    return max_ticks


def previous_wall(twin: Twin, model: mujoco.MjModel, targets, ticks: int) -> tuple[float, mujoco.MjData]:
    """Wall time (s) of the simple drive model's loop on its model for `ticks` ticks from flat, and its data after."""
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
    return time.perf_counter() - start, d


def stage_times(run, ticks: int) -> dict:
    """Mean us per tick of each of MuJoCo's stages (data.timer) while run() runs a closed loop of `ticks` ticks
    and returns its MjData; the timers read a C clock (their own calls are included)."""
    lib = ctypes.CDLL(str(core.build(extra_sources=[CLOCK_SOURCE], name="stage_clock")))
    clock = ctypes.CFUNCTYPE(ctypes.c_double)(("stage_clock", lib))
    mujoco.set_mjcb_time(clock)
    try:
        d = run()
    finally:
        mujoco.set_mjcb_time(None)
    out = {name: d.timer[getattr(mujoco.mjtTimer, f"mjTIMER_{name}")].duration / ticks * 1e6
           for name in ("STEP",) + STAGES + POSITION_PARTS}
    out["nefc"] = int(d.nefc)
    return out


def recorded_drive(twin: Twin, targets, ticks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The twin's closed loop from flat, tick by tick: what its drive gave MuJoCo each tick (ctrl, V;
    qfrc_applied, N*m) and the qpos it ends at."""
    twin.reset()
    ctrl, applied = np.zeros((ticks, twin.model.nu)), np.zeros((ticks, twin.model.nv))
    for i in range(ticks):
        if i == 0:
            twin.move_to(targets, max_time=twin.spec.firmware_dt, stop_when_settled=False)
        else:
            twin.hold(twin.spec.firmware_dt)
        ctrl[i], applied[i] = twin.data.ctrl, twin.data.qfrc_applied
    return ctrl, applied, twin.data.qpos.copy()


@numba.njit
def _open_loop(m, d, ctrl_buf, applied_buf, ctrl, applied):
    """The twin loop's physics alone: the same compiled mj_step calls, the drive's output replayed."""
    for i in range(ctrl.shape[0]):
        ctrl_buf[:] = ctrl[i]
        applied_buf[:] = applied[i]
        mj_step(m, d)


def replay_wall(model: mujoco.MjModel, ctrl, applied, repeats: int) -> tuple[list, np.ndarray]:
    """Wall times (s) of mj_step alone over the recorded drive from flat, one per repeat; the qpos it ends at."""
    d = mujoco.MjData(model)
    walls = []
    for _ in range(repeats):
        mujoco.mj_resetDataKeyframe(model, d, model.key("flat").id)
        mujoco.mj_forward(model, d)
        start = time.perf_counter()
        _open_loop(model._address, d._address, d.ctrl, d.qfrc_applied, ctrl, applied)
        walls.append(time.perf_counter() - start)
    return walls, d.qpos.copy()


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
    walls, previous_walls = [], []
    for _ in range(args.repeats):  # interleaved, so both see the same machine
        twin.reset()
        trace = twin.move_to(targets, max_time=DURATION, stop_when_settled=False)
        walls.append(trace.wall_time)
        previous_walls.append(previous_wall(twin, previous, targets, ticks)[0])
    full, prev = statistics.median(walls), statistics.median(previous_walls)
    best = {"full": min(walls), "previous": min(previous_walls)}

    # the same physics with no controller: the closed loop's own drive replayed, open loop
    ctrl, applied, qpos = recorded_drive(twin, targets, ticks)
    np.testing.assert_array_equal(qpos, twin.data.qpos)  # tick by tick, the same run as above
    m = twin.model
    no_contact = copy.copy(m)
    no_contact.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    scratch = mujoco.MjData(m)
    _open_loop(m._address, scratch._address, scratch.ctrl, scratch.qfrc_applied, ctrl[:1], applied[:1])  # compile
    raw = {}
    for label, model in (("on", m), ("off", no_contact)):
        raw_walls, end = replay_wall(model, ctrl, applied, args.repeats)
        raw[label], best[f"raw mj_step, collision detection {label}"] = statistics.median(raw_walls), min(raw_walls)
        np.testing.assert_array_equal(end, qpos)  # the replay is the closed loop's trajectory, to the bit

    print(f"2 s morph of all six hinges, firmware at {spec.loop_rate:.0f} Hz, one core (median of {args.repeats}):")
    print(f"  full drive train (backlash, LuGre friction, pack, drivers, efficiency), C core in the loop: "
          f"{full * 1e3:.2f} ms wall, {full / ticks * 1e6:.2f} us/tick -> {DURATION / full:.0f}x real time "
          f"(goal >= 200x)")
    print(f"  simple drive model (joint friction, no backlash, duty x 6 V), C core in the loop: "
          f"{prev * 1e3:.2f} ms wall, {prev / ticks * 1e6:.2f} us/tick -> {DURATION / prev:.0f}x real time")
    for label, what in (("on", "collision detection on"), ("off", "collision detection off, as the twin while apart")):
        print(f"  raw mj_step on the full model, the closed loop's drive replayed, {what}: "
              f"{raw[label] / ticks * 1e6:.2f} us/step -> {DURATION / raw[label]:.0f}x real time")
    print(f"  controller, drive model and collision skipping / raw mj_step (collision detection off): "
          f"{(full - raw['off']) / raw['off']:+.2f}")
    print("  best of the repeats (the least disturbed, on a shared machine): " + ", ".join(
        f"{k} {w / ticks * 1e6:.2f} us/tick {DURATION / w:.0f}x" for k, w in best.items()))
    print("  where a tick's time goes in the closed loop (data.timer, us per tick; the timers' own calls included):")

    def run_full():
        twin.reset()
        twin.move_to(targets, max_time=DURATION, stop_when_settled=False)
        return twin.data

    for label, run in (("full", run_full), ("previous", lambda: previous_wall(twin, previous, targets, ticks)[1])):
        t = stage_times(run, ticks)
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
