"""Quadrature encoder on the motor shaft: angles to counts and back.

The encoder counts motor-shaft turns (spec [encoder] counts_per_motor_rev), so one
output revolution is counts_per_motor_rev * gear_ratio counts (1204.44 for
VRScroll): not a whole number, which is why the firmware works in counts.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from twin.device.spec import DeviceSpec


@numba.njit(cache=True)
def counts_from_motor_angle(motor_angle: float, counts_per_motor_rev: float) -> int:
    """Counts the encoder reports for a motor-shaft angle (rad): floor, as a counter does."""
    return int(math.floor(motor_angle * counts_per_motor_rev / (2.0 * math.pi)))


def counts_from_motor_angles(motor_angle, counts_per_motor_rev: float) -> np.ndarray:
    """counts_from_motor_angle over an array of motor-shaft angles, rad."""
    return np.floor(np.asarray(motor_angle, float) * counts_per_motor_rev / (2.0 * np.pi)).astype(np.int64)


def counts_from_angle(spec: DeviceSpec, angle) -> np.ndarray:
    """Encoder counts for output (hinge) angles, rad: the counter's floor of motor turns."""
    return counts_from_motor_angles(np.asarray(angle, float) * spec.gear_ratio, spec.counts_per_motor_rev)


def target_counts(spec: DeviceSpec, angle) -> np.ndarray:
    """Nearest whole count to an output angle, rad: what a target is sent as."""
    return np.rint(np.asarray(angle, float) / spec.rad_per_count).astype(np.int64)


def angle_from_counts(spec: DeviceSpec, counts) -> np.ndarray:
    """Output angle, rad, of an encoder count."""
    return np.asarray(counts, float) * spec.rad_per_count
