"""Quadrature encoder on the motor shaft: angles to counts and back.

The encoder counts motor-shaft turns (spec [encoder] counts_per_motor_rev), so one
output revolution is counts_per_motor_rev * gear_ratio counts (1204.44 for
VRScroll): not a whole number, which is why the firmware works in counts.
"""

from __future__ import annotations

import numpy as np

from twin.device.spec import DeviceSpec


def counts_from_angle(spec: DeviceSpec, angle) -> np.ndarray:
    """Encoder counts for output (hinge) angles, rad: the counter's floor of motor turns."""
    motor = np.asarray(angle, float) * spec.gear_ratio
    return np.floor(motor * spec.counts_per_motor_rev / (2 * np.pi)).astype(np.int64)


def target_counts(spec: DeviceSpec, angle) -> np.ndarray:
    """Nearest whole count to an output angle, rad: what a target is sent as."""
    return np.rint(np.asarray(angle, float) / spec.rad_per_count).astype(np.int64)


def angle_from_counts(spec: DeviceSpec, counts) -> np.ndarray:
    """Output angle, rad, of an encoder count."""
    return np.asarray(counts, float) * spec.rad_per_count
