"""Twin calibration: fit the plant's uncertain parameters to recorded HIL runs.

Residual: replay each recorded run on the twin (the device's gains, its measured
start, each target taking effect at the device time the device acknowledged it)
with candidate plant parameters, and compare the twin's hinge angles with the
device's encoder angles at every telemetry frame (deg). The firmware PID is in
the loop, exactly as on the device, so what is fitted is the closed loop.

Parameters (all fitted as log(value / base), with bounds x1/3 .. x3):
    no_load_speed   (sets the motor constant K, spec.motor_constant)
    gear_friction   (Coulomb, output side)
    gear_damping    (viscous, output side)
    rotor_inertia   (armature; optional, --armature: weakly observable at 500 Hz)
Command latency is not a parameter: the HIL run aligns each target with the
device's own ACK time, which already includes it. Backlash is not modelled by
the twin's MJCF (spec.backlash feeds the emulator only), so it is not fitted.

Optimiser: mujoco.minimize.least_squares (Levenberg-Marquardt with box
bounds). Its residual is vectorised over columns, and each column is one twin
replay (the compiled firmware loop runs a 2 s replay in ~10 ms), so the
finite-difference Jacobian costs n_params replays. The finite-difference step
is large (3 % in log space) on purpose: the encoder quantises the closed loop,
so the residual is piecewise constant at tiny scales. mujoco.sysid was read and
not used: its rollouts replay open-loop controls through MuJoCo's own
actuators (sysid_rollout over ctrl time series), whereas this device's traces
are closed-loop through the firmware's PID on quantised counts; replaying the
recorded duty open-loop drifts (friction and the integral state make it
unstable), so the residual needs our own closed-loop replay.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np

from controllers.encoder import angle_from_counts
from twin.spec import SPEC_PATH, DeviceSpec

PARAMS = ("no_load_speed", "gear_friction", "gear_damping")
ARMATURE = "rotor_inertia"
LOG_BOUND = math.log(3.0)
TRANSIENT_BAND_DEG = 2.0


def replay(run: dict, plant: DeviceSpec, spec: DeviceSpec | None = None) -> np.ndarray:
    """The twin's hinge angles (deg) at the run's device frame times, with `plant` as the physics."""
    from twin.simulation import Twin

    spec = spec or plant
    dev = run["device"]
    meta = run["meta"]
    t = dev["time_s"]
    dt = spec.firmware_dt
    end_tick = int(round(t[-1] / dt)) + 1 if len(t) else 1
    twin = Twin(plant, run["gains"])
    start = angle_from_counts(spec, np.asarray(meta["start_counts"]))
    twin.reset(np.clip(start, -spec.hinge_limit, spec.hinge_limit))
    changes = [(c["t_s"], np.radians(c["angles_deg"])) for c in meta["changes"]]
    angles = []
    tick = 0
    for i, (tc, tgt) in enumerate(changes):
        stop = min(end_tick, int(round(changes[i + 1][0] / dt)) if i + 1 < len(changes) else end_tick)
        if stop > tick:
            tr = twin.move_to(tgt, max_time=(stop - tick) * dt, stop_when_settled=False)
            angles.append(tr.angle)
            tick += len(tr.time)
    a = np.concatenate(angles) if angles else np.zeros((1, spec.n_hinges))
    idx = np.clip(np.rint(t / dt).astype(int), 0, len(a) - 1)
    return np.degrees(a[idx])


def device_angles(run: dict, spec: DeviceSpec) -> np.ndarray:
    """The device's encoder angles, deg, mid-count (the encoder floors: the true angle is half a count up)."""
    return run["device"]["angle_deg"] + 0.5 * math.degrees(spec.rad_per_count)


def trace_rmse(run: dict, plant: DeviceSpec, spec: DeviceSpec, transients_only: bool = False) -> np.ndarray:
    """Per-hinge RMSE, deg, between the device and the twin replayed with `plant` (all frames, or the transients)."""
    err = replay(run, plant, spec) - device_angles(run, spec)
    if transients_only:
        m = transient_mask(run)
        return np.array([np.sqrt(np.mean(err[m[:, k], k] ** 2)) if m[:, k].any() else np.nan
                         for k in range(err.shape[1])])
    return np.sqrt(np.mean(err ** 2, axis=0))


@dataclasses.dataclass
class CalibrationResult:
    spec: DeviceSpec  # calibrated
    values: dict  # parameter -> fitted value (SI)
    scales: dict  # parameter -> fitted / base
    rmse_before: float  # deg, all training runs and hinges
    rmse_after: float
    iterations: int
    evaluations: int


def transient_mask(run: dict, band_deg: float = TRANSIENT_BAND_DEG) -> np.ndarray:
    """(frames, hinges) True where the device is still on its way: farther than band_deg from its target."""
    dev = run["device"]
    return np.abs(dev["target_deg"] - dev["angle_deg"]) > band_deg


def calibrate(runs: list[dict], base: DeviceSpec, params=PARAMS, max_iter: int = 25, eps: float = 0.03,
              verbose: bool = False, band_deg: float = TRANSIENT_BAND_DEG, prior: float = 0.1) -> CalibrationResult:
    """Least-squares fit of `params` (log-scaled, bounded x1/3..x3) to the runs' device traces.

    Only the transients are fitted (device farther than band_deg from its target):
    at rest inside the firmware's hold band the hinge sticks wherever friction
    and the integral leave it, a stick-slip that no smooth parameter change
    reproduces and that would drown the motion in noise. `prior` (deg per unit
    of log-scale, times sqrt(samples)) pulls each parameter gently toward the
    spec, so an unobservable one (gear damping: ~4 % of the motor's back-EMF
    damping) stays put instead of wandering to a bound.
    """
    from mujoco import minimize

    params = tuple(params)
    base_vals = np.array([getattr(base, p) for p in params])
    masks = [transient_mask(r, band_deg) for r in runs]
    targets = [device_angles(r, base)[m] for r, m in zip(runs, masks)]
    count = [0]

    def plant(x):
        return base.replace(**{p: float(v * math.exp(xi)) for p, v, xi in zip(params, base_vals, x)})

    def residual(X):
        X = np.atleast_2d(X.T).T if X.ndim == 1 else X
        cols = []
        for j in range(X.shape[1]):
            p = plant(X[:, j])
            cols.append(np.concatenate([(replay(r, p, base)[m] - y) for r, y, m in zip(runs, targets, masks)]))
            count[0] += 1
        R = np.stack(cols, axis=1)
        return np.concatenate([R, prior_w * X], axis=0)  # weak prior: stay at the spec where the data say nothing

    # prior weight: a 10 % change in a parameter the data cannot see costs as much as 0.1 deg on 1 % of samples
    prior_w = prior * math.sqrt(sum(len(y) for y in targets))
    x0 = np.zeros(len(params))
    r0 = residual(x0[:, None])[:-len(params), 0]
    lo, hi = np.full(len(params), -LOG_BOUND), np.full(len(params), LOG_BOUND)
    x, trace = minimize.least_squares(x0, residual, bounds=(lo, hi), eps=eps, max_iter=max_iter,
                                      verbose=minimize.Verbosity.ITER if verbose else minimize.Verbosity.SILENT,
                                      xtol=1e-4, gtol=1e-8)
    x = np.asarray(x).ravel()
    r1 = residual(x[:, None])[:-len(params), 0]
    fitted = plant(x)
    return CalibrationResult(
        spec=fitted,
        values={p: float(getattr(fitted, p)) for p in params},
        scales={p: float(math.exp(xi)) for p, xi in zip(params, x)},
        rmse_before=float(np.sqrt(np.mean(r0 ** 2))),
        rmse_after=float(np.sqrt(np.mean(r1 ** 2))),
        iterations=len(trace),
        evaluations=count[0],
    )


# ---- writing a calibrated spec ------------------------------------------------------------------

_TO_FILE = {"rpm": lambda v: v * 60.0 / (2.0 * math.pi), "deg": math.degrees}


def write_spec(path, spec: DeviceSpec, values: dict, source: str, template=SPEC_PATH) -> None:
    """A spec TOML like the template, the fitted fields' values and sources replaced (same units)."""
    text = Path(template).read_text()
    for name, value in values.items():
        pat = re.compile(rf'^(\s*{name}\s*=\s*\{{\s*value\s*=\s*)([^,]+)(,\s*unit\s*=\s*"([^"]*)",\s*source\s*=\s*)'
                         rf'"[^"]*"', re.M)
        m = pat.search(text)
        if not m:
            raise ValueError(f"{template}: no entry for {name}")
        unit = m.group(4)
        v = _TO_FILE.get(unit, lambda x: x)(value)
        text = pat.sub(lambda mm: f'{mm.group(1)}{v:.6g}{mm.group(3)}"{source}"', text, count=1)
    text = ("# Calibrated device spec, written by `vrscroll calibrate` (see docs/tuning-hil-calibration.md).\n" + text)
    Path(path).write_text(text)
