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

from controllers import core
from controllers.encoder import angle_from_counts, counts_from_motor_angle, counts_from_motor_angles, target_counts
from controllers.pid import PidGains
from twin.device.flap_collision import apart, apart_spreads
from twin.device.mjcf import load_model
from twin.device.spec import DeviceSpec, load_spec
from twin.sim.response import step_metrics
from twin.sim.drive import V_PACK, drive, drive_params
from twin.formats.trace import TWIN_COLUMNS, TraceWriter


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

    def write_csv(self, path, spec: DeviceSpec) -> None:
        """The trace as a trace CSV (twin.formats.trace, docs/formats.md): the device's columns (angle_deg the
        encoder's angle, as a device reports it) and the twin's own (true angle, target counts, torque)."""
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".part")
        encoder = np.degrees(angle_from_counts(spec, self.counts))
        with TraceWriter(tmp, self.angle.shape[1], extra=TWIN_COLUMNS) as w:
            for i in range(len(self.time)):
                w.write(self.time[i], target_deg=np.degrees(self.target[i]), angle_deg=encoder[i],
                        counts=self.counts[i], duty=self.duty[i], current_A=self.current[i],
                        true_angle_deg=np.degrees(self.angle[i]), target_counts=self.target_counts[i],
                        torque_Nm=self.torque[i])
        os.replace(tmp, path)


def join_traces(traces: list[Trace]) -> Trace:
    """Consecutive traces of one twin as one (their wall times summed)."""
    cat = {f.name: np.concatenate([getattr(t, f.name) for t in traces])
           for f in dataclasses.fields(Trace) if f.name != "wall_time"}
    return Trace(**cat, wall_time=float(sum(t.wall_time for t in traces)))


# MuJoCo's C API and the firmware core's control tick, for the compiled loops
_LIB = ctypes.CDLL(os.path.join(os.path.dirname(mujoco.__file__), f"libmujoco.so.{mujoco.__version__}"))
_mj_step1, _mj_step2, _mj_step = _LIB.mj_step1, _LIB.mj_step2, _LIB.mj_step
for _fn in (_mj_step1, _mj_step2, _mj_step):
    _fn.argtypes, _fn.restype = [ctypes.c_void_p, ctypes.c_void_p], None
_LIB.mj_copyModel.argtypes, _LIB.mj_copyModel.restype = [ctypes.c_void_p, ctypes.c_void_p], ctypes.c_void_p
_vrs_tick = core.library().vrs_tick
_vrs_pwm = core.library().vrs_pwm
_vrs_set_battery_mv = core.library().vrs_set_battery_mv


@numba.njit(cache=False)
def _control_tick(fw, now_us, sensordata, enc_adr, cpr_motor, bus, counts, duty, decay, pwm):
    """The firmware's side of one tick: encoder counts, the battery it reads (bus[0], V), vrs_tick, vrs_pwm."""
    for h in range(counts.shape[0]):
        counts[h] = counts_from_motor_angle(sensordata[enc_adr[h]], cpr_motor)
    _vrs_set_battery_mv(fw, min(max(int(round(bus[0] * 1000.0)), 0), 65535))
    _vrs_tick(fw, now_us & 0xFFFFFFFF, counts.ctypes.data, 0, duty.ctypes.data, decay.ctypes.data)
    _vrs_pwm(fw, pwm.ctypes.data)


def contact_free_spreads(spec: DeviceSpec, model: mujoco.MjModel) -> np.ndarray:
    """`apart`'s spreads for a model whose only colliding geoms are the spec's flap boxes, neighbours
    excluded and no explicit pairs (the generated device); empty for any other model (a scene with
    target shapes), where collision detection is never skipped."""
    n = spec.n_flaps
    flaps = np.array([model.body(f"flap{i}").id for i in range(n)])
    geoms = np.array([model.geom(f"flap{i}_collision").id for i in range(n)])
    colliding = np.flatnonzero(model.geom_contype | model.geom_conaffinity)
    neighbours = {(min(a, b) << 16) + max(a, b) for a, b in zip(flaps[:-1], flaps[1:])}
    size = [(spec.flap_pitch - spec.flap_gap) / 2, spec.depth / 2, spec.thickness / 2]
    if (model.npair or set(model.exclude_signature) != neighbours or not np.array_equal(colliding, np.sort(geoms))
            or np.any(model.geom_type[geoms] != mujoco.mjtGeom.mjGEOM_BOX)
            or not np.allclose(model.geom_size[geoms], size, rtol=1e-8, atol=0)):
        return np.zeros(0)
    return apart_spreads(spec, float(model.geom_margin[geoms].max()))


@numba.njit(cache=False)
def _step_model(m, m_free, spreads, qpos, qadr, angles):
    """The model to step from this state: m_free (contacts disabled) where the flaps are apart, else m."""
    if spreads.shape[0] == 0:
        return m
    for h in range(angles.shape[0]):
        angles[h] = qpos[qadr[h]]
    return m_free if apart(spreads, angles) else m


# not cacheable (it calls MuJoCo and the core through ctypes pointers): compiled once per process, in Twin()
@numba.njit(cache=False)
def _firmware_loop(m, m_free, spreads, d, substeps, fw, now_us, dt_us, sensordata, qpos, qvel, ctrl, qfrc,
                   qfrc_applied, enc_adr, qadr, gear_dof, cpr_motor, params, bus, target, counts, duty, decay, pwm,
                   max_ticks, settle_band, hold_ticks, stop_when_settled, rec_angle, rec_counts, rec_duty,
                   rec_current, rec_torque):
    """Run firmware ticks until settled (if asked) or max_ticks; returns the ticks run.

    m_free: the model with contacts disabled, stepped where `apart(spreads, hinge angles)` (no spreads: never);
    fw: the core's address; now_us: device time of the first tick (us), dt_us per tick; counts (int32),
    duty and pwm (float32) and decay (uint8) are the core's input and output buffers; params the drive
    model's (twin.sim.drive), bus[0] the bus voltage (V) the core reads, carried from tick to tick.
    """
    n = target.shape[0]
    current = np.zeros(n)
    angles = np.zeros(n)
    in_band = 0
    for i in range(max_ticks):
        mi = _step_model(m, m_free, spreads, qpos, qadr, angles)
        _mj_step1(mi, d)  # positions, velocities and sensors at the start of the tick
        _control_tick(fw, now_us + i * dt_us, sensordata, enc_adr, cpr_motor, bus, counts, duty, decay, pwm)
        bus[0] = drive(params, pwm, decay, qvel, gear_dof, ctrl, qfrc_applied, current)
        settled = True
        for h in range(n):
            if abs(target[h] - counts[h]) > settle_band:
                settled = False
            rec_angle[i, h] = qpos[qadr[h]]
            rec_counts[i, h] = counts[h]
            rec_duty[i, h] = duty[h]
            rec_current[i, h] = current[h]
        _mj_step2(mi, d)
        for h in range(n):
            rec_torque[i, h] = qfrc[gear_dof[h]] + qfrc_applied[gear_dof[h]]
        for _ in range(substeps - 1):  # finer physics than the firmware, drive held
            _mj_step(_step_model(m, m_free, spreads, qpos, qadr, angles), d)
        in_band = in_band + 1 if settled else 0
        if stop_when_settled and in_band >= hold_ticks:
            return i + 1
    return max_ticks


@numba.njit(cache=False)
def _batch_tick(i, cores, core_size, now_us, sensordata, qpos, qvel, ctrl, qfrc_applied, enc_adr, qadr, gear_dof,
                cpr_motor, params, bus, counts, duty, decay, pwm, rec_angle, rec_counts, rec_duty, rec_current):
    """Tick i of every simulation: its encoders, its core (at cores + sim * core_size), its drive."""
    nsim, n = counts.shape
    current = np.zeros(n)
    for s in range(nsim):
        _control_tick(cores + s * core_size, now_us, sensordata[s], enc_adr, cpr_motor, bus[s:s + 1], counts[s],
                      duty[s], decay[s], pwm[s])
        bus[s] = drive(params[s], pwm[s], decay[s], qvel[s], gear_dof, ctrl[s], qfrc_applied[s], current)
        for h in range(n):
            rec_angle[i, s, h] = qpos[s, qadr[h]]
            rec_counts[i, s, h] = counts[s, h]
            rec_duty[i, s, h] = duty[s, h]
            rec_current[i, s, h] = current[h]


def place_hinges(qpos, hinges: "Hinges", angles) -> None:
    """Put each flap at its hinge angle (rad) and its gearbox output with it, mid-backlash (in qpos)."""
    qpos[hinges.qadr] = angles
    qpos[hinges.gear_qadr] = angles


def physics_substeps(spec: DeviceSpec, model: mujoco.MjModel) -> int:
    """Physics steps per firmware tick (the duty is held between them): the one rule every runner uses."""
    return max(1, round(spec.firmware_dt / model.opt.timestep))


def tick_us(spec: DeviceSpec) -> int:
    """One firmware tick in device time, us."""
    return round(spec.firmware_dt * 1e6)


def per_hinge(gains, n: int) -> list[PidGains]:
    """n PidGains from one (for every hinge) or a sequence of n."""
    gains = [gains] * n if isinstance(gains, PidGains) else list(gains)
    if len(gains) != n:
        raise ValueError(f"expected gains for {n} hinges, got {len(gains)}")
    return gains


def start_core(spec: DeviceSpec, gains: list[PidGains], counts, stall_detection: bool = False) -> core.Core:
    """The twin's firmware core, ACTIVE and holding `counts`: the device's config with the watchdog off
    (no host talks to the twin) and, unless asked for, stall detection off (the twin is also driven into
    contact on purpose: the CBS baseline, the gate's runs).

    ValueError naming the hinge for gains outside the firmware's bounds.
    """
    cfg = core.config_from_spec(spec)
    cfg.watchdog_ms = 0
    if not stall_detection:
        cfg.stall_duty = math.inf  # no |duty| reaches it
    fw = core.Core(cfg, [PidGains.from_spec(spec)] * spec.n_hinges, counts)
    set_core_gains(fw, gains)
    fw.set_targets(counts, 0)
    return fw


def set_core_gains(fw: core.Core, gains: list[PidGains]) -> None:
    """Each hinge's gains into the core, as SET_GAINS would; ValueError naming the first hinge it refuses."""
    for k, g in enumerate(gains):
        if fw.set_gains(k, g):
            raise ValueError(f"hinge {k}: the firmware refuses gains outside its bounds (docs/protocol.md): {g}")


def pid_memory(fw: core.Core) -> np.recarray:
    """A live view of the core's PID memory per hinge: fields prev (counts), rate (counts/s), integral (duty)."""
    mem = (core.PidState * fw.n).from_address(fw.lib.vrs_pid_memory(fw.address))
    mem.owner = fw  # the view keeps the core's memory alive
    return np.ctypeslib.as_array(mem).view(np.recarray)


class Hinges:
    """Addresses of each hinge's joint and dof (the flap), the joint and dof its motor turns (the gearbox
    output, beyond the backlash; the flap's own where there is none), its actuator and encoder."""

    def __init__(self, model: mujoco.MjModel, n: int):
        self.qadr = np.array([model.joint(f"hinge{k}").qposadr[0] for k in range(n)], np.int64)
        self.dadr = np.array([model.joint(f"hinge{k}").dofadr[0] for k in range(n)], np.int64)
        gear = [model.joint(model.actuator_trnid[model.actuator(f"motor{k}").id, 0]) for k in range(n)]
        self.gear_qadr = np.array([j.qposadr[0] for j in gear], np.int64)  # the flap's own without backlash
        self.gear_dof = np.array([j.dofadr[0] for j in gear], np.int64)
        self.enc = np.array([model.sensor(f"encoder{k}").adr[0] for k in range(n)], np.int64)
        act = [model.actuator(f"motor{k}").id for k in range(n)]
        if act != list(range(n)):
            raise ValueError("actuators must be declared in hinge order")


class Twin:
    """One simulated VRScroll with its firmware in the loop.

    The root flap is held by a hand: fixed in the world at `root_pose`
    (root='fixed'), or free to move (root='free'). The firmware keeps its state
    between moves, as the device's does; `reset` restarts it. Its supervisor
    checks the hinge limits, and stalls with stall_detection=True.
    """

    def __init__(self, spec: DeviceSpec | None = None, gains=None, root: str = "fixed",
                 model: mujoco.MjModel | None = None, stall_detection: bool = False):
        self.spec = spec or load_spec()
        self.model = model or load_model(self.spec, root)
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
        self._params = drive_params(self.spec)
        self._bus = np.zeros(1)  # V: the bus voltage the core reads, from the last tick
        self.reset()
        self._run(np.zeros(n), 0.0, False)  # compile the loop now, so moves time only the simulation

    # ---- state ---------------------------------------------------------------
    def reset(self, angles=None) -> None:
        """Back to the `flat` keyframe (or given hinge angles, rad); the firmware restarted, holding there."""
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("flat").id)
        if angles is not None:
            place_hinges(self.data.qpos, self.hinges, check_targets(self.spec, angles))
        mujoco.mj_forward(self.model, self.data)
        self._bus[0] = self.spec.supply_voltage
        self._target[:] = self.counts
        self.firmware = start_core(self.spec, self.gains, self._target, self.stall_detection)
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

    def _run(self, targets, max_time, stop_when_settled) -> Trace:
        s, m, d, h = self.spec, self.model, self.data, self.hinges
        ticks = int(round(max_time / s.firmware_dt))
        n = s.n_hinges
        rec = [np.zeros((ticks, n)), np.zeros((ticks, n), np.int64)] + [np.zeros((ticks, n)) for _ in range(3)]
        t0 = d.time
        start = time.perf_counter()
        spreads = contact_free_spreads(s, m)
        if len(spreads):  # the model may have changed since the last run (a root pose, a parameter)
            _LIB.mj_copyModel(self._free_model._address, m._address)
            self._free_model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
        done = _firmware_loop(
            m._address, self._free_model._address, spreads, d._address, self.substeps, self.firmware.address,
            self._now_us, tick_us(s), d.sensordata, d.qpos, d.qvel, d.ctrl, d.qfrc_actuator, d.qfrc_applied, h.enc,
            h.qadr, h.gear_dof, float(s.counts_per_motor_rev), self._params, self._bus, self._target, self._counts,
            self._duty, self._decay, self._pwm, ticks, s.settle_band, int(round(s.settle_hold / s.firmware_dt)),
            stop_when_settled, *rec)
        wall = time.perf_counter() - start
        self._now_us = (self._now_us + done * tick_us(s)) & 0xFFFFFFFF
        angle, counts, duty, current, torque = (r[:done] for r in rec)
        return Trace(
            time=t0 + np.arange(done) * s.firmware_dt,
            target=np.tile(targets, (done, 1)),
            target_counts=np.tile(self._target, (done, 1)).astype(np.int64),
            angle=angle, counts=counts, duty=duty, current=current, torque=torque, wall_time=wall,
        )


class TwinBatch:
    """nsim twins in lockstep on MuJoCo's `Batch` thread pool, one firmware core per simulation.

    specs: one plant spec per simulation (e.g. perturbed friction or motor
    constant for robust tuning); they must share the device's layout. gains: one
    PidGains for all, or per simulation a sequence of one PidGains per hinge.
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
        self._params = np.stack([drive_params(p) for p in (specs or [self.spec] * nsim)])
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

    def reset(self, angles=None) -> None:
        """All simulations back to flat (or to angles, rad, shape (nsim, n_hinges)); their firmware restarted."""
        self.batch.reset(keyframe=0, stage=mujoco.mjtStage.mjSTAGE_NONE.value)
        if angles is not None:
            for q, a in zip(self.qpos, np.broadcast_to(angles, (self.nsim, self.spec.n_hinges))):
                place_hinges(q, self.hinges, a)
        self.batch.forward()
        self._bus[:] = self._params[:, V_PACK]
        counts = self._counts_now()
        size = core.library().vrs_core_size()
        self._cores = np.zeros((self.nsim, size), np.uint8)  # one vrs_core per simulation, contiguous
        for i in range(self.nsim):
            self._cores[i] = _core_bytes(start_core(self.spec, self.gains[i], counts[i]))
        self._now_us = 0

    def _counts_now(self) -> np.ndarray:
        return counts_from_motor_angles(self.sensordata[:, self.hinges.enc], self.spec.counts_per_motor_rev)

    def run(self, targets, duration: float) -> dict:
        """Run every simulation to its targets (rad, (nsim, n_hinges)) for `duration` s.

        Returns arrays (ticks, nsim, n_hinges): 'angle' (rad), 'counts', 'duty',
        'current' (A); 'time' (s), 'wall_time' (s). TargetError if a firmware refuses its targets.
        """
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
        vel_stage = mujoco.mjtStage.mjSTAGE_VEL.value
        dt_us = tick_us(s)
        start = time.perf_counter()
        for i in range(ticks):
            _batch_tick(i, base, size, self._now_us, self.sensordata, self.qpos, self.qvel, self.ctrl,
                        self.qfrc_applied, self.hinges.enc, self.hinges.qadr, self.hinges.gear_dof,
                        float(s.counts_per_motor_rev), self._params, self._bus, self._counts, self._duty, self._decay,
                        self._pwm, out["angle"], out["counts"], out["duty"], out["current"])
            self.batch.step(nstep=self.substeps, stage=vel_stage)
            self._now_us = (self._now_us + dt_us) & 0xFFFFFFFF
        out["wall_time"] = time.perf_counter() - start
        out["time"] = np.arange(ticks) * s.firmware_dt
        return out


def _core_bytes(fw: core.Core) -> np.ndarray:
    """A copy of a core's state (a vrs_core holds no pointers: its copy is a core)."""
    return np.ctypeslib.as_array((ctypes.c_uint8 * core.library().vrs_core_size()).from_address(fw.address)).copy()


def hinge_metrics(spec: DeviceSpec, time_s, target_counts: float, counts, target: float, angle):
    """One hinge's step from time_s[0]: (metrics in counts, settle band in counts; metrics in rad).

    The one definition of settle time (from the counts, the firmware's settle
    band) and overshoot (from the true angle) that reports and the tuner share.
    """
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
