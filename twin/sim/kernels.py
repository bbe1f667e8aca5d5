"""The compiled inner loops of the twin and the batch twin (numba): MuJoCo's C API (mj_step1 / mj_step2)
and the firmware core's control tick through ctypes. Loads libmujoco and builds the core when imported:
only the runners import it."""

from __future__ import annotations

import ctypes
import os

import mujoco
import numba
import numpy as np

from controllers import core
from controllers.encoder import counts_from_motor_angle
from twin.device.flap_collision import apart
from twin.sim.drive import DECAY_COAST, drive
from twin.sim.settle import samples_in_band

# MuJoCo's C API and the firmware core's control tick, for the compiled loops
LIBMUJOCO = ctypes.CDLL(os.path.join(os.path.dirname(mujoco.__file__), f"libmujoco.so.{mujoco.__version__}"))
mj_step1, mj_step2, mj_step = LIBMUJOCO.mj_step1, LIBMUJOCO.mj_step2, LIBMUJOCO.mj_step
for _fn in (mj_step1, mj_step2, mj_step):
    _fn.argtypes, _fn.restype = [ctypes.c_void_p, ctypes.c_void_p], None
LIBMUJOCO.mj_copyModel.argtypes, LIBMUJOCO.mj_copyModel.restype = [ctypes.c_void_p, ctypes.c_void_p], ctypes.c_void_p
vrs_tick = core.library().vrs_tick
vrs_pwm = core.library().vrs_pwm
vrs_set_battery_mv = core.library().vrs_set_battery_mv


@numba.njit(cache=False)
def control_tick(fw, now_us, sensordata, enc_adr, cpr_motor, bus, counts, duty, decay, pwm):
    """The firmware's side of one tick: encoder counts, the battery it reads (bus[0], V), vrs_tick, vrs_pwm."""
    for h in range(counts.shape[0]):
        counts[h] = counts_from_motor_angle(sensordata[enc_adr[h]], cpr_motor)
    vrs_set_battery_mv(fw, min(max(int(round(bus[0] * 1000.0)), 0), 65535))
    vrs_tick(fw, now_us & 0xFFFFFFFF, counts.ctypes.data, 0, duty.ctypes.data, decay.ctypes.data)
    vrs_pwm(fw, pwm.ctypes.data)


@numba.njit(cache=False)
def step_model(m, m_free, spreads, qpos, qadr, angles):
    """The model to step from this state: m_free (contacts disabled) where the flaps are apart, else m."""
    if spreads.shape[0] == 0:
        return m
    for h in range(angles.shape[0]):
        angles[h] = qpos[qadr[h]]
    return m_free if apart(spreads, angles) else m


# not cacheable (it calls MuJoCo and the core through ctypes pointers): compiled once per process, in Twin()
@numba.njit(cache=False)
def firmware_loop(m, m_free, spreads, d, substeps, fw, now_us, dt_us, sensordata, qpos, qvel, ctrl, qfrc,
                   qfrc_applied, enc_adr, qadr, gear_dof, cpr_motor, params, bus, target, counts, duty, decay, pwm,
                   max_ticks, settle_band, hold_ticks, stop_when_settled, unpowered, rec_angle, rec_counts, rec_duty,
                   rec_current, rec_torque, rec_decay):
    """Run firmware ticks until settled (if asked: hold_ticks ticks in a row in the band, twin.sim.settle) or
    max_ticks; returns the ticks run. unpowered: the drive
    without power (a pack pulled): zero PWM and the windings open on every hinge, whatever the core commands.

    m_free: the model with contacts disabled, stepped where `apart(spreads, hinge angles)` (no spreads: never);
    fw: the core's address; now_us: device time of the first tick (us), dt_us per tick; counts (int32),
    duty and pwm (float32) and decay (uint8) are the core's input and output buffers; params the drive
    model's (twin.sim.drive), bus[0] the bus voltage (V) the core reads, carried from tick to tick; rec_*: per
    tick and hinge, what it recorded (the decay the drive applied: 0 coast, 1 brake).
    """
    n = target.shape[0]
    current = np.zeros(n)
    angles = np.zeros(n)
    ticks_in_band = 0
    for i in range(max_ticks):
        mi = step_model(m, m_free, spreads, qpos, qadr, angles)
        mj_step1(mi, d)  # positions, velocities and sensors at the start of the tick
        control_tick(fw, now_us + i * dt_us, sensordata, enc_adr, cpr_motor, bus, counts, duty, decay, pwm)
        if unpowered:
            for h in range(n):
                pwm[h] = 0.0
                decay[h] = DECAY_COAST
        bus[0] = drive(params, pwm, decay, qvel, gear_dof, ctrl, qfrc_applied, current)
        ticks_in_band = samples_in_band(target, counts, settle_band, ticks_in_band)  # the settle rule (twin.sim.settle)
        for h in range(n):
            rec_angle[i, h] = qpos[qadr[h]]
            rec_counts[i, h] = counts[h]
            rec_duty[i, h] = duty[h]
            rec_current[i, h] = current[h]
            rec_decay[i, h] = decay[h]
        mj_step2(mi, d)
        for h in range(n):
            rec_torque[i, h] = qfrc[gear_dof[h]] + qfrc_applied[gear_dof[h]]
        for _ in range(substeps - 1):  # finer physics than the firmware, drive held
            mj_step(step_model(m, m_free, spreads, qpos, qadr, angles), d)
        if stop_when_settled and ticks_in_band >= hold_ticks:
            return i + 1
    return max_ticks


@numba.njit(cache=False)
def batch_tick(i, cores, core_size, now_us, sensordata, qpos, qvel, ctrl, qfrc_applied, enc_adr, qadr, gear_dof,
                cpr_motor, params, bus, counts, duty, decay, pwm, rec_angle, rec_counts, rec_duty, rec_current,
                rec_decay):
    """Tick i of every simulation: its encoders, its core (at cores + sim * core_size), its drive; rec_* (tick,
    sim, hinge) what it recorded (the decay: 0 coast, 1 brake)."""
    nsim, n = counts.shape
    current = np.zeros(n)
    for s in range(nsim):
        control_tick(cores + s * core_size, now_us, sensordata[s], enc_adr, cpr_motor, bus[s:s + 1], counts[s],
                      duty[s], decay[s], pwm[s])
        bus[s] = drive(params[s], pwm[s], decay[s], qvel[s], gear_dof, ctrl[s], qfrc_applied[s], current)
        for h in range(n):
            rec_angle[i, s, h] = qpos[s, qadr[h]]
            rec_counts[i, s, h] = counts[s, h]
            rec_duty[i, s, h] = duty[s, h]
            rec_current[i, s, h] = current[h]
            rec_decay[i, s, h] = decay[s, h]

