"""Hinge targets checked against the device's range: never clipped in silence."""

from __future__ import annotations

import math

import numpy as np

from twin.device.spec import DeviceSpec


class TargetError(ValueError):
    """A hinge target the device cannot reach; names the hinge and the limit."""


def check_targets(spec: DeviceSpec, targets) -> np.ndarray:
    """Hinge targets as a float array (rad), or TargetError: never clipped in silence."""
    targets = np.asarray(targets, dtype=float)
    if targets.shape != (spec.n_hinges,):
        raise TargetError(f"expected {spec.n_hinges} hinge targets, got {targets.size}")
    lim = spec.hinge_limit
    for k, a in enumerate(targets):
        if not math.isfinite(a):
            raise TargetError(f"hinge {k}: target {a} is not a number")
        if abs(a) > lim + 1e-12:
            raise TargetError(
                f"hinge {k}: target {math.degrees(a):.2f} deg is outside the hinge range "
                f"+-{math.degrees(lim):.1f} deg"
            )
    return targets

