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

Parameters (PARAMS; each fitted as log(value / prior), within x1/3 .. x3):
    no_load_speed   the motor constant and the top speed at full duty
    gear_friction   Coulomb friction at the output (gear_stiction keeps its ratio to it)
    gear_damping    viscous loss at the output
    rotor_inertia   the armature, reflected by gear_ratio^2 (most of a hinge's inertia)
    backlash        the dead zone between gearbox output and flap, outside the loop
Not fitted: latency (the HIL run aligns each target with the device's own ACK time,
which already includes it).

Search: a cross-entropy method, then a quadratic fitted to the better half of its
samples (the cost is rough at small scales, where a gradient method stalls: see
`calibrate`). The quadratic's Hessian gives each parameter's 95 % interval, the
residual's autocorrelation allowed for; a parameter the runs do not pin within
x(1 -+ MAX_HALFWIDTH) is left at its prior and reported so, with its prior range
(PRIOR_RANGE) as what calibration leaves open. docs/tuning-hil-calibration.md says
why mujoco.sysid is not used.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from twin.device.spec import DeviceSpec
from twin.sim.replay import replay_targets, twin_at_start

PARAMS = ("no_load_speed", "gear_friction", "gear_damping", "rotor_inertia", "backlash")
# the spec fields that move with a parameter, in proportion: the static friction keeps its ratio to the
# Coulomb friction (one gearbox's friction, the emulator scales them together)
MOVES_WITH = {"gear_friction": ("gear_stiction",)}
# x the prior: how far a device may differ from its datasheet (an assumption: the spread of a batch of micro
# metal gearmotors and of their assembly; the backlash 0.01 .. 0.5 deg about the spec's 0.25 deg: not 0,
# which the MJCF makes a rigid coupling, another model layout than the batch twin's other plants). The
# interval a parameter the runs do not show is left with.
PRIOR_RANGE = {"no_load_speed": (0.7, 1.3), "gear_friction": (0.7, 1.6), "gear_damping": (0.7, 1.6),
               "rotor_inertia": (0.7, 1.4), "backlash": (0.04, 2.0)}
LOG_BOUND = math.log(3.0)
MAX_HALFWIDTH = 0.15  # a parameter is identifiable when its 95 % interval is within x(1 -+ this) of its value
SEARCH_STD = 0.25  # log: the cross-entropy search's first spread about the prior
ELITE = 6  # samples per generation the next is drawn about
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
    singular_values: list  # of the cost's Hessian in log parameters, scaled to a unit diagonal
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


def quadratic_fit(X: np.ndarray, c: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(c0, gradient g, Hessian H) of the quadratic c0 + g.x + x.H.x / 2 that fits costs c at points X
    (samples, k) best in least squares: the cost's shape at the scale of the samples, its roughness
    averaged out."""
    k = X.shape[1]
    pairs = [(i, j) for i in range(k) for j in range(i, k)]
    A = np.concatenate([np.ones((len(X), 1)), X, np.stack([X[:, i] * X[:, j] * (0.5 if i == j else 1.0)
                                                         for i, j in pairs], axis=1)], axis=1)
    coef = np.linalg.lstsq(A, c, rcond=None)[0]
    H = np.zeros((k, k))
    for (i, j), h in zip(pairs, coef[1 + k:]):
        H[i, j] = H[j, i] = h
    return float(coef[0]), coef[1:1 + k], H


def calibrate(runs: list[dict], base: DeviceSpec, params=PARAMS, population: int = 24, generations: int = 8,
              seed: int = 0, max_halfwidth: float = MAX_HALFWIDTH, progress=None) -> CalibrationResult:
    """Fit `params` (log(value / base value), within x1/3 .. x3) to the runs' device traces (angles and duty),
    and say what the runs show.

    The cost (the residual's sum of squares) is rough at small scales: the encoder quantises the closed loop
    and the hinges stick and slip, so a gradient method stalls (Levenberg-Marquardt through
    mujoco.minimize.least_squares stopped after 6-10 iterations with "insufficient reduction", well short of
    the truth, on the emulator's drawn plants). So: a cross-entropy search (population x generations
    replays), then a quadratic fitted to the costs of the samples near the best (the cost's shape at the
    scale of the search, its roughness averaged out). Its Hessian H gives the covariance 2 s^2 H^-1, s^2 the
    residual's variance per independent sample (its autocorrelation allowed for), and with it each
    parameter's 95 % interval. A parameter whose interval is wider than x(1 -+ max_halfwidth), or along which
    the quadratic does not curve up, is not shown by the runs: it is put back at its prior, the least seen
    first, and the others re-estimated at the quadratic's minimum with it held there, until every parameter
    left is identifiable. progress(generation, best cost) is called as the search goes.
    """
    params = tuple(params)
    prior = {p: float(getattr(base, p)) for p in params}
    k = len(params)
    count = [0]

    def plant(x):
        return base.replace(**{f: getattr(base, f) * math.exp(float(xi)) for p, xi in zip(params, x)
                               for f in (p, *MOVES_WITH.get(p, ()))})

    def cost(x):
        count[0] += 1
        return float(sum((residuals(r, plant(x), base) ** 2).sum() for r in runs))

    def angle_rmse(p):
        return float(np.sqrt(np.mean(np.concatenate([trace_rmse(r, p, base) ** 2 for r in runs]))))

    rng = np.random.default_rng(seed)
    mean, std = np.zeros(k), np.full(k, SEARCH_STD)
    X, C = [], []
    best = (cost(mean), mean.copy())
    X.append(mean.copy())
    C.append(best[0])
    for g in range(generations):
        pop = np.clip(mean + std * rng.standard_normal((population, k)), -LOG_BOUND, LOG_BOUND)
        pop[0] = best[1]
        c = np.array([cost(x) for x in pop[1:]] + [best[0]])
        c = np.roll(c, 1)
        X.extend(pop[1:])
        C.extend(c[1:])
        order = np.argsort(c)
        if c[order[0]] < best[0]:
            best = (float(c[order[0]]), pop[order[0]].copy())
        elite = pop[order[:ELITE]]
        mean = elite.mean(axis=0)
        std = np.maximum(0.7 * std + 0.3 * elite.std(axis=0), 0.02)
        if progress:
            progress(g, best[0])
    X, C = np.array(X), np.array(C)
    near = np.argsort(C)[:max(len(C) // 2, 3 * (1 + k + k * (k + 1) // 2))]
    xb = best[1]
    _, grad, H = quadratic_fit(X[near] - xb, C[near])
    tau = autocorrelation_time([b for run in runs for b in residual_blocks(run, plant(xb), base)])
    m = sum(len(r["device"]["time_s"]) for r in runs) * 2 * base.n_hinges
    s2 = best[0] * tau / max(m - k, 1)

    free, dropped = list(range(k)), {}
    x, sigma = np.zeros(k), np.full(k, np.inf)
    while free:
        F, D = np.array(free), np.setdiff1d(np.arange(k), free)
        x = np.zeros(k)  # the dropped ones at their prior: 0
        # minimum of the quadratic (about xb) over the free parameters, the dropped ones held at 0
        HFF = H[np.ix_(F, F)]
        rhs = -(grad[F] - H[np.ix_(F, D)] @ xb[D])
        curved = np.all(np.linalg.eigvalsh(HFF) > 0)
        if curved:
            x[F] = np.clip(xb[F] + np.linalg.solve(HFF, rhs), -LOG_BOUND, LOG_BOUND)
            cov = 2.0 * s2 * np.linalg.inv(HFF)
            sigma = np.full(k, np.inf)
            sigma[F] = np.sqrt(np.maximum(np.diag(cov), 0.0))
        else:
            x[F] = xb[F]
            sigma = np.full(k, np.inf)
            sigma[F] = [math.sqrt(2.0 * s2 / H[i, i]) if H[i, i] > 0 else np.inf for i in F]
        wide = [i for i in free if not 1.96 * sigma[i] <= math.log1p(max_halfwidth)]
        if curved and not wide:
            break
        i = max(wide or free, key=lambda i: sigma[i])
        dropped[params[i]] = (f"not shown by the runs: its 95 % interval would be x{math.exp(-1.96 * sigma[i]):.2f} .. "
                              f"x{math.exp(1.96 * sigma[i]):.2f}" if math.isfinite(sigma[i]) else
                              "not shown by the runs: the cost does not curve up along it") + "; left at its prior"
        free.remove(i)
    if not free:
        x = np.zeros(k)
    fitted = plant(x)
    estimates = {}
    for i, p in enumerate(params):
        if i in free:
            half = 1.96 * sigma[i]
            estimates[p] = Estimate(float(getattr(fitted, p)), prior[p], prior[p] * math.exp(x[i] - half),
                                    prior[p] * math.exp(x[i] + half), True,
                                    f"fitted; 95 % interval x{math.exp(-half):.3f} .. x{math.exp(half):.3f}")
        else:
            lo, hi = PRIOR_RANGE[p]
            estimates[p] = Estimate(prior[p], prior[p], prior[p] * lo, prior[p] * hi, False,
                                    dropped.get(p, "not fitted") + f"; prior range x{lo:g} .. x{hi:g}")
    norms = np.sqrt(np.maximum(np.diag(H), 1e-300))
    sv = np.linalg.svd(H / np.outer(norms, norms), compute_uv=False)
    return CalibrationResult(
        spec=fitted, estimates=estimates, singular_values=[float(v) for v in sv], autocorrelation_frames=tau,
        rmse_before=angle_rmse(base), rmse_after=angle_rmse(fitted), iterations=generations,
        evaluations=count[0])
