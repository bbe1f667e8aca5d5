"""The firmware PID's gains, in SI units; the PID itself is the C core's (controllers/firmware/vrs_pid.c).

Per hinge and tick (dt = 1 / loop_rate), computed in float on the device, in the twin and in the emulator:

    e      = target - counts                                  counts
    rate   = rate + a * ((counts - prev) / dt - rate)         counts/s, a = dt / (dt + 1/(2 pi fc))
    I      = clamp(I + ki * e * dt, +-integral_limit)         duty; frozen when |e| <= hold_band
                                                              or when the output is saturated the same way
    u      = kp * e + I - kd * rate                           derivative on measurement
    duty   = sign(u) * (deadband + (1 - deadband) * |u|)      deadband compensation, off when |e| <= hold_band
    duty   = clamp(duty, -1, 1)
"""

from __future__ import annotations

import dataclasses

from twin.device.spec import DeviceSpec

# The gains the firmware accepts in SET_GAINS, in SI units, inclusive (docs/protocol.md, "Gain
# bounds"). The device refuses anything outside them with NACK BAD_VALUE; the host checks them
# before it sends anything. The derivative cutoff stays below the Nyquist rate of the 1 kHz loop.
GAIN_BOUNDS = {
    "kp": (0.0, 1.0),  # duty per count
    "ki": (0.0, 10.0),  # duty per count*s
    "kd": (0.0, 0.05),  # duty per count/s
    "derivative_cutoff": (1.0, 450.0),  # Hz
    "integral_limit": (0.0, 1.0),  # duty
    "deadband_duty": (0.0, 0.5),  # duty
    "hold_band": (0, 50),  # counts
}


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

    def replace(self, **changes) -> "PidGains":
        return dataclasses.replace(self, **changes)
