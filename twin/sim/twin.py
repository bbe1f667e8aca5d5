"""The twin: VRScroll's MuJoCo plant with the device's firmware in the loop at the firmware rate.

The firmware is the device's own C core (controllers/firmware, bound by
controllers.core) built for this host: supervisor and PID, with the watchdog
off (no host talks to the twin). `Twin` is one simulation; its inner loop (read
encoders, the core's `vrs_tick`, drive voltage, physics steps) is compiled with
numba and calls MuJoCo's C API (mj_step1 / mj_step2) and the core through
ctypes. `TwinBatch` runs many simulations in lockstep on MuJoCo's own `Batch`
thread pool, one core per simulation, ticked by a compiled loop over them.
Every runner steps the same physics per tick (`physics_substeps`).

The single twin skips MuJoCo's collision detection for a physics step where no two flaps can touch
(`twin.device.flap_collision.apart` on the hinge angles at the step's start): it steps a copy of the
model with contacts disabled then, the model itself otherwise, so its results are the same to the bit
as with collision detection always on (the batch twin's and the emulator's).
"""

from __future__ import annotations

import copy
import time

import mujoco
import numpy as np

from controllers.core import per_hinge, pid_memory, program_spec, set_core_gains, start_core, tick_us
from controllers.encoder import angle_from_counts, counts_from_motor_angles, target_counts
from controllers.pid import PidGains
from controllers.program import ProgramEnd, ProgramRun, end_name
from twin.device.mjcf import load_model, motor_attributes
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec, load_spec
from twin.records.profile import Profile
from twin.records.trace import Trace
from twin.sim.drive import DECAY_COAST, drive_params
from twin.sim.hinges import Hinges, contact_free_spreads, physics_substeps, place_hinges
from twin.sim.settle import hold_samples
from twin.sim.targets import TargetError, check_targets


class Twin:
    """One simulated VRScroll with its firmware in the loop.

    The root flap is held by a hand: fixed in the world at `root_pose`
    (root='fixed'), or free to move (root='free'). The firmware keeps its state
    between moves, as the device's does; `reset` restarts it. Its supervisor
    checks the hinge limits, and stalls with stall_detection=True.
    """

    def __init__(self, spec: DeviceSpec | None = None, gains=None, root: str = "fixed",
                 model: mujoco.MjModel | None = None, stall_detection: bool = False,
                 hinges: list[DeviceSpec] | None = None, mount: str = DEFAULT_MOUNT):
        """hinges: each hinge's own spec where the device's motors and gearboxes differ (a per-hinge
        calibration's); their plant fields are used, the rest is `spec`'s. mount: how the device is held
        (twin.device.mount.MOUNTS: hanging, flat on a table, on a stand; a given model is taken as it is)."""
        self.spec = spec or load_spec()
        self.mount = mount
        motors = None if hinges is None else [motor_attributes(h) for h in hinges]
        self.model = model or load_model(self.spec, root, mount, motors=motors)
        self.data = mujoco.MjData(self.model)
        self._free_model = copy.copy(self.model)  # the model with contacts disabled, refreshed every run
        self.root = root
        self.stall_detection = stall_detection
        n = self.spec.n_hinges
        self.hinges = Hinges(self.model, n)
        self.substeps = physics_substeps(self.spec, self.model)
        self.gains = per_hinge(gains or PidGains.from_spec(self.spec), n)
        self._root_body = self.model.body(f"flap{self.spec.root_flap}").id
        self._target = np.zeros(n, np.int32)
        self._counts = np.zeros(n, np.int32)  # the core's input and output buffers
        self._duty = np.zeros(n, np.float32)
        self._decay = np.zeros(n, np.uint8)
        self._pwm = np.zeros(n, np.float32)
        self._params = drive_params(self.spec, hinges)
        self._bus = np.zeros(1)  # V: the bus voltage the core reads, from the last tick
        self.reset()
        self._run(np.zeros(n), 0.0, False)  # compile the loop now, so moves time only the simulation

    # ---- state ---------------------------------------------------------------
    def reset(self, angles=None, integral=None, active: bool = True) -> None:
        """Back to the `flat` keyframe (or given hinge angles, rad); the firmware restarted, holding there,
        its PID integral per hinge `integral` (duty, as a device's STATE reports it; default none); with
        active=False IDLE instead (every hinge braked), as a device is before its first targets."""
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("flat").id)
        if angles is not None:
            place_hinges(self.data.qpos, self.hinges, check_targets(self.spec, angles))
        mujoco.mj_forward(self.model, self.data)
        self._bus[0] = self.spec.supply_voltage
        self._target[:] = self.counts
        self.firmware = start_core(self.spec, self.gains, self._target, self.stall_detection, active)
        if integral is not None:
            self.pid.integral[:] = integral
        self._now_us = 0

    def set_gains(self, gains) -> None:
        """New firmware gains (one PidGains, or one per hinge), as SET_GAINS would; the PID memory is kept.

        ValueError naming the hinge for gains outside the firmware's bounds (nothing changes then).
        """
        gains = per_hinge(gains, self.spec.n_hinges)
        start_core(self.spec, gains, self._target)  # a scratch core: refused before anything changes
        set_core_gains(self.firmware, gains)
        self.gains = gains

    @property
    def pid(self) -> np.recarray:
        """The firmware's PID memory per hinge (live): prev (counts), rate (counts/s), integral (duty)."""
        return pid_memory(self.firmware)

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
        return counts_from_motor_angles(self.data.sensordata[self.hinges.enc], self.spec.counts_per_motor_rev)

    @property
    def time(self) -> float:
        return float(self.data.time)

    # ---- running -------------------------------------------------------------
    def move_to(self, targets, max_time: float = 3.0, stop_when_settled: bool = True) -> Trace:
        """Command hinge targets (rad) and run the firmware until all settle or max_time (s) passes.

        Raises TargetError, before anything moves, for a target outside the hinge range or one the
        firmware refuses (it is in FAULT or ESTOP: its state says why).
        """
        targets = check_targets(self.spec, targets)
        counts = target_counts(self.spec, targets)
        refused = self.firmware.set_targets(counts, self._now_us)
        if refused:
            raise TargetError(f"the firmware refused the targets (NACK reason {refused}); its state "
                              f"{self.firmware.state}, faults {self.firmware.faults:#x}, hinge "
                              f"{self.firmware.fault_hinge}")
        self._target[:] = counts
        return self._run(targets, max_time, stop_when_settled)

    def hold(self, duration: float) -> Trace:
        """Keep the present targets for `duration` seconds."""
        return self._run(self._target * self.spec.rad_per_count, duration, False)

    def run_program(self, hinge: int, segments, window_counts, timeout_s: float | None = None, angles=None,
                    chunk_s: float = 0.05) -> ProgramRun:
        """An open-loop duty program on one hinge, run by the firmware core as the device runs it (PROGRAM):
        from hinge angles `angles` (rad; default flat), the core restarted IDLE, the other hinges braked.

        segments: (duty, duration_s) pairs; window_counts: (low, high) counts; timeout_s: default the segments'
        sum (controllers.core.program_spec). Runs until the core ends the program (checked every chunk_s s) and
        returns its samples, one per tick, as Link.run_program does. ValueError where the core refuses it."""
        self.reset(angles, active=False)
        spec = program_spec(hinge, segments, window_counts, timeout_s)
        refused = self.firmware.program(spec)
        if refused:
            raise ValueError(f"the firmware refused the program on hinge {hinge} (NACK reason {refused}; "
                             "docs/protocol.md, PROGRAM)")
        most = max(spec.timeout_ms, sum(spec.ms[:spec.n_segments])) / 1000 + self.spec.firmware_dt
        traces = []
        while self.firmware.program_status().end == ProgramEnd.RUNNING and len(traces) * chunk_s < most:
            traces.append(self._run(np.zeros(self.spec.n_hinges), chunk_s, False))
        status = self.firmware.program_status()
        counts, duty, decay = (np.concatenate([getattr(t, c)[:, hinge] for t in traces])[:status.ticks]
                               for c in ("counts", "duty", "decay"))
        return ProgramRun(hinge=hinge, time_s=np.arange(status.ticks) * self.spec.firmware_dt, duty=duty,
                          counts=counts.astype(np.int64), battery_mV=float(status.battery_mv) or None,
                          end=end_name(status.end), coasting=decay == DECAY_COAST)

    def unpowered(self, duration: float) -> Trace:
        """`duration` seconds with the drive unpowered (a pack pulled): zero PWM, every winding open, whatever
        the firmware commands; the flaps fall as gravity, friction and the gearboxes let them."""
        return self._run(self._target * self.spec.rad_per_count, duration, False, unpowered=True)

    def _run(self, targets, max_time, stop_when_settled, unpowered: bool = False) -> Trace:
        from twin.sim import kernels  # compiled on first use, not on import

        s, m, d, h = self.spec, self.model, self.data, self.hinges
        ticks = int(round(max_time / s.firmware_dt))
        n = s.n_hinges
        rec = ([np.zeros((ticks, n)), np.zeros((ticks, n), np.int64)] + [np.zeros((ticks, n)) for _ in range(3)]
               + [np.zeros((ticks, n), np.uint8)])
        t0 = d.time
        start = time.perf_counter()
        spreads = contact_free_spreads(s, m)
        if len(spreads):  # the model may have changed since the last run (a root pose, a parameter)
            kernels.LIBMUJOCO.mj_copyModel(self._free_model._address, m._address)
            self._free_model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
        done = kernels.firmware_loop(
            m._address, self._free_model._address, spreads, d._address, self.substeps, self.firmware.address,
            self._now_us, tick_us(s), d.sensordata, d.qpos, d.qvel, d.ctrl, d.qfrc_actuator, d.qfrc_applied, h.enc,
            h.qadr, h.gear_dof, float(s.counts_per_motor_rev), self._params, self._bus, self._target, self._counts,
            self._duty, self._decay, self._pwm, ticks, s.settle_band, hold_samples(s.settle_hold, s.firmware_dt),
            stop_when_settled, unpowered, *rec)
        wall = time.perf_counter() - start
        self._now_us = (self._now_us + done * tick_us(s)) & 0xFFFFFFFF
        angle, counts, duty, current, torque, decay = (r[:done] for r in rec)
        return Trace(
            time=t0 + np.arange(done) * s.firmware_dt,
            target=np.tile(targets, (done, 1)),
            target_counts=np.tile(self._target, (done, 1)).astype(np.int64),
            angle=angle_from_counts(s, counts), counts=counts, duty=duty, current=current, true_angle=angle,
            torque=torque, decay=decay, wall_time=wall,
        )



def profile_twin(profile: Profile, **options) -> Twin:
    """The twin of a device: its profile's spec and gains, each hinge's own plant where it was calibrated per hinge
    (Profile.hinges), held as the profile says (Profile.mount). options: Twin's (root, model, stall_detection)."""
    return Twin(profile.spec, profile.gains, hinges=profile.hinges, mount=profile.mount, **options)
