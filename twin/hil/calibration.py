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
# x the prior: how far a device may differ from its datasheet (an assumption: the spread of a batch of micro
# metal gearmotors and of their assembly). The interval a parameter the runs do not show is left with.
PRIOR_RANGE = {"no_load_speed": (0.7, 1.3), "gear_friction": (0.7, 1.6), "rotor_inertia": (0.7, 1.4)}
LOG_BOUND = math.log(3.0)
MAX_HALFWIDTH = 0.15  # a parameter is identifiable when its 95 % interval is within x(1 -+ this) of its value
CHI2_95 = 3.84  # ... and moving it that far raises the cost by more than this x the variance per independent sample
ROUGH_STEP = 0.02  # log: the cost's change over +- this is roughness (stick-slip, quantisation), not information
ROUGH_FACTOR = 1.0  # ... and the rise at the interval's edges must exceed this x that roughness
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


def residual_blocks(run: dict, plant: DeviceSpec, spec: DeviceSpec) -> tuple[np.ndarray, np.ndarray]:
    """The fit's residual for one run, per frame and hinge (frames, n): the angle error (deg), and the
    error of the duty's window mean x DUTY_WEIGHT."""
    angle, duty = replay(run, plant, spec)
    dev = run["device"]
    t = dev["time_s"]
    return angle - device_angles(run, spec), DUTY_WEIGHT * (window_means(t, duty) - window_means(t, dev["duty"]))


def residuals(run: dict, plant: DeviceSpec, spec: DeviceSpec) -> np.ndarray:
    """residual_blocks, flattened into one vector."""
    return np.concatenate([b.ravel() for b in residual_blocks(run, plant, spec)])


def trace_rmse(run: dict, plant: DeviceSpec, spec: DeviceSpec) -> np.ndarray:
    """Per-hinge RMSE, deg, between the device's hinge angles and the twin's replayed with `plant`.

    The overall figure quoted for a run is the RMS of these (every frame of every hinge alike)."""
    return np.sqrt(np.mean((replay(run, plant, spec)[0] - device_angles(run, spec)) ** 2, axis=0))


@dataclasses.dataclass
class Estimate:
    """One parameter after calibration, SI (the spec field's unit)."""

    value: float  # fitted, or the prior when not identifiable
    prior: float  # the value calibration started from (the profile's or the spec's)
    low: float  # the interval left open: the 95 % interval when fitted, the prior range when not
    high: float
    identifiable: bool
    note: str  # why it is or is not fitted, in words

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class CalibrationResult:
    spec: DeviceSpec  # calibrated
    estimates: dict  # parameter -> Estimate
    singular_values: list  # of the Jacobian of the residual in log parameters, columns scaled to unit norm
    autocorrelation_frames: float  # residual autocorrelation time the intervals allow for, frames
    rmse_before: float  # deg, hinge angles, all training runs, frames and hinges
    rmse_after: float
    iterations: int
    evaluations: int

    @property
    def values(self) -> dict:
        return {p: e.value for p, e in self.estimates.items()}

    @property
    def scales(self) -> dict:
        return {p: e.value / e.prior for p, e in self.estimates.items()}


def autocorrelation_time(blocks) -> float:
    """Integrated autocorrelation time, frames, of residual columns (each block (frames, channels)): per
    channel 1 + 2 x the sum of its autocorrelation up to the lag where it first falls below 0.05, then the
    mean over channels weighted by their energy. Frames this far apart are about independent, so a residual
    of m values holds about m / this independent samples (what the intervals allow for)."""
    taus, weights = [], []
    for block in blocks:
        for x in np.asarray(block, float).T:
            x = x - x.mean()
            e = float(x @ x)
            if e <= 0:
                continue
            f = np.fft.rfft(x, 2 * len(x))
            acf = np.fft.irfft(f * np.conj(f))[:len(x)] / e
            below = np.nonzero(acf < 0.05)[0]
            cut = int(below[0]) if len(below) else len(x)
            taus.append(1.0 + 2.0 * float(acf[1:cut].sum()))
            weights.append(e)
    return float(np.average(taus, weights=weights)) if taus else 1.0


def log_sigma(J: np.ndarray, r: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """(standard deviation of each log parameter, singular values of J with its columns scaled to unit norm).

    The Gauss-Newton covariance s^2 (J^T J)^-1, s^2 the residual's variance per independent sample
    (|r|^2 tau / (m - k)); a parameter in a direction J does not see (a singular value below 1e-9 of the
    largest) gets an infinite deviation."""
    m, k = J.shape
    s2 = float(r @ r) * tau / max(m - k, 1)
    norms = np.linalg.norm(J, axis=0)
    sv = np.linalg.svd(J / np.where(norms > 0, norms, 1.0), compute_uv=False)
    _, S, Vt = np.linalg.svd(J, full_matrices=False)
    seen = S > 1e-9 * max(float(S.max()), 1e-300)
    var = s2 * ((Vt[seen] ** 2) / S[seen, None] ** 2).sum(axis=0)
    blind = (np.abs(Vt[~seen]) > 1e-6).any(axis=0)
    return np.where(blind, np.inf, np.sqrt(var)), sv


def calibrate(runs: list[dict], base: DeviceSpec, params=PARAMS, max_iter: int = 25, eps: float = 0.1,
              max_halfwidth: float = MAX_HALFWIDTH, verbose: bool = False) -> CalibrationResult:
    """Fit `params` (log-scaled, bounded x1/3..x3 of `base`) to the runs' device traces (angles and duty),
    and say what the runs show.

    After each fit, every parameter is moved x(1 -+ max_halfwidth) and x(1 -+ ROUGH_STEP) from the optimum.
    The secants over the wider move are the Jacobian that gives its 95 % interval (Gauss-Newton, the
    residual's autocorrelation allowed for); it is identifiable when that interval is within x(1 -+
    max_halfwidth), and moving it that far raises the cost on both sides by more than the chi-square 95 %
    point (CHI2_95 x the variance per independent sample) and by more than ROUGH_FACTOR x the cost's
    change over the small move (the residual's roughness: stick-slip and encoder quantisation make the
    cost jagged, and a jagged cost can look curved to a local Jacobian). The parameters that are not are put
    back at their prior (base) and the rest fitted again, until every parameter left is identifiable. The interval reported is at least x(1 -+ eps): the residual is rough
    at scales below the finite-difference step, so the fit cannot place a parameter closer than that. A
    parameter left at its prior keeps its prior range (PRIOR_RANGE) as its interval.
    """
    params = tuple(params)
    prior = {p: float(getattr(base, p)) for p in params}
    count = [0]

    def plant(free, x):
        return base.replace(**{p: prior[p] * math.exp(float(xi)) for p, xi in zip(free, x)})

    def stack(free, X):
        cols = []
        for j in range(X.shape[1]):
            cols.append(np.concatenate([residuals(r, plant(free, X[:, j]), base) for r in runs]))
            count[0] += 1
        return np.stack(cols, axis=1)

    def angle_rmse(p):
        return float(np.sqrt(np.mean(np.concatenate([trace_rmse(r, p, base) ** 2 for r in runs]))))

    free, dropped = list(params), {}
    x, iterations, sv, tau, sigma = np.zeros(0), 0, [], 1.0, np.zeros(0)
    while free:
        k = len(free)
        x, log = minimize.least_squares(np.zeros(k), lambda X: stack(free, X),
                                        bounds=(np.full(k, -LOG_BOUND), np.full(k, LOG_BOUND)), eps=eps,
                                        max_iter=max_iter, xtol=1e-4, gtol=1e-8,
                                        verbose=minimize.Verbosity.ITER if verbose else minimize.Verbosity.SILENT)
        x = np.asarray(x).ravel()
        iterations += len(log)
        H = math.log1p(max_halfwidth)
        steps = np.concatenate([x[:, None] + H * np.eye(k), x[:, None] - H * np.eye(k),
                                x[:, None] + ROUGH_STEP * np.eye(k), x[:, None] - ROUGH_STEP * np.eye(k),
                                x[:, None]], axis=1)
        R = stack(free, steps)
        r = R[:, -1]
        J = (R[:, :k] - R[:, k:2 * k]) / (2 * H)  # secants over the interval that would count as identifiable
        cost = (R ** 2).sum(axis=0)
        rise = np.minimum(cost[:k], cost[k:2 * k]) - cost[-1]  # cost at the edges of that interval, above the fit
        rough = np.maximum(np.abs(cost[2 * k:3 * k] - cost[-1]), np.abs(cost[3 * k:4 * k] - cost[-1]))
        tau = autocorrelation_time([b for run in runs for b in residual_blocks(run, plant(free, x), base)])
        sigma, sv = log_sigma(J, r, tau)
        s2 = cost[-1] * tau / max(len(r) - k, 1)  # residual variance per independent sample
        unseen = {i: f"its 95 % interval would be x{math.exp(-1.96 * sigma[i]):.2f} .. x{math.exp(1.96 * sigma[i]):.2f}"
                  for i in range(k) if not 1.96 * sigma[i] <= H}
        unseen.update({i: f"moving it x(1 -+ {max_halfwidth:g}) raises the cost by {rise[i] / s2:.2g} (needs "
                          f"{CHI2_95:g}) or by {rise[i] / max(rough[i], 1e-300):.2g} x its change over "
                          f"+-{ROUGH_STEP:g} (needs {ROUGH_FACTOR:g})"
                       for i in range(k) if i not in unseen and not (rise[i] > CHI2_95 * s2
                                                                     and rise[i] > ROUGH_FACTOR * rough[i])})
        if not unseen:
            break
        for i in sorted(unseen, reverse=True):
            dropped[free[i]] = f"not shown by the runs: {unseen[i]}; left at its prior"
            del free[i]
    fitted = plant(free, x) if free else base
    estimates = {}
    for p in params:
        if p in free:
            i = free.index(p)
            half = max(1.96 * sigma[i], eps)
            estimates[p] = Estimate(float(getattr(fitted, p)), prior[p], prior[p] * math.exp(x[i] - half),
                                    prior[p] * math.exp(x[i] + half), True,
                                    f"fitted; 95 % interval x{math.exp(-half):.3f} .. x{math.exp(half):.3f}")
        else:
            lo, hi = PRIOR_RANGE[p]
            estimates[p] = Estimate(prior[p], prior[p], prior[p] * lo, prior[p] * hi, False,
                                    dropped.get(p, "not fitted") + f"; prior range x{lo:g} .. x{hi:g}")
    return CalibrationResult(
        spec=fitted, estimates=estimates, singular_values=[float(s) for s in sv], autocorrelation_frames=tau,
        rmse_before=angle_rmse(base), rmse_after=angle_rmse(fitted), iterations=iterations,
        evaluations=count[0])
