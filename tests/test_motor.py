"""The dcmotor model against the gearmotor's datasheet (spec [motor])."""

import math

import mujoco
import numpy as np
import pytest

from twin.device.mjcf import load_model


def _one_free_hinge(spec):
    m = load_model(spec)
    m.opt.gravity[:] = 0
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    m.jnt_limited[:] = 0
    return m


def test_free_running_speed_at_rated_voltage(spec):
    """Hinge 5 (the outermost flap) spins up to the datasheet's unloaded output speed, within 10 %."""
    m = _one_free_hinge(spec)
    d = mujoco.MjData(m)
    d.ctrl[m.actuator("motor5").id] = spec.rated_voltage
    for _ in range(1000):
        mujoco.mj_step(m, d)
    speed_rpm = abs(d.qvel[m.joint("hinge5").dofadr[0]]) * 60 / (2 * math.pi)
    assert speed_rpm == pytest.approx(310.0, rel=0.10)


def test_stall_torque_at_rated_voltage(spec):
    m = _one_free_hinge(spec)
    d = mujoco.MjData(m)
    d.ctrl[:] = spec.rated_voltage
    mujoco.mj_forward(m, d)  # at rest: no back-EMF, the motor is stalled
    torque = d.qfrc_actuator[[m.joint(f"hinge{k}").dofadr[0] for k in range(6)]]
    assert np.abs(torque) == pytest.approx(np.full(6, 0.167), rel=0.10)


def test_back_emf_brakes_an_unpowered_motor(spec):
    m = _one_free_hinge(spec)
    d = mujoco.MjData(m)
    dof = m.joint("hinge5").dofadr[0]
    d.qvel[dof] = 10.0  # rad/s, output
    mujoco.mj_forward(m, d)
    assert d.qfrc_actuator[dof] < 0  # shorted winding opposes motion
