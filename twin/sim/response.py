"""Step-response metrics that read simulated and measured traces alike, and the twin's move report.

Inputs are plain arrays: time (s) and a signal in any unit; outputs are in the
signal's unit (or s, or percent). NaN means "not defined for this trace" (no
step, never settled), never a made-up number.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from twin.device.spec import DeviceSpec
from twin.records.move_report import MoveReport
from twin.records.trace import Trace


@dataclasses.dataclass(frozen=True)
class StepMetrics:
    """Step response of one channel. Times in s; errors in the signal's unit."""

    rise_time: float  # 10 % -> 90 % of the step, s
    settle_time: float  # settle_time(): when the error last entered the band and stayed, s after the step
    overshoot: float  # furthest excursion past the target, signal unit (>= 0)
    overshoot_pct: float  # overshoot / step size, percent
    steady_state_error: float  # target - final value (mean of the last `hold` s), signal unit
    itae: float  # integral of t * |error| dt, signal unit * s^2


def settle_time(t, error, band: float, hold: float, start: float | None = None) -> float:
    """THE settle time (docs/device.md, "Settle time"), s after the command at `start` (s; t[0] by default,
    a trace whose first row is the command's tick): the moment |error| last entered the band
    (|error| <= band) and stayed there to the record's end, the record going on at least `hold` s from it
    (counting the last sample's period); NaN where it never settled so. error (samples,) or (samples,
    channels): with channels, all of them at once (a move's settle time, the latest hinge's)."""
    t = np.asarray(t, float)
    e = np.abs(np.asarray(error, float))
    if e.ndim == 2:
        e = e.max(axis=1) if e.shape[1] else np.zeros(len(t))
    if len(t) < 2 or e.shape != t.shape:
        raise ValueError("t and error must hold the same number of samples, at least 2")
    outside = np.nonzero(e > band * (1 + 1e-9))[0]  # the band itself is inside, whatever the rounding
    first = int(outside[-1]) + 1 if len(outside) else 0
    if first >= len(t):
        return float("nan")
    period = float(np.median(np.diff(t)))
    if t[-1] - t[first] + period < hold - 1e-9:
        return float("nan")
    return float(t[first] - (t[0] if start is None else start))


def step_metrics(t, y, target: float, band: float, hold: float = 0.1, start: float | None = None) -> StepMetrics:
    """Metrics of y(t) stepping to `target` at `start` (s; t[0] by default); `band` is the settle tolerance
    (signal unit), `hold` the s the error must then stay in it (settle_time) and the span the final value is
    averaged over. Times (settle, rise) are from `start`."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    if t.ndim != 1 or t.shape != y.shape or len(t) < 2:
        raise ValueError("t and y must be 1-D arrays of the same length, at least 2 samples")
    settle = settle_time(t, target - y, band, hold, start)
    t = t - (t[0] if start is None else start)
    y0 = y[0]
    step = target - y0
    err = target - y
    direction = np.sign(step) if step != 0 else 1.0
    overshoot = float(max(0.0, np.max(direction * (y - target)))) if step != 0 else float(np.max(np.abs(err)))
    final = float(np.mean(y[t >= t[-1] - hold]))
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


def hinge_metrics(spec: DeviceSpec, time_s, target_counts: float, counts, target: float, angle):
    """One hinge's step from time_s[0]: (metrics in counts, settle band in counts; metrics in rad).

    The one definition of settle time (from the counts, the firmware's settle
    band) and overshoot (from the true angle) that reports and the tuner share.
    """
    return (step_metrics(time_s, counts, target_counts, spec.settle_band, hold=spec.settle_hold),
            step_metrics(time_s, angle, target, spec.settle_band * spec.rad_per_count, hold=spec.settle_hold))


def move_settle_time(spec: DeviceSpec, time_s, counts, target_counts, start: float | None = None) -> float:
    """A move's settle time (s after the command at `start`, time_s[0] by default; NaN: not settled): every
    hinge's encoder counts within the firmware's settle band of its target for settle_hold s (settle_time,
    all hinges at once)."""
    return settle_time(time_s, np.asarray(target_counts) - np.asarray(counts), spec.settle_band, spec.settle_hold,
                       start)


def move_report(spec: DeviceSpec, trace: Trace) -> MoveReport:
    """A twin's move, per hinge: settle time (s), overshoot and steady-state error (rad, of the true angle;
    the error also in counts), peak current (A).

    Settling uses the firmware's settle band in encoder counts; the step starts
    at the trace's first tick.
    """
    metrics = [hinge_metrics(spec, trace.time, float(trace.target_counts[0, k]), trace.counts[:, k],
                             float(trace.target[0, k]), trace.true_angle[:, k]) for k in range(trace.n_hinges)]
    return MoveReport(target=trace.target[0].copy(), final=trace.true_angle[-1].copy(),
                      settle_time=np.array([c.settle_time for c, _ in metrics]),
                      overshoot=np.array([a.overshoot for _, a in metrics]),
                      steady_state_error=np.array([a.steady_state_error for _, a in metrics]),
                      steady_state_error_counts=np.array([c.steady_state_error for c, _ in metrics]),
                      peak_current=np.abs(trace.current).max(axis=0))
