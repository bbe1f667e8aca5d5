"""The C core's PID equals the numba PID that controllers/pid.py held before it, within float32 rounding.

Each tick is drawn at random (gains within the firmware's bounds, targets, counts, and the PID's
memory); both computed one update from the same start. The numba PID is gone (the twin runs the C
core); its answers are recorded in tests/firmware/firmware_pid_reference.npz (written by commit 66ec328's
`python tests/firmware/test_firmware_pid.py`, which compared the two live over 100 000 random ticks).
"""

import ctypes
import math
from pathlib import Path

import numpy as np

from controllers import core

REFERENCE = Path(__file__).parent / "firmware_pid_reference.npz"
DT = 0.001
EPS = 2.0 ** -23  # float32 spacing at 1


def c_pid(t: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(duty, rate, integral, scale) after one tick of vrs_pid_update, float32; scale bounds the terms."""
    lib = core.library()
    n = len(t["kp"])
    duty, rate, integral, scale = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    dt = ctypes.c_float(DT).value
    s, g = core.PidState(), core.Gains()
    for i in range(n):
        g.kp, g.ki, g.kd, g.cutoff_hz = t["kp"][i], t["ki"][i], t["kd"][i], t["cutoff"][i]
        g.integral_limit, g.deadband, g.hold_band = t["ilim"][i], t["deadband"][i], int(t["hold"][i])
        s.prev, s.rate, s.integral = int(t["prev"][i]), t["rate"][i], t["integral"][i]
        alpha = lib.vrs_pid_alpha(g.cutoff_hz, dt)
        duty[i] = lib.vrs_pid_update(ctypes.addressof(s), ctypes.addressof(g), alpha, dt, int(t["target"][i]),
                                     int(t["counts"][i]))
        rate[i], integral[i] = s.rate, s.integral
        e = float(t["target"][i]) - float(t["counts"][i])
        scale[i] = 1.0 + abs(g.kp * e) + abs(s.integral) + abs(g.ki * e * DT) + abs(g.kd * s.rate) \
            + abs(g.kd * (t["counts"][i] - t["prev"][i]) / DT)
    return duty, rate, integral, scale


def assert_same(t: dict, duty, rate, integral) -> None:
    c_duty, c_rate, c_integral, scale = c_pid(t)
    tol = 16 * EPS * scale
    # where u sits within rounding of the saturation edge, float32 and float64 may decide
    # differently whether to integrate; those ticks are counted, not compared
    e = t["target"].astype(float) - t["counts"]
    u_free = t["kp"] * e + t["integral"] - t["kd"] * rate
    edge = np.abs(np.abs(u_free) - 1.0) <= tol
    assert edge.mean() < 1e-3
    ok = ~edge
    assert np.all(np.abs(c_rate - rate) <= 16 * EPS * (1 + np.abs(rate) + np.abs((t["counts"] - t["prev"]) / DT)))
    assert np.all(np.abs(c_integral - integral)[ok] <= tol[ok])
    assert np.all(np.abs(c_duty - duty)[ok] <= tol[ok])


def test_c_pid_equals_the_recorded_reference():
    ref = np.load(REFERENCE)
    t = {k: ref[k] for k in ref.files if not k.startswith("out_")}
    assert len(t["kp"]) >= 4000
    assert_same(t, ref["out_duty"], ref["out_rate"], ref["out_integral"])


def test_derivative_filter_coefficient():
    lib = core.library()
    for fc in (1.0, 50.0, 450.0):
        tau = 1.0 / (2.0 * math.pi * fc)
        assert abs(lib.vrs_pid_alpha(fc, DT) - DT / (DT + tau)) <= 4 * EPS
