"""Twin calibration: fit the plant's uncertain parameters to recorded HIL runs.

Residual: replay each recorded run on the twin (the device's gains; its start,
held by the twin's firmware until the integral carries the flaps' weight as the
device's does; each target taking effect at the device time the device
acknowledged it) with candidate plant parameters, and compare with the device's
telemetry at every frame:

- the hinge angles (deg; the device's encoder angle, mid-count), and
- the duty the firmware commanded, averaged over DUTY_WINDOW s and weighted by
  DUTY_WEIGHT deg per unit duty. The duty is what makes friction observable:
  where the hinge is moving fast the duty is saturated and friction hides in 2 %
  of the stall torque; where it creeps or holds, the integral has to push the
  gravity load plus the friction, and the device reports exactly how much. The
  window averages out the stick-slip cycles, whose phase no model reproduces.

The firmware PID is in the loop, exactly as on the device, so what is fitted is
the closed loop.

Parameters (all fitted as log(value / spec value), bounded x1/3 .. x3):
    no_load_speed   sets the motor constant K (spec.motor_constant) and the
                    viscous loss (tau_stall - friction) / no_load_speed
    gear_friction   Coulomb friction at the output
    rotor_inertia   the armature, reflected by gear_ratio^2 (most of a hinge's inertia)
Not fitted, and why (docs/tuning-hil-calibration.md):
    gear_damping    no effect on motion: the spec fixes the motor by its stall torque
                    and no-load speed, so the total viscous coefficient is
                    (tau_stall - friction) / no_load_speed whatever the gear damping is
                    (it only moves the split with the back-EMF: K changes to keep the
                    datasheet's no-load speed). Only the winding current would show it,
                    by < 1 %, less than the no-load speed's own fit error.
    latency         the HIL run aligns each target with the device's own ACK time,
                    which already includes it.
    backlash        not in the twin's MJCF (spec.backlash feeds the emulator only).

Optimiser: mujoco.minimize.least_squares (Levenberg-Marquardt with box
bounds). Its residual is vectorised over columns, and each column is one twin
replay, so the finite-difference Jacobian costs n_params replays. The
finite-difference step is large (10 % in log space) on purpose: the encoder
quantises the closed loop and the hinges stick and slip, so the residual is
rough at small scales (with 3 % steps the fit stopped 10 % short of the truth). mujoco.sysid (MuJoCo 4.0; needs the mujoco[sysid] extra, absl) was read
and not used: its rollouts replay recorded controls open loop through MuJoCo's
own actuators, whereas these traces are closed loop through the firmware's PID
on quantised counts; replaying the recorded duty open loop drifts (friction and
gravity make the open-loop plant an integrator), so the residual needs our own
closed-loop replay.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from mujoco import minimize

from twin.device.spec import DeviceSpec
from twin.sim.replay import replay_targets, twin_at_start

PARAMS = ("no_load_speed", "gear_friction", "rotor_inertia")
LOG_BOUND = math.log(3.0)
DUTY_WINDOW = 0.2  # s: the duty is compared as means over windows this long
DUTY_WEIGHT = 20.0  # deg per unit duty: a 0.01 duty error weighs as 0.2 deg (each about its noise floor)


def replay(run: dict, plant: DeviceSpec, spec: DeviceSpec | None = None):
    """The twin's hinge angles (deg) and duty at the run's device frame times, with `plant` as the physics."""
    spec = spec or plant
    t = run["device"]["time_s"]
    dt = spec.firmware_dt
    end_tick = int(round(t[-1] / dt)) + 1 if len(t) else 1
    twin = twin_at_start(plant, run["gains"], run["meta"], spec)
    changes = [(c["t_s"], np.radians(c["angles_deg"])) for c in run["meta"]["changes"]]
    traces = [tr for _, tr in replay_targets(twin, changes, 0, end_tick)]
    a = np.concatenate([tr.angle for tr in traces])
    d = np.concatenate([tr.duty for tr in traces])
    idx = np.clip(np.rint(t / dt).astype(int), 0, max(len(a) - 1, 0))
    return np.degrees(a[idx]), d[idx]


def device_angles(run: dict, spec: DeviceSpec) -> np.ndarray:
    """The device's encoder angles, deg, mid-count (the encoder floors: the true angle is half a count up)."""
    return run["device"]["angle_deg"] + 0.5 * math.degrees(spec.rad_per_count)


def window_means(t, x, width: float = DUTY_WINDOW) -> np.ndarray:
    """x (frames, hinges) replaced at each frame by its mean over the frame's window of `width` s of t (s)."""
    bins = np.floor(np.asarray(t) / width).astype(int)
    bins -= bins.min()
    n = np.maximum(np.bincount(bins), 1)
    return np.stack([(np.bincount(bins, weights=x[:, k]) / n)[bins] for k in range(x.shape[1])], axis=1)


def residuals(run: dict, plant: DeviceSpec, spec: DeviceSpec) -> np.ndarray:
    """The fit's residual for one run, per frame and hinge: the angle error (deg), then the error of the
    duty's window mean x DUTY_WEIGHT."""
    angle, duty = replay(run, plant, spec)
    dev = run["device"]
    t = dev["time_s"]
    return np.concatenate([(angle - device_angles(run, spec)).ravel(),
                           DUTY_WEIGHT * (window_means(t, duty) - window_means(t, dev["duty"])).ravel()])


def trace_rmse(run: dict, plant: DeviceSpec, spec: DeviceSpec) -> np.ndarray:
    """Per-hinge RMSE, deg, between the device's hinge angles and the twin's replayed with `plant`.

    The overall figure quoted for a run is the RMS of these (every frame of every hinge alike)."""
    return np.sqrt(np.mean((replay(run, plant, spec)[0] - device_angles(run, spec)) ** 2, axis=0))


@dataclasses.dataclass
class CalibrationResult:
    spec: DeviceSpec  # calibrated
    values: dict  # parameter -> fitted value (SI)
    scales: dict  # parameter -> fitted / base
    rmse_before: float  # deg, hinge angles, all training runs, frames and hinges
    rmse_after: float
    iterations: int
    evaluations: int


def calibrate(runs: list[dict], base: DeviceSpec, params=PARAMS, max_iter: int = 25, eps: float = 0.1,
              verbose: bool = False) -> CalibrationResult:
    """Least-squares fit of `params` (log-scaled, bounded x1/3..x3) to the runs' device traces (angles and duty)."""
    params = tuple(params)
    base_vals = np.array([getattr(base, p) for p in params])
    count = [0]

    def plant(x):
        return base.replace(**{p: float(v * math.exp(xi)) for p, v, xi in zip(params, base_vals, x)})

    def residual(X):
        cols = []
        for j in range(X.shape[1]):
            cols.append(np.concatenate([residuals(r, plant(X[:, j]), base) for r in runs]))
            count[0] += 1
        return np.stack(cols, axis=1)

    def angle_rmse(p):
        return float(np.sqrt(np.mean(np.concatenate([trace_rmse(r, p, base) ** 2 for r in runs]))))

    lo, hi = np.full(len(params), -LOG_BOUND), np.full(len(params), LOG_BOUND)
    x, trace = minimize.least_squares(np.zeros(len(params)), residual, bounds=(lo, hi), eps=eps, max_iter=max_iter,
                                      verbose=minimize.Verbosity.ITER if verbose else minimize.Verbosity.SILENT,
                                      xtol=1e-4, gtol=1e-8)
    x = np.asarray(x).ravel()
    fitted = plant(x)
    return CalibrationResult(
        spec=fitted,
        values={p: float(getattr(fitted, p)) for p in params},
        scales={p: float(math.exp(xi)) for p, xi in zip(params, x)},
        rmse_before=angle_rmse(base),
        rmse_after=angle_rmse(fitted),
        iterations=len(trace),
        evaluations=count[0],
    )
