"""Comparison of a HIL run's device and twin traces: per hinge RMSE, largest error, lag and settle
times (all on encoder angles, deg, at the device's sample times)."""

from __future__ import annotations

import math

import numpy as np

from twin.device.spec import DeviceSpec
from twin.formats.trace import Recording
from twin.sim.response import step_metrics


def _lag(t, a, b, max_lag: float = 0.2) -> float:
    """Seconds by which b lags a (positive: b later), by cross-correlating their rates on a uniform grid."""
    if len(t) < 8:
        return float("nan")
    dt = float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1], dt)
    da, db = np.diff(np.interp(grid, t, a)), np.diff(np.interp(grid, t, b))
    if not np.any(da) or not np.any(db):
        return 0.0
    m = int(max_lag / dt)
    best, arg = -np.inf, 0
    for s in range(-m, m + 1):
        x, y = (da[: len(da) - s], db[s:]) if s >= 0 else (da[-s:], db[: len(db) + s])
        c = float(np.dot(x, y))
        if c > best:
            best, arg = c, s
    return arg * dt


def segment_settle(spec: DeviceSpec, t, angle_deg, target_deg, changes_t, end_t):
    """Per step segment and hinge: settle time (s) after each target change, NaN if not settled or no step."""
    band = math.degrees(spec.settle_band * spec.rad_per_count)
    out = []
    bounds = list(changes_t) + [end_t]
    for i in range(len(changes_t)):
        sel = (t >= bounds[i] - 1e-9) & (t < bounds[i + 1] - 1e-9)
        row = []
        for k in range(angle_deg.shape[1]):
            if sel.sum() < 2:
                row.append(float("nan"))
                continue
            y = angle_deg[sel, k]
            tgt = float(target_deg[sel, k][-1])
            if abs(tgt - y[0]) <= band:
                row.append(float("nan"))  # no step for this hinge here
                continue
            row.append(step_metrics(t[sel], y, tgt, band, tail=spec.settle_hold).settle_time)
        out.append(row)
    return np.array(out).reshape(len(changes_t), angle_deg.shape[1])


def compare(spec: DeviceSpec, device: Recording, twin: Recording, changes_t=(0.0,)) -> list[dict]:
    """Per hinge: RMSE and largest |device - twin| (deg, encoder angles, at the device's sample times),
    lag (s, positive: the device later than the twin), mean settle time per side over the steps."""
    t = device.time
    end = float(min(t[-1], twin.time[-1])) if len(t) and len(twin.time) else 0.0
    device, twin = device.until(end), twin.until(end)
    t = device.time
    n = device.n_hinges
    rows = []
    tw = np.degrees(np.stack([np.interp(t, twin.time, twin.angle[:, k]) for k in range(n)], axis=1))
    dv = np.degrees(device.angle)
    err = dv - tw
    s_dev = segment_settle(spec, t, dv, np.degrees(device.target), changes_t, end)
    s_twin = segment_settle(spec, twin.time, np.degrees(twin.angle), np.degrees(twin.target), changes_t, end)
    for k in range(n):
        rows.append({
            "hinge": k,
            "rmse_deg": round(float(np.sqrt(np.mean(err[:, k] ** 2))) if len(t) else float("nan"), 4),
            "max_error_deg": round(float(np.max(np.abs(err[:, k]))) if len(t) else float("nan"), 4),
            "lag_s": round(_lag(t, tw[:, k], dv[:, k]), 4),
            "settle_device_s": _nanmean(s_dev[:, k]),
            "settle_twin_s": _nanmean(s_twin[:, k]),
            "steps": int(np.sum(~np.isnan(s_dev[:, k]) | ~np.isnan(s_twin[:, k]))),
        })
    return rows


def _nanmean(a):
    a = np.asarray(a, float)
    return round(float(np.mean(a[~np.isnan(a)])), 4) if np.any(~np.isnan(a)) else float("nan")
