"""The twin: VRScroll's MuJoCo plant with the firmware's PID in the loop at the firmware rate.

`Twin` is one simulation; its inner loop (read encoders, PID, drive voltage,
physics step) is compiled with numba and calls MuJoCo's C API directly
(mj_step1 / mj_step2 through ctypes), so the controller costs little beside the
physics. `TwinBatch` runs many simulations in lockstep on MuJoCo's own `Batch`
thread pool, with the same PID kernel vectorised over all of them.
"""

from __future__ import annotations

import csv
import ctypes
import dataclasses
import math
import os
import time
from pathlib import Path

import mujoco
from mujoco.batch import Batch
import numba
import numpy as np

from controllers.encoder import counts_from_angle, target_counts
from controllers.pid import FirmwarePid, PidGains, gains_table, pid_update
from twin.device.mjcf import load_model
from twin.device.spec import DeviceSpec, load_spec


class TargetError(ValueError):
    """A hinge target the device cannot reach; names the hinge and the limit."""


def check_targets(spec: DeviceSpec, targets) -> np.ndarray:
    """Hinge targets as a float array (rad), or TargetError: never clipped in silence."""
    targets = np.asarray(targets, dtype=float)
    if targets.shape != (spec.n_hinges,):
        raise TargetError(f"expected {spec.n_hinges} hinge targets, got {targets.size}")
    lim = spec.hinge_limit
    for k, a in enumerate(targets):
        if not math.isfinite(a):
            raise TargetError(f"hinge {k}: target {a} is not a number")
        if abs(a) > lim + 1e-12:
            raise TargetError(
                f"hinge {k}: target {math.degrees(a):.2f} deg is outside the hinge range "
                f"+-{math.degrees(lim):.1f} deg"
            )
    return targets


@dataclasses.dataclass
class Trace:
    """A recorded run at the firmware rate; arrays are (ticks, hinges), SI units."""

    time: np.ndarray  # s, start of each tick
    target: np.ndarray  # rad
    target_counts: np.ndarray  # counts
    angle: np.ndarray  # rad, true hinge angle
    counts: np.ndarray  # counts, as the firmware read them
    duty: np.ndarray  # [-1, 1]
    current: np.ndarray  # A, winding current
    torque: np.ndarray  # N*m at the output shaft
    wall_time: float = float("nan")  # s the simulation took

    @property
    def duration(self) -> float:
        return float(len(self.time) * (self.time[1] - self.time[0])) if len(self.time) > 1 else 0.0

    @property
    def real_time_factor(self) -> float:
        return self.duration / self.wall_time

    def write_csv(self, path) -> None:
        """One row per tick: time_s, then per hinge k target/angle in deg, counts, duty, current_A, torque_Nm."""
        n = self.angle.shape[1]
        cols = ["target_deg", "angle_deg", "target_counts", "counts", "duty", "current_A", "torque_Nm"]
        data = [np.degrees(self.target), np.degrees(self.angle), self.target_counts, self.counts,
                self.duty, self.current, self.torque]
        header = ["time_s"] + [f"h{k}_{c}" for k in range(n) for c in cols]
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".part")
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            for i in range(len(self.time)):
                row = [f"{self.time[i]:.4f}"]
                for k in range(n):
                    row += [f"{data[0][i, k]:.4f}", f"{data[1][i, k]:.4f}", int(data[2][i, k]), int(data[3][i, k]),
                            f"{data[4][i, k]:.4f}", f"{data[5][i, k]:.4f}", f"{data[6][i, k]:.5f}"]
                w.writerow(row)
        os.replace(tmp, path)


# MuJoCo's C API, for the compiled loop (the bindings load this same library)
_LIB = ctypes.CDLL(os.path.join(os.path.dirname(mujoco.__file__), f"libmujoco.so.{mujoco.__version__}"))
_mj_step1, _mj_step2, _mj_step = _LIB.mj_step1, _LIB.mj_step2, _LIB.mj_step
for _fn in (_mj_step1, _mj_step2, _mj_step):
    _fn.argtypes, _fn.restype = [ctypes.c_void_p, ctypes.c_void_p], None


# not cacheable (it calls MuJoCo through ctypes pointers): compiled once per process, in Twin()
@numba.njit(cache=False)
def _firmware_loop(m, d, substeps, sensordata, qpos, qvel, ctrl, qfrc, enc_adr, qadr, dadr, cpr_motor, cap,
                   back_emf, resistance, target, prev, rate, integral, gains, dt, max_ticks, settle_band,
                   hold_ticks, stop_when_settled, rec_angle, rec_counts, rec_duty, rec_current, rec_torque):
    """Run firmware ticks until settled (if asked) or max_ticks; returns the ticks run."""
    n = target.shape[0]
    counts = np.zeros(n, np.int64)
    duty = np.zeros(n)
    in_band = 0
    for i in range(max_ticks):
        _mj_step1(m, d)  # positions, velocities and sensors at the start of the tick
        settled = True
        for h in range(n):
            counts[h] = int(math.floor(sensordata[enc_adr[h]] * cpr_motor / (2.0 * math.pi)))
            if abs(target[h] - counts[h]) > settle_band:
                settled = False
        pid_update(target, counts, prev, rate, integral, gains, dt, duty)
        for h in range(n):
            v = duty[h] * cap
            ctrl[h] = v
            w = qvel[dadr[h]]
            rec_angle[i, h] = qpos[qadr[h]]
            rec_counts[i, h] = counts[h]
            rec_duty[i, h] = duty[h]
            rec_current[i, h] = (v - back_emf * w) / resistance
        _mj_step2(m, d)
        for h in range(n):
            rec_torque[i, h] = qfrc[dadr[h]]
        for _ in range(substeps - 1):  # finer physics than the firmware, duty held
            _mj_step(m, d)
        in_band = in_band + 1 if settled else 0
        if stop_when_settled and in_band >= hold_ticks:
            return i + 1
    return max_ticks


def physics_substeps(spec: DeviceSpec, model: mujoco.MjModel) -> int:
    """Physics steps per firmware tick (the duty is held between them): the one rule every runner uses."""
    return max(1, round(spec.firmware_dt / model.opt.timestep))


class _Hinges:
    """Addresses of each hinge's joint, dof, actuator and encoder in a compiled model."""

    def __init__(self, model: mujoco.MjModel, n: int):
        self.qadr = np.array([model.joint(f"hinge{k}").qposadr[0] for k in range(n)], np.int64)
        self.dadr = np.array([model.joint(f"hinge{k}").dofadr[0] for k in range(n)], np.int64)
        self.enc = np.array([model.sensor(f"encoder{k}").adr[0] for k in range(n)], np.int64)
        act = [model.actuator(f"motor{k}").id for k in range(n)]
        if act != list(range(n)):
            raise ValueError("actuators must be declared in hinge order")


class Twin:
    """One simulated VRScroll with its firmware in the loop.

    The root flap is held by a hand: fixed in the world at `root_pose`
    (root='fixed'), or free to move (root='free'). The firmware keeps its state
    between moves, as the device's does.
    """

    def __init__(self, spec: DeviceSpec | None = None, gains=None, root: str = "fixed",
                 model: mujoco.MjModel | None = None):
        self.spec = spec or load_spec()
        self.model = model or load_model(self.spec, root)
        self.data = mujoco.MjData(self.model)
        self.root = root
        n = self.spec.n_hinges
        self.hinges = _Hinges(self.model, n)
        self.substeps = physics_substeps(self.spec, self.model)
        self.pid = FirmwarePid(gains or PidGains.from_spec(self.spec), n, self.spec.firmware_dt)
        self._root_body = self.model.body(f"flap{self.spec.root_flap}").id
        self._target = np.zeros(n, np.int64)
        self.reset()
        self._run(np.zeros(n), 0.0, False)  # compile the loop now, so moves time only the simulation

    # ---- state ---------------------------------------------------------------
    def reset(self, angles=None) -> None:
        """Back to the `flat` keyframe (or given hinge angles, rad), firmware state cleared."""
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("flat").id)
        if angles is not None:
            self.data.qpos[self.hinges.qadr] = check_targets(self.spec, angles)
        mujoco.mj_forward(self.model, self.data)
        self.pid.reset(self.counts)
        self._target[:] = self.counts

    def set_root_pose(self, position, quat=(1.0, 0.0, 0.0, 0.0)) -> None:
        """Place the root flap's anchor at position (m) with orientation quat (w, x, y, z)."""
        if self.root == "free":
            self.data.qpos[:3], self.data.qpos[3:7] = position, quat
        else:
            self.model.body_pos[self._root_body], self.model.body_quat[self._root_body] = position, quat
        mujoco.mj_forward(self.model, self.data)

    @property
    def angles(self) -> np.ndarray:
        """True hinge angles, rad."""
        return self.data.qpos[self.hinges.qadr].copy()

    @property
    def counts(self) -> np.ndarray:
        """Encoder counts, as the firmware reads them."""
        return counts_from_angle(self.spec, self.data.sensordata[self.hinges.enc] / self.spec.gear_ratio)

    @property
    def time(self) -> float:
        return float(self.data.time)

    # ---- running -------------------------------------------------------------
    def move_to(self, targets, max_time: float = 3.0, stop_when_settled: bool = True) -> Trace:
        """Command hinge targets (rad) and run the firmware until all settle or max_time (s) passes.

        Raises TargetError, before anything moves, for a target outside the hinge range.
        """
        targets = check_targets(self.spec, targets)
        self._target[:] = target_counts(self.spec, targets)
        return self._run(targets, max_time, stop_when_settled)

    def hold(self, duration: float) -> Trace:
        """Keep the present targets for `duration` seconds."""
        return self._run(self._target * self.spec.rad_per_count, duration, False)

    def _run(self, targets, max_time, stop_when_settled) -> Trace:
        s, m, d, h = self.spec, self.model, self.data, self.hinges
        ticks = int(round(max_time / s.firmware_dt))
        n = s.n_hinges
        rec = [np.zeros((ticks, n)), np.zeros((ticks, n), np.int64)] + [np.zeros((ticks, n)) for _ in range(3)]
        t0 = d.time
        start = time.perf_counter()
        done = _firmware_loop(
            m._address, d._address, self.substeps, d.sensordata, d.qpos, d.qvel, d.ctrl, d.qfrc_actuator,
            h.enc, h.qadr, h.dadr, float(s.counts_per_motor_rev), s.drive_cap,
            s.motor_constant * s.gear_ratio, s.resistance, self._target, self.pid.prev, self.pid.rate,
            self.pid.integral, self.pid.gains, s.firmware_dt, ticks, s.settle_band,
            int(round(s.settle_hold / s.firmware_dt)), stop_when_settled, *rec)
        wall = time.perf_counter() - start
        angle, counts, duty, current, torque = (r[:done] for r in rec)
        return Trace(
            time=t0 + np.arange(done) * s.firmware_dt,
            target=np.tile(targets, (done, 1)),
            target_counts=np.tile(self._target, (done, 1)),
            angle=angle, counts=counts, duty=duty, current=current, torque=torque, wall_time=wall,
        )


class TwinBatch:
    """nsim twins in lockstep on MuJoCo's `Batch` thread pool, the firmware PID vectorised over all.

    specs: one plant spec per simulation (e.g. perturbed friction or motor
    constant for robust tuning); they must share the device's layout. gains: one
    PidGains for all, or a (nsim, n_hinges, 7) table of kernel rows.
    """

    def __init__(self, nsim: int, spec: DeviceSpec | None = None, gains=None, specs=None, nthread: int = 0):
        self.spec = spec or load_spec()
        self.nsim = nsim
        n = self.spec.n_hinges
        model = load_model(self.spec)
        self.batch = Batch(model, nsim, nthread=nthread, persistent=True)
        self._models = None
        if specs is not None:
            if len(specs) != nsim:
                raise ValueError(f"expected {nsim} plant specs, got {len(specs)}")
            self._models = [load_model(p) for p in specs]
            self.batch.set_models(self._models)
        self.hinges = _Hinges(model, n)
        self.substeps = physics_substeps(self.spec, model)
        self.sensordata = self.batch.bind("sensordata")
        self.qpos = self.batch.bind("qpos")
        self.qvel = self.batch.bind("qvel")
        self.ctrl = self.batch.bind("ctrl")
        self.qfrc = self.batch.bind("qfrc_actuator")
        self.set_gains(gains or PidGains.from_spec(self.spec))
        self.reset()

    def set_gains(self, gains) -> None:
        n = self.spec.n_hinges
        if isinstance(gains, PidGains):
            self.gains = np.tile(gains_table(gains, n, self.spec.firmware_dt), (self.nsim, 1))
        else:
            self.gains = np.ascontiguousarray(np.reshape(gains, (self.nsim * n, 7)), dtype=float)

    def reset(self, angles=None) -> None:
        """All simulations back to flat (or to angles, rad, shape (nsim, n_hinges))."""
        self.batch.reset(keyframe=0, stage=mujoco.mjtStage.mjSTAGE_NONE.value)
        if angles is not None:
            self.qpos[:, self.hinges.qadr] = angles
        self.batch.forward()
        counts = self._counts().ravel()
        self.prev = counts.copy()
        self.rate = np.zeros(counts.shape)
        self.integral = np.zeros(counts.shape)

    def _counts(self) -> np.ndarray:
        motor = self.sensordata[:, self.hinges.enc]
        return np.floor(motor * self.spec.counts_per_motor_rev / (2 * np.pi)).astype(np.int64)

    def run(self, targets, duration: float) -> dict:
        """Run every simulation to its targets (rad, (nsim, n_hinges)) for `duration` s.

        Returns arrays (ticks, nsim, n_hinges): 'angle' (rad), 'counts', 'duty',
        'current' (A); 'time' (s), 'wall_time' (s).
        """
        s = self.spec
        n = s.n_hinges
        targets = np.broadcast_to(np.asarray(targets, float), (self.nsim, n))
        for row in targets:
            check_targets(s, row)
        tgt = target_counts(s, targets).ravel()
        ticks = int(round(duration / s.firmware_dt))
        out = {k: np.zeros((ticks, self.nsim, n)) for k in ("angle", "duty", "current")}
        out["counts"] = np.zeros((ticks, self.nsim, n), np.int64)
        duty = np.zeros(self.nsim * n)
        back_emf = s.motor_constant * s.gear_ratio
        vel_stage = mujoco.mjtStage.mjSTAGE_VEL.value
        start = time.perf_counter()
        for i in range(ticks):
            counts = self._counts()
            pid_update(tgt, counts.ravel(), self.prev, self.rate, self.integral, self.gains, s.firmware_dt, duty)
            volts = duty.reshape(self.nsim, n) * s.drive_cap
            self.ctrl[:] = volts
            out["angle"][i] = self.qpos[:, self.hinges.qadr]
            out["counts"][i] = counts
            out["duty"][i] = volts / s.drive_cap
            out["current"][i] = (volts - back_emf * self.qvel[:, self.hinges.dadr]) / s.resistance
            self.batch.step(nstep=self.substeps, stage=vel_stage)
        out["wall_time"] = time.perf_counter() - start
        out["time"] = np.arange(ticks) * s.firmware_dt
        return out


def hinge_metrics(spec: DeviceSpec, time_s, target_counts: float, counts, target: float, angle):
    """One hinge's step from time_s[0]: (metrics in counts, settle band in counts; metrics in rad).

    The one definition of settle time (from the counts, the firmware's settle
    band) and overshoot (from the true angle) that reports and the tuner share.
    """
    from twin.sim.response import step_metrics

    return (step_metrics(time_s, counts, target_counts, spec.settle_band, tail=spec.settle_hold),
            step_metrics(time_s, angle, target, spec.settle_band * spec.rad_per_count, tail=spec.settle_hold))


def move_report(spec: DeviceSpec, trace: Trace) -> list[dict]:
    """Per hinge: settle time (s), overshoot (deg), steady-state error (deg and counts), peak current (A).

    Settling uses the firmware's settle band in encoder counts; the step starts
    at the trace's first tick.
    """
    rows = []
    for k in range(trace.angle.shape[1]):
        in_counts, in_angle = hinge_metrics(spec, trace.time, float(trace.target_counts[0, k]), trace.counts[:, k],
                                            float(trace.target[0, k]), trace.angle[:, k])
        rows.append({
            "hinge": k,
            "target_deg": round(math.degrees(trace.target[0, k]), 3),
            "final_deg": round(math.degrees(trace.angle[-1, k]), 3),
            "settle_time_s": round(in_counts.settle_time, 4),
            "overshoot_deg": round(math.degrees(in_angle.overshoot), 3),
            "steady_state_error_deg": round(math.degrees(in_angle.steady_state_error), 3),
            "steady_state_error_counts": round(in_counts.steady_state_error, 2),
            "peak_current_A": round(float(np.max(np.abs(trace.current[:, k]))), 3),
        })
    return rows
