"""Step-response metrics that read simulated and measured traces alike.

Inputs are plain arrays: time (s) and a signal in any unit; outputs are in the
signal's unit (or s, or percent). NaN means "not defined for this trace" (no
step, never settled), never a made-up number.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class StepMetrics:
    """Step response of one channel. Times in s; errors in the signal's unit."""

    rise_time: float  # 10 % -> 90 % of the step, s
    settle_time: float  # from the step until the error stays within the band, s
    overshoot: float  # furthest excursion past the target, signal unit (>= 0)
    overshoot_pct: float  # overshoot / step size, percent
    steady_state_error: float  # target - final value (mean of the last `tail` s), signal unit
    itae: float  # integral of t * |error| dt, signal unit * s^2


def step_metrics(t, y, target: float, band: float, tail: float = 0.1) -> StepMetrics:
    """Metrics of y(t) stepping to `target` at t[0]; `band` is the settle tolerance (signal unit)."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    if t.ndim != 1 or t.shape != y.shape or len(t) < 2:
        raise ValueError("t and y must be 1-D arrays of the same length, at least 2 samples")
    t = t - t[0]
    y0 = y[0]
    step = target - y0
    err = target - y
    outside = np.nonzero(np.abs(err) > band)[0]
    if len(outside) == 0:
        settle = 0.0
    elif outside[-1] == len(t) - 1:
        settle = float("nan")  # still outside the band at the end
    else:
        settle = float(t[outside[-1] + 1])
    direction = np.sign(step) if step != 0 else 1.0
    overshoot = float(max(0.0, np.max(direction * (y - target)))) if step != 0 else float(np.max(np.abs(err)))
    final = float(np.mean(y[t >= t[-1] - tail]))
    rise = float("nan")
    if abs(step) > band:
        frac = (y - y0) / step
        i10, i90 = np.argmax(frac >= 0.1), np.argmax(frac >= 0.9)
        if frac[i10] >= 0.1 and frac[i90] >= 0.9:
            rise = float(t[i90] - t[i10])
    dt = np.diff(t, prepend=t[0])
    return StepMetrics(
        rise_time=rise,
        settle_time=settle,
        overshoot=overshoot,
        overshoot_pct=100.0 * overshoot / abs(step) if step != 0 else float("nan"),
        steady_state_error=target - final,
        itae=float(np.sum(t * np.abs(err) * dt)),
    )
