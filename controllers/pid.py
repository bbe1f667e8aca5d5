"""The firmware's PID, as it runs on the ESP32-S3: discrete, on encoder counts, duty out.

Per hinge and tick (dt = 1 / loop_rate):

    e      = target - counts                                  counts
    rate   = rate + a * ((counts - prev) / dt - rate)         counts/s, a = dt / (dt + 1/(2 pi fc))
    I      = clamp(I + ki * e * dt, +-integral_limit)         duty; frozen when |e| <= hold_band
                                                              or when the output is saturated the same way
    u      = kp * e + I - kd * rate                           derivative on measurement
    duty   = sign(u) * (deadband + (1 - deadband) * |u|)      deadband compensation, off when |e| <= hold_band
    duty   = clamp(duty, -1, 1)

`pid_update` is the one implementation: the twin's compiled loop, the batch path,
the emulator and the tuner all call it, so gains mean the same everywhere.
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from twin.device.spec import DeviceSpec

# columns of a gains row, as pid_update reads them
KP, KI, KD, ALPHA, ILIM, DEADBAND, HOLD = range(7)


@dataclasses.dataclass(frozen=True)
class PidGains:
    """One hinge's firmware gains. Units: duty per count (kp), per count-second (ki), per count/s (kd)."""

    kp: float
    ki: float
    kd: float
    derivative_cutoff: float  # Hz
    integral_limit: float  # duty
    deadband_duty: float  # duty
    hold_band: int  # counts

    @classmethod
    def from_spec(cls, spec: DeviceSpec) -> "PidGains":
        return cls(spec.kp, spec.ki, spec.kd, spec.derivative_cutoff, spec.integral_limit,
                   spec.deadband_duty, spec.hold_band)

    def row(self, dt: float) -> np.ndarray:
        """The gains as the kernel's row, for a tick of dt seconds."""
        tau = 1.0 / (2.0 * math.pi * self.derivative_cutoff)
        return np.array([self.kp, self.ki, self.kd, dt / (dt + tau), self.integral_limit,
                         self.deadband_duty, self.hold_band], dtype=float)

    def replace(self, **changes) -> "PidGains":
        return dataclasses.replace(self, **changes)


def gains_table(gains, n: int, dt: float) -> np.ndarray:
    """(n, 7) kernel rows from one PidGains (for every hinge) or a sequence of n of them."""
    if isinstance(gains, PidGains):
        gains = [gains] * n
    if len(gains) != n:
        raise ValueError(f"expected gains for {n} hinges, got {len(gains)}")
    return np.stack([g.row(dt) for g in gains])


@numba.njit(cache=True)
def pid_update(target, counts, prev, rate, integral, gains, dt, duty):
    """One firmware tick for every channel; updates prev, rate, integral in place; writes duty.

    target, counts, prev: int64 (n,); rate, integral, duty: float (n,); gains: (n, 7).
    """
    for i in range(target.shape[0]):
        g = gains[i]
        e = target[i] - counts[i]
        rate[i] += g[ALPHA] * ((counts[i] - prev[i]) / dt - rate[i])
        prev[i] = counts[i]
        on_target = abs(e) <= g[HOLD]
        u_free = g[KP] * e + integral[i] - g[KD] * rate[i]
        # conditional integration: not on target, and not pushing further into saturation
        if not on_target and not (abs(u_free) >= 1.0 and u_free * e > 0):
            integral[i] = min(max(integral[i] + g[KI] * e * dt, -g[ILIM]), g[ILIM])
        u = g[KP] * e + integral[i] - g[KD] * rate[i]
        if not on_target and u != 0.0:
            u = math.copysign(g[DEADBAND] + (1.0 - g[DEADBAND]) * abs(u), u)
        duty[i] = min(max(u, -1.0), 1.0)


class FirmwarePid:
    """The firmware's controller state for n hinges; call `step` once per tick."""

    def __init__(self, gains, n: int, dt: float):
        self.dt = dt
        self.gains = gains_table(gains, n, dt)
        self.prev = np.zeros(n, np.int64)
        self.rate = np.zeros(n)
        self.integral = np.zeros(n)
        self.duty = np.zeros(n)

    def reset(self, counts) -> None:
        """Forget history; the next tick sees no motion since `counts`."""
        self.prev[:] = counts
        self.rate[:] = 0.0
        self.integral[:] = 0.0
        self.duty[:] = 0.0

    def set_gains(self, gains) -> None:
        self.gains = gains_table(gains, len(self.prev), self.dt)

    def step(self, target, counts) -> np.ndarray:
        """Duty in [-1, 1] per hinge, from target and measured counts (int)."""
        pid_update(np.asarray(target, np.int64), np.asarray(counts, np.int64), self.prev, self.rate,
                   self.integral, self.gains, self.dt, self.duty)
        return self.duty.copy()
