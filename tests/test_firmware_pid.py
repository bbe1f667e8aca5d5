"""The C core's PID equals the numba PID of controllers/pid.py within float32 rounding.

Each tick is drawn at random (gains within the firmware's bounds, targets, counts, and the PID's
memory); both compute one update from the same start. A recorded reference (tests/data/
firmware_pid_reference.npz, written by the numba PID: `python tests/test_firmware_pid.py`)
keeps the comparison once the numba PID is gone.
"""

import ctypes
import math
from pathlib import Path

import numpy as np

from controllers import core

REFERENCE = Path(__file__).parent / "data" / "firmware_pid_reference.npz"
DT = 0.001
EPS = 2.0 ** -23  # float32 spacing at 1


def random_ticks(rng: np.random.Generator, n: int) -> dict:
    """n independent ticks: gains within the firmware's bounds (float32 values), memory and inputs."""
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    wide = rng.random(n) < 0.2  # a fifth of the ticks draw kp and kd up to their bounds (mostly saturated)
    ilim = f32(rng.uniform(0.0, 1.0, n))
    e = np.where(rng.random(n) < 0.8, rng.integers(-60, 61, n), rng.integers(-700, 701, n))
    target = rng.integers(-376, 377, n)
    counts = target - e
    return dict(
        kp=f32(10 ** rng.uniform(-4, wide * 1.5 - 1.5, n)), ki=f32(10 ** rng.uniform(-3, 1, n)),
        kd=f32(10 ** rng.uniform(-5, wide * (math.log10(0.05) + 2.5) - 2.5, n)),
        cutoff=f32(rng.uniform(1.0, 450.0, n)),
        ilim=ilim, deadband=f32(rng.uniform(0.0, 0.5, n)), hold=rng.integers(0, 51, n).astype(np.int32),
        target=target.astype(np.int32), counts=counts.astype(np.int32),
        prev=(counts - rng.integers(-6, 7, n)).astype(np.int32), rate=f32(rng.uniform(-1000, 1000, n)),
        integral=f32(rng.uniform(-1, 1, n) * ilim))


def numba_pid(t: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(duty, rate, integral) after one tick of controllers.pid.pid_update, float64."""
    from controllers.pid import PidGains, pid_update

    n = len(t["kp"])
    rows = np.stack([PidGains(float(t["kp"][i]), float(t["ki"][i]), float(t["kd"][i]), float(t["cutoff"][i]),
                              float(t["ilim"][i]), float(t["deadband"][i]), int(t["hold"][i])).row(DT)
                     for i in range(n)])
    prev, rate, integral, duty = (t["prev"].astype(np.int64), t["rate"].astype(float), t["integral"].astype(float),
                                  np.zeros(n))
    pid_update(t["target"].astype(np.int64), t["counts"].astype(np.int64), prev, rate, integral, rows, DT, duty)
    return duty, rate, integral


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


def test_c_pid_equals_the_numba_pid_over_100000_random_ticks():
    t = random_ticks(np.random.default_rng(12), 100_000)
    assert_same(t, *numba_pid(t))


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


def record(path: Path = REFERENCE) -> None:
    """Write the reference: random ticks and the numba PID's answers."""
    t = random_ticks(np.random.default_rng(2026), 4096)
    duty, rate, integral = numba_pid(t)
    path.parent.mkdir(exist_ok=True)
    np.savez_compressed(path, **t, out_duty=duty, out_rate=rate, out_integral=integral)


if __name__ == "__main__":
    record()
    print(f"wrote {REFERENCE}")
