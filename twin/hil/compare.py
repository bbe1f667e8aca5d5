"""Comparison of a HIL run's device and twin traces: per hinge RMSE, largest error, lag and settle
times (all on encoder angles, deg, at the device's sample times)."""

from __future__ import annotations

import math

import numpy as np

from twin.device.spec import DeviceSpec
from twin.records.trace import Trace
from twin.sim.response import step_metrics

# compare()'s per-hinge metrics: (key, column label, what it means), for reports and the command line
METRICS = (
    ("rmse_deg", "RMSE deg", "root mean square of device - twin over the run, deg (encoder angles, at the device's "
                             "sample times)"),
    ("max_error_deg", "largest error deg", "largest |device - twin| over the run, deg"),
    ("lag_s", "lag s", "time by which the device follows the twin (cross-correlation of their rates), s; > 0: "
                       "the device is later"),
    ("settle_device_s", "mean settle time device s", "the device's settle time (docs/device.md) after each target "
                                                     "change that moves this hinge, averaged over those steps, s"),
    ("settle_twin_s", "mean settle time twin s", "the same for the twin, s"),
    ("overshoot_device_deg", "largest overshoot device deg", "the furthest the device went past a step's target, "
                                                             "over the steps, deg"),
    ("overshoot_twin_deg", "largest overshoot twin deg", "the same for the twin, deg"),
)
# deg: a hinge whose device-twin RMSE over a run is above this did not follow the twin at all (a zero confirmed
# while the flaps hung, a wiring mistake, a flap that met something): far beyond what calibration explains (an
# uncalibrated twin's held-out error on the emulator's drawn plants: 0.2-0.9 deg)
NOT_FOLLOWED_DEG = 5.0


def not_followed(rows: list[dict]) -> str | None:
    """compare()'s rows -> a warning naming the hinges whose RMSE is above NOT_FOLLOWED_DEG and what to check,
    or None where every hinge followed the twin."""
    far = [r for r in rows if r["rmse_deg"] > NOT_FOLLOWED_DEG]
    if not far:
        return None
    return ("the device did not follow the twin on hinge(s) " + ", ".join(
        f"{r['hinge']} ({r['rmse_deg']:.1f} deg RMS)" for r in far) + f", beyond {NOT_FOLLOWED_DEG:g} deg: no "
            "calibration explains that. Check the zero (confirmed with the flaps lying flat: `vrscroll zero`), the "
            "wiring (`vrscroll bringup`) and that no flap met something; a run like this one is no use to "
            "`vrscroll calibrate`")


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


def segment_steps(spec: DeviceSpec, t, angle_deg, target_deg, changes_t, end_t):
    """Per step segment and hinge: (settle time s, overshoot deg) after each target change (step_metrics on
    the encoder angle, the settle band in deg), NaN where the hinge did not step there (or, for the settle
    time, did not settle)."""
    band = math.degrees(spec.settle_band * spec.rad_per_count)
    settle, over = np.full((len(changes_t), angle_deg.shape[1]), np.nan), np.full((len(changes_t), angle_deg.shape[1]), np.nan)
    bounds = list(changes_t) + [end_t]
    for i in range(len(changes_t)):
        sel = (t >= bounds[i] - 1e-9) & (t < bounds[i + 1] - 1e-9)
        if sel.sum() < 2:
            continue
        for k in range(angle_deg.shape[1]):
            y = angle_deg[sel, k]
            tgt = float(target_deg[sel, k][-1])
            if abs(tgt - y[0]) <= band:
                continue  # no step for this hinge here
            m = step_metrics(t[sel], y, tgt, band, hold=spec.settle_hold, start=bounds[i])
            settle[i, k], over[i, k] = m.settle_time, m.overshoot
    return settle, over


def compare(spec: DeviceSpec, device: Trace, twin: Trace, changes_t=(0.0,)) -> list[dict]:
    """Per hinge: RMSE and largest |device - twin| (deg, encoder angles, at the device's sample times),
    lag (s, positive: the device later than the twin), mean settle time and largest overshoot per side over the
    steps (METRICS says each)."""
    t = device.time
    end = float(min(t[-1], twin.time[-1])) if len(t) and len(twin.time) else 0.0
    device, twin = device.until(end), twin.until(end)
    t = device.time
    n = device.n_hinges
    rows = []
    tw = np.degrees(np.stack([np.interp(t, twin.time, twin.angle[:, k]) for k in range(n)], axis=1))
    dv = np.degrees(device.angle)
    err = dv - tw
    s_dev, o_dev = segment_steps(spec, t, dv, np.degrees(device.target), changes_t, end)
    s_twin, o_twin = segment_steps(spec, twin.time, np.degrees(twin.angle), np.degrees(twin.target), changes_t, end)
    for k in range(n):
        rows.append({
            "hinge": k,
            "rmse_deg": round(float(np.sqrt(np.mean(err[:, k] ** 2))) if len(t) else float("nan"), 4),
            "max_error_deg": round(float(np.max(np.abs(err[:, k]))) if len(t) else float("nan"), 4),
            "lag_s": round(_lag(t, tw[:, k], dv[:, k]), 4),
            "settle_device_s": _nanmean(s_dev[:, k]),
            "settle_twin_s": _nanmean(s_twin[:, k]),
            "overshoot_device_deg": _nanmax(o_dev[:, k]),
            "overshoot_twin_deg": _nanmax(o_twin[:, k]),
            "steps": int(np.sum(~np.isnan(s_dev[:, k]) | ~np.isnan(s_twin[:, k]))),
        })
    return rows


def _nanmean(a):
    a = np.asarray(a, float)
    return round(float(np.mean(a[~np.isnan(a)])), 4) if np.any(~np.isnan(a)) else float("nan")


def _nanmax(a):
    a = np.asarray(a, float)
    return round(float(np.max(a[~np.isnan(a)])), 4) if np.any(~np.isnan(a)) else float("nan")


def metrics_text(rows: list[dict], first: str = "hinge") -> str:
    """compare()'s rows as a text table, a column per METRICS entry, labelled with its unit."""
    lines = [f"{first:>5} " + " ".join(f"{label:>8}" for _, label, _ in METRICS)]
    for r in rows:
        lines.append(f"{r['hinge']:>5} " + " ".join(f"{r[key]:>{max(len(label), 8)}.{4 if key == 'lag_s' else 3}f}"
                                                   for key, label, _ in METRICS))
    return "\n".join(lines)
