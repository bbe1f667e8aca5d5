"""The batch twin: many simulations in lockstep on MuJoCo's own `Batch` thread pool, one firmware core
per simulation, ticked by a compiled loop over them (twin.sim.kernels)."""

from __future__ import annotations

import ctypes
import time

import mujoco
import numpy as np
from mujoco.batch import Batch

from controllers import core
from controllers.core import (ProgramStatus, core_state_bytes, per_hinge, pid_memory, pid_memory_at, program_spec,
                              set_core_gains, start_core, tick_us)
from controllers.encoder import counts_from_motor_angles, target_counts
from controllers.pid import PidGains
from controllers.program import ProgramEnd, ProgramRun, end_name
from twin.device.mjcf import load_model, motor_attributes
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec, load_spec
from twin.sim.drive import DECAY_COAST, V_PACK, drive_params
from twin.sim.hinges import Hinges, physics_substeps, place_hinges
from twin.sim.targets import TargetError, check_targets


class TwinBatch:
    """nsim twins in lockstep on MuJoCo's `Batch` thread pool, one firmware core per simulation.

    specs: one plant spec per simulation (e.g. perturbed friction or motor
    constant for robust tuning); they must share the device's layout. hinges: per
    simulation, each hinge's own spec (n_hinges of them, as Twin takes them) or
    None. gains: one PidGains for all, or per simulation a sequence of one PidGains
    per hinge. mount: how the device is held (twin.device.mount.MOUNTS).
    """

    def __init__(self, nsim: int, spec: DeviceSpec | None = None, gains=None, specs=None, nthread: int = 0,
                 hinges=None, mount: str = DEFAULT_MOUNT):
        self.spec = spec or load_spec()
        self.nsim = nsim
        n = self.spec.n_hinges
        model = load_model(self.spec, mount=mount)
        self.batch = Batch(model, nsim, nthread=nthread, persistent=True)
        self._models = None
        hinges = [None] * nsim if hinges is None else list(hinges)
        if specs is not None or any(h is not None for h in hinges):
            specs = specs or [self.spec] * nsim
            if len(specs) != nsim or len(hinges) != nsim:
                raise ValueError(f"expected {nsim} plant specs and hinge lists, got {len(specs)} and {len(hinges)}")
            self._models = [load_model(p, mount=mount, motors=None if hs is None else [motor_attributes(h) for h in hs])
                            for p, hs in zip(specs, hinges)]
            self.batch.set_models(self._models)
        self.hinges = Hinges(model, n)
        self.substeps = physics_substeps(self.spec, model)
        self.sensordata = self.batch.bind("sensordata")
        self.qpos = self.batch.bind("qpos")
        self.qvel = self.batch.bind("qvel")
        self.ctrl = self.batch.bind("ctrl")
        self.qfrc_applied = self.batch.bind("qfrc_applied")
        self._counts = np.zeros((nsim, n), np.int32)  # the cores' input and output buffers
        self._duty = np.zeros((nsim, n), np.float32)
        self._decay = np.zeros((nsim, n), np.uint8)
        self._pwm = np.zeros((nsim, n), np.float32)
        self._params = np.stack([drive_params(p, hs) for p, hs in zip(specs or [self.spec] * nsim, hinges)])
        self._bus = np.zeros(nsim)  # V, per simulation
        self.gains = self._per_simulation(gains or PidGains.from_spec(self.spec))
        self.reset()

    def set_gains(self, gains) -> None:
        """One PidGains for every simulation and hinge, or per simulation a sequence of n, as SET_GAINS would.

        ValueError naming the simulation and hinge for gains outside the firmware's bounds (nothing changes then).
        """
        gains = self._per_simulation(gains)
        scratch = start_core(self.spec, self.gains[0], np.zeros(self.spec.n_hinges, np.int32))
        for i, g in enumerate(gains):
            try:
                set_core_gains(scratch, g)
            except ValueError as exc:
                raise ValueError(f"simulation {i}: {exc}") from None
        lib, base, size = core.library(), self._cores.ctypes.data, self._cores.shape[1]
        for i, g in enumerate(gains):
            table = core.gains_struct(g)  # held until the calls return
            for k in range(len(g)):
                lib.vrs_set_gains(base + i * size, k, ctypes.addressof(table[k]))
        self.gains = gains

    def _per_simulation(self, gains) -> list[list[PidGains]]:
        if isinstance(gains, PidGains):
            gains = [gains] * self.nsim
        if len(gains) != self.nsim:
            raise ValueError(f"expected gains for {self.nsim} simulations, got {len(gains)}")
        return [per_hinge(g, self.spec.n_hinges) for g in gains]

    def reset(self, angles=None, integral=None, active: bool = True) -> None:
        """All simulations back to flat (or to angles, rad, (nsim, n_hinges) or one row for all); their firmware
        restarted, holding there, its PID integral per hinge `integral` (duty, the same shapes; default none);
        with active=False IDLE instead (every hinge braked), as a device is before its first targets."""
        self.batch.reset(keyframe=0, stage=mujoco.mjtStage.mjSTAGE_NONE.value)
        if angles is not None:
            for q, a in zip(self.qpos, np.broadcast_to(angles, (self.nsim, self.spec.n_hinges))):
                place_hinges(q, self.hinges, a)
        self.batch.forward()
        self._bus[:] = self._params[:, 0, V_PACK]
        counts = self._counts_now()
        size = core.library().vrs_core_size()
        self._cores = np.zeros((self.nsim, size), np.uint8)  # one vrs_core per simulation, contiguous
        integral = None if integral is None else np.broadcast_to(integral, (self.nsim, self.spec.n_hinges))
        for i in range(self.nsim):
            fw = start_core(self.spec, self.gains[i], counts[i], active=active)
            if integral is not None:
                pid_memory(fw).integral[:] = integral[i]
            self._cores[i] = core_state_bytes(fw)
        self._now_us = 0

    @property
    def integral(self) -> np.ndarray:
        """Each simulation's firmware PID integral per hinge (duty, (nsim, n_hinges)), a copy."""
        base, size = self._cores.ctypes.data, self._cores.shape[1]
        return np.array([pid_memory_at(base + i * size, self.spec.n_hinges, self._cores).integral
                         for i in range(self.nsim)])

    def _counts_now(self) -> np.ndarray:
        return counts_from_motor_angles(self.sensordata[:, self.hinges.enc], self.spec.counts_per_motor_rev)

    def run_program(self, hinge: int, segments, window_counts, timeout_s: float | None = None,
                    angles=None) -> list[ProgramRun]:
        """One open-loop duty program run by every simulation's firmware core from hinge angles `angles` (rad,
        (nsim, n_hinges) or one row; default flat), the cores restarted IDLE: Twin.run_program on each plant at
        once, a ProgramRun per simulation. ValueError where a core refuses the program."""
        from twin.sim import kernels  # compiled on first use, not on import

        s = self.spec
        n = s.n_hinges
        self.reset(angles, active=False)
        spec = program_spec(hinge, segments, window_counts, timeout_s)
        lib, base, size = core.library(), self._cores.ctypes.data, self._cores.shape[1]
        for i in range(self.nsim):
            refused = lib.vrs_program(base + i * size, ctypes.addressof(spec))
            if refused:
                raise ValueError(f"simulation {i}: the firmware refused the program on hinge {hinge} "
                                 f"(NACK reason {refused}; docs/protocol.md, PROGRAM)")
        ticks = round(max(spec.timeout_ms, sum(spec.ms[:spec.n_segments])) / 1000 / s.firmware_dt) + 1
        rec = {k: np.zeros((ticks, self.nsim, n)) for k in ("angle", "duty", "current")}
        rec["counts"] = np.zeros((ticks, self.nsim, n), np.int64)
        rec["decay"] = np.zeros((ticks, self.nsim, n), np.uint8)
        status = [ProgramStatus() for _ in range(self.nsim)]
        vel_stage = mujoco.mjtStage.mjSTAGE_VEL.value
        for i in range(ticks):
            kernels.batch_tick(i, base, size, self._now_us, self.sensordata, self.qpos, self.qvel, self.ctrl,
                               self.qfrc_applied, self.hinges.enc, self.hinges.qadr, self.hinges.gear_dof,
                               float(s.counts_per_motor_rev), self._params, self._bus, self._counts, self._duty,
                               self._decay, self._pwm, rec["angle"], rec["counts"], rec["duty"], rec["current"],
                               rec["decay"])
            self._now_us = (self._now_us + tick_us(s)) & 0xFFFFFFFF
            for j in range(self.nsim):
                lib.vrs_get_program(base + j * size, ctypes.addressof(status[j]))
            if all(st.end != ProgramEnd.RUNNING for st in status):
                break
            self.batch.step(nstep=self.substeps, stage=vel_stage)
        return [ProgramRun(hinge=hinge, time_s=np.arange(st.ticks) * s.firmware_dt,
                           duty=rec["duty"][:st.ticks, j, hinge].copy(),
                           counts=rec["counts"][:st.ticks, j, hinge].copy(),
                           battery_mV=float(st.battery_mv) or None, end=end_name(st.end),
                           coasting=rec["decay"][:st.ticks, j, hinge] == DECAY_COAST)
                for j, st in enumerate(status)]

    def run(self, targets, duration: float) -> dict:
        """Run every simulation to its targets (rad, (nsim, n_hinges)) for `duration` s.

        Returns arrays (ticks, nsim, n_hinges): 'angle' (rad), 'counts', 'duty',
        'current' (A), 'decay' (0 coast, 1 brake); 'time' (s), 'wall_time' (s). TargetError if a firmware refuses its targets.
        """
        from twin.sim import kernels  # compiled on first use, not on import

        s = self.spec
        n = s.n_hinges
        targets = np.broadcast_to(np.asarray(targets, float), (self.nsim, n))
        for row in targets:
            check_targets(s, row)
        tgt = target_counts(s, targets).astype(np.int32)
        lib, base, size = core.library(), self._cores.ctypes.data, self._cores.shape[1]
        for i in range(self.nsim):
            refused = lib.vrs_set_targets(base + i * size, tgt[i].ctypes.data, self._now_us)
            if refused:
                raise TargetError(f"simulation {i}: the firmware refused the targets (NACK reason {refused})")
        ticks = int(round(duration / s.firmware_dt))
        out = {k: np.zeros((ticks, self.nsim, n)) for k in ("angle", "duty", "current")}
        out["counts"] = np.zeros((ticks, self.nsim, n), np.int64)
        out["decay"] = np.zeros((ticks, self.nsim, n), np.uint8)
        vel_stage = mujoco.mjtStage.mjSTAGE_VEL.value
        dt_us = tick_us(s)
        start = time.perf_counter()
        for i in range(ticks):
            kernels.batch_tick(i, base, size, self._now_us, self.sensordata, self.qpos, self.qvel, self.ctrl,
                               self.qfrc_applied, self.hinges.enc, self.hinges.qadr, self.hinges.gear_dof,
                               float(s.counts_per_motor_rev), self._params, self._bus, self._counts, self._duty,
                               self._decay, self._pwm, out["angle"], out["counts"], out["duty"], out["current"],
                               out["decay"])
            self.batch.step(nstep=self.substeps, stage=vel_stage)
            self._now_us = (self._now_us + dt_us) & 0xFFFFFFFF
        out["wall_time"] = time.perf_counter() - start
        out["time"] = np.arange(ticks) * s.firmware_dt
        return out

