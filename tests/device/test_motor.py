"""The drive train against the gearmotor's datasheet (spec [motor]) and its own bookkeeping: MuJoCo's dcmotor
driven through the drive model (twin.sim.drive), as the twin, the batch twin and the emulator drive it."""

import math

import mujoco
import numpy as np
import pytest

from controllers import core
from controllers.pid import PidGains
from twin.device.mjcf import load_model
from twin.sim.drive import drive, drive_params
from twin.sim.hinges import Hinges

COAST, BRAKE = 0, 1


def _dyno(spec, **changes):
    """One free hinge on a bench: no gravity, contact or hinge limits; 6 V at the winding's terminals for PWM 1
    (no pack or driver resistance), so the datasheet's conditions. Returns (spec, model, data, hinges, params)."""
    spec = spec.replace(driver_on_resistance=0.0, pack_resistance=0.0, supply_voltage=spec.rated_voltage, **changes)
    m = load_model(spec)
    m.opt.gravity[:] = 0
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    m.jnt_limited[:] = 0
    return spec, m, mujoco.MjData(m), Hinges(m, spec.n_hinges), drive_params(spec)


def _run(m, d, h, params, pwm, seconds, load=None):
    """Step with the drive model each step (PWM per hinge, brake decay) and an optional load torque on the flaps
    (N*m, opposing positive motion); returns the last currents (A)."""
    current = np.zeros(len(pwm))
    pwm = np.asarray(pwm, np.float32)
    decay = np.full(len(pwm), BRAKE, np.uint8)
    for _ in range(int(round(seconds / m.opt.timestep))):
        mujoco.mj_step1(m, d)
        drive(params, pwm, decay, d.qvel, h.gear_dof, d.ctrl, d.qfrc_applied, current)
        if load is not None:
            d.qfrc_applied[h.dadr] = -np.asarray(load)
        mujoco.mj_step2(m, d)
    return current


def test_free_running_speed_and_current_at_rated_voltage(spec):
    """Hinge 5 (the outermost flap) spins up to the datasheet's unloaded output speed and draws its no-load
    current, within 10 %."""
    spec, m, d, h, params = _dyno(spec)
    pwm = np.zeros(spec.n_hinges)
    pwm[5] = 1.0
    current = _run(m, d, h, params, pwm, 1.0)
    speed_rpm = abs(d.qvel[h.gear_dof[5]]) * 60 / (2 * math.pi)
    assert speed_rpm == pytest.approx(310.0, rel=0.10)
    assert current[5] == pytest.approx(spec.no_load_current, rel=0.10)


def test_stall_torque_and_current_at_rated_voltage(spec):
    """On a dynamometer: two loads against the outer hinges (0 and 5, whose flaps carry no others) at 6 V give
    two points of the torque-speed and current-torque lines; where the speed reaches zero is the stall,
    within 10 % of the datasheet's."""
    outer = [0, spec.n_hinges - 1]
    pwm = np.zeros(spec.n_hinges)
    pwm[outer] = 1.0
    points = []
    for share in (0.3, 0.7):
        spec_, m, d, h, params = _dyno(spec)
        load = np.zeros(spec.n_hinges)
        load[outer] = share * spec.stall_torque
        current = _run(m, d, h, params, pwm, 0.6, load)
        points.append((load[outer], d.qvel[h.gear_dof[outer]].copy(), current[outer].copy()))
    (l1, w1, i1), (l2, w2, i2) = points
    assert np.all(w2 > 0) and np.all(w1 > w2)  # still turning forward, slower under more load
    stall_torque = l1 + (l2 - l1) * w1 / (w1 - w2)
    stall_current = i1 + (i2 - i1) * (stall_torque - l1) / (l2 - l1)
    assert stall_torque == pytest.approx([0.167, 0.167], rel=0.10)
    assert stall_current == pytest.approx([1.6, 1.6], rel=0.10)


def test_reported_current_and_applied_torque_agree_driving_and_back_driven(spec):
    """At random operating points (PWM, speed either way, pack voltage, the current limit reached or not)
    the torque the simulation applies through the gearbox equals current x K x N x efficiency within 2 %:
    eta driving, 1 / eta_back when the flap drives the motor. Friction and cogging are off, so the torque is
    the gearbox's."""
    spec = spec.replace(gear_friction=0.0, gear_stiction=0.0, gear_damping=0.0, friction_stiffness=0.0, cogging=0.0)
    m = load_model(spec)
    d = mujoco.MjData(m)
    h = Hinges(m, spec.n_hinges)
    rng = np.random.default_rng(3)
    kn = spec.motor_constant * spec.gear_ratio
    seen = {"driving": 0, "back-driven": 0, "limited": 0}
    current = np.zeros(spec.n_hinges)
    for _ in range(100):
        p = spec.replace(supply_voltage=rng.uniform(spec.pack_low_voltage, spec.pack_full_voltage))
        mujoco.mj_resetData(m, d)
        d.qvel[h.gear_dof] = rng.uniform(-1.5, 1.5, spec.n_hinges) * spec.no_load_speed
        d.qvel[h.dadr] = d.qvel[h.gear_dof]
        pwm = rng.uniform(-1, 1, spec.n_hinges).astype(np.float32)
        drive(drive_params(p), pwm, np.full(spec.n_hinges, BRAKE, np.uint8), d.qvel, h.gear_dof, d.ctrl,
              d.qfrc_applied, current)
        mujoco.mj_forward(m, d)
        applied = d.qfrc_actuator[h.gear_dof] + d.qfrc_applied[h.gear_dof]
        w = d.qvel[h.gear_dof]
        driving = current * w >= 0
        eff = np.where(driving, spec.gearbox_efficiency, 1 / spec.backdrive_efficiency)
        np.testing.assert_allclose(applied, current * kn * eff, rtol=0.02, atol=1e-9)
        seen["driving"] += int(driving.sum())
        seen["back-driven"] += int((~driving).sum())
        seen["limited"] += int(np.sum(np.isclose(np.abs(current), spec.driver_current_limit)))
    assert min(seen.values()) > 5, seen


def test_back_emf_brakes_a_shorted_motor_and_coast_does_not(spec):
    """Zero PWM in brake decay (the firmware ACTIVE, FAULT, ESTOP) shorts the winding: a turning flap meets
    back-EMF braking. In coast (IDLE) the winding is open: no current, no braking torque."""
    m = load_model(spec)
    d = mujoco.MjData(m)
    h = Hinges(m, spec.n_hinges)
    current = np.zeros(spec.n_hinges)
    zero = np.zeros(spec.n_hinges, np.float32)
    for decay, brakes in ((BRAKE, True), (COAST, False)):
        mujoco.mj_resetData(m, d)
        d.qvel[h.gear_dof] = d.qvel[h.dadr] = 10.0  # rad/s, output
        drive(drive_params(spec), zero, np.full(spec.n_hinges, decay, np.uint8), d.qvel, h.gear_dof, d.ctrl,
              d.qfrc_applied, current)
        mujoco.mj_forward(m, d)
        electric = current * spec.motor_constant * spec.gear_ratio
        if brakes:
            assert np.all(current < 0) and np.all(electric < 0)  # the shorted winding opposes the motion
        else:
            assert np.all(current == 0.0)
            assert np.all(d.ctrl == pytest.approx(spec.motor_constant * spec.gear_ratio * 10.0))  # open circuit


def test_the_pack_sags_under_six_stalled_hinges(spec):
    """Six hinges at full PWM from rest share the pack: the bus drops by the pack's resistance times their
    current, the same for every hinge; a fuller pack drives more current."""
    m = load_model(spec)
    d = mujoco.MjData(m)
    h = Hinges(m, spec.n_hinges)
    current = np.zeros(spec.n_hinges)
    full = np.ones(spec.n_hinges, np.float32)
    brake = np.full(spec.n_hinges, BRAKE, np.uint8)
    stalled = {}
    for v in (spec.pack_low_voltage, spec.pack_full_voltage):
        bus = drive(drive_params(spec.replace(supply_voltage=v)), full, brake, d.qvel, h.gear_dof, d.ctrl,
                    d.qfrc_applied, current)
        assert current == pytest.approx(np.full(spec.n_hinges, bus / spec.drive_resistance))
        assert bus == pytest.approx(v - spec.pack_resistance * current.sum())
        stalled[v] = current[0]
    assert stalled[spec.pack_low_voltage] < stalled[spec.pack_full_voltage]


def test_the_firmware_compensates_its_duty_for_the_battery(spec):
    """The C core's vrs_pwm: duty 1 means the drive cap (6 V) at the motor, whatever the pack: PWM = duty x
    6 V / battery, clamped to 1 when the pack sags below the cap; with no battery reading, PWM = duty."""
    fw = core.Core(core.config_from_spec(spec), [PidGains.from_spec(spec)] * spec.n_hinges, np.zeros(spec.n_hinges))
    fw.mark_zero_confirmed()
    assert fw.set_targets(np.array([40, -40, 10, -10, 300, 0]), 0) == 0
    duty, _ = fw.tick(0, np.zeros(spec.n_hinges))
    assert np.all(fw.pwm() == pytest.approx(duty))  # no reading yet
    for mv in (8400, 7400, 6600, 5000):
        fw.battery(mv)
        expected = np.clip(duty * spec.drive_cap * 1000 / mv, -1, 1)
        assert fw.pwm() == pytest.approx(expected, rel=1e-6)
    assert fw.pwm()[4] == 1.0  # a sagging pack gives what it has
