"""The firmware PID (the C core's vrs_pid_update) on its own: one tick at a time, against hand-computed outputs."""

import ctypes
import math

import numpy as np
import pytest

from controllers import core
from controllers.encoder import angle_from_counts, counts_from_angle, target_counts
from controllers.pid import PidGains

DT = 0.001
PLAIN = PidGains(kp=0.01, ki=0.0, kd=0.0, derivative_cutoff=50.0, integral_limit=0.3, deadband_duty=0.0,
                 hold_band=0)


def near(expected):
    """Equal within float32 rounding (the core computes in float)."""
    return pytest.approx(expected, rel=1e-5, abs=1e-9)


class FirmwarePid:
    """n hinges of the C core's PID, ticked one at a time (float32 inside)."""

    def __init__(self, gains: PidGains, n: int, dt: float):
        self.lib = core.library()
        self.gains = core.gains_struct([gains] * n)
        self.dt = ctypes.c_float(dt).value
        self.alpha = self.lib.vrs_pid_alpha(gains.derivative_cutoff, self.dt)
        self.memory = (core.PidState * n)()

    def reset(self, counts) -> None:
        for k, c in enumerate(counts):
            self.memory[k] = core.PidState(int(c), 0.0, 0.0)

    @property
    def integral(self) -> np.ndarray:
        return np.array([m.integral for m in self.memory])

    def step(self, target, counts) -> np.ndarray:
        return np.array([self.lib.vrs_pid_update(ctypes.addressof(self.memory[k]), ctypes.addressof(self.gains[k]),
                                                 self.alpha, self.dt, int(t), int(c))
                         for k, (t, c) in enumerate(zip(target, counts))])


def test_proportional_and_saturation():
    pid = FirmwarePid(PLAIN, 2, DT)
    duty = pid.step([50, 1000], [0, 0])
    assert duty == near([0.5, 1.0])  # 0.01 * 50; 0.01 * 1000 saturates at 1
    assert pid.step([-1000, 0], [0, 0]) == near([-1.0, 0.0])


def test_derivative_on_measurement_has_no_setpoint_kick():
    pid = FirmwarePid(PLAIN.replace(kp=0.0, kd=0.0001), 1, DT)
    pid.reset([0])
    assert pid.step([500], [0]) == near([0.0])  # target jumped, measurement did not
    duty = pid.step([500], [1])  # measurement moved 1 count in 1 ms: 1000 counts/s raw
    alpha = DT / (DT + 1 / (2 * math.pi * 50.0))
    assert duty == near([-0.0001 * alpha * 1000.0])


def test_integral_accumulates_and_is_clamped():
    pid = FirmwarePid(PLAIN.replace(kp=0.0, ki=1.0, integral_limit=0.05), 1, DT)
    pid.reset([0])
    assert pid.step([10], [0]) == near([0.01])  # ki * e * dt
    for _ in range(100):
        duty = pid.step([10], [0])
    assert duty == near([0.05])  # held at the limit


def test_no_windup_while_saturated():
    pid = FirmwarePid(PLAIN.replace(kp=0.01, ki=1.0, integral_limit=0.5), 1, DT)
    pid.reset([0])
    for _ in range(1000):  # error 1000 counts: the output saturates at once
        pid.step([1000], [0])
    assert pid.integral[0] == near(0.0)


def test_deadband_compensation_and_hold_band():
    g = PLAIN.replace(deadband_duty=0.1, hold_band=2)
    pid = FirmwarePid(g, 3, DT)
    duty = pid.step([2, 10, -10], [0, 0, 0])
    # within the hold band: no kick; outside: deadband + (1 - deadband) * |u|
    assert duty == near([0.02, 0.1 + 0.9 * 0.1, -(0.1 + 0.9 * 0.1)])


def test_encoder_quantization(spec):
    one_rev = counts_from_angle(spec, 2 * math.pi)
    assert one_rev == math.floor(12 * 100.37)  # 1204 whole counts in one output revolution
    step = spec.rad_per_count
    # a counter floors: just below a count edge reads one less
    assert counts_from_angle(spec, [5 * step - 1e-9, 5 * step + 1e-9]).tolist() == [4, 5]
    assert counts_from_angle(spec, -1e-9) == -1
    assert target_counts(spec, angle_from_counts(spec, [-300, 0, 777])).tolist() == [-300, 0, 777]
