"""Twin calibration: fit the plant's uncertain parameters to recorded HIL runs.

Residual: replay each recorded run on the twin (the device's gains; its start,
held by the twin's firmware until the integral carries the flaps' weight as the
device's does; each target taking effect at the device time the device
acknowledged it) with candidate plant parameters, and compare with the device's
telemetry at every frame:

- the hinge angles (deg; the encoder's, mid-count, on both sides: the encoder is on
  the motor, the backlash outside the loop, and the device reports the encoder), and
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
Bounded, not fitted (twin.device.variation.BOUNDED): the cogging, the winding's
resistance and the gearbox's back-driven efficiency move the traces as the fitted
parameters do and no run tells them apart; each is held at the profile's value and
the fitted parameters' intervals are widened by what it could do within its range
(`bounded_fit`). Not fitted: latency (the HIL run aligns each target with the
device's own ACK time, which already includes it).

Search: a cross-entropy method, then a quadratic fitted to the better half of its
samples (the cost is rough at small scales, where a gradient method stalls: see
`calibrate`); the quadratic's mode is replayed and kept only where it costs no more
than the best sample, allowing for the cost's roughness (else the best sample is
kept, nothing identifiable: `fit_blocks`). The parameters are the mode of the runs' likelihood (that quadratic)
times a prior about the spec's values (log spread: half the farther end of
twin.device.variation.SPREAD), so a parameter the runs show little stays near its prior without
being held there. Each one's 95 % interval is the wider of the posterior's and a
jackknife's over the hinges' stretches of the runs. Three verdicts: identifiable
(the interval within x(1 -+ MAX_HALFWIDTH)); fitted, not identifiable (its fitted
value kept, its interval and prior range left open); left at its prior (the
hinges disagree on it beyond NOT_SHOWN of the prior's spread), the others'
intervals then widened by what it could move them within its prior range.
docs/tuning-hil-calibration.md says why mujoco.sysid is not used.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from controllers.encoder import angle_from_counts
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec
from twin.device.variation import PARAMS, SPREAD, bounded_ranges, scaled
from twin.formats.run import Run
from twin.records.calibration import Estimate
from twin.search import CrossEntropy
from twin.sim.replay import replay_batch

LOG_BOUND = math.log(3.0)
MAX_HALFWIDTH = 0.15  # a parameter is identifiable when its 95 % interval is within x(1 -+ this) of its value
NOT_SHOWN = 3.0  # a parameter whose fitted spread exceeds this many times its prior's is left at its prior
SEARCH_STD = 0.25  # log: the cross-entropy search's first spread about the prior
ELITE = 6  # samples per generation the next is drawn about
STD_FLOOR = 0.02  # log: the search's least spread (2 %: the parameters' own resolution in the cost)
DUTY_WINDOW = 0.2  # s: the duty is compared as means over windows this long
DUTY_WEIGHT = 20.0  # deg per unit duty: a 0.01 duty error weighs as 0.2 deg (each about its noise floor)
ACCEPT_ROUGHNESS = 3.0  # the fitted mode is kept when, replayed, it costs at most this many roughnesses more
# than the best sample (`fit_blocks`)
BOUNDED_SAMPLES = 2  # x the population: the replays that show how the bounded parameters trade with the fitted
JACKKNIFE_SEGMENTS = 3  # stretches of a run per hinge the jackknife leaves out: 18 groups for one run


def replays(run: Run, plants: list[DeviceSpec], spec: DeviceSpec, hinges=None, nthread: int = 0):
    """The twin's encoder angles (deg, mid-count, as device_angles) and duty at the run's device frame times,
    one twin per plant (the physics), each (plants, frames, n): the encoder, on the motor, is what the device
    reports, so the twin is read the same way (its flap angle differs by up to half the backlash, which is
    outside the loop). hinges: per plant, each hinge's own specs where they differ (a per-hinge
    calibration's), or None. The plants run together on the batch twin (twin.sim.replay.replay_batch), on
    nthread of MuJoCo's threads (0: every core)."""
    t = run.device.time
    dt = spec.firmware_dt
    end_tick = int(round(t[-1] / dt)) + 1 if len(t) else 1
    counts, duty = replay_batch(plants, run.gains, run.start, run.changes, end_tick, spec, hinges, nthread,
                                mount=run.meta.get("mount", DEFAULT_MOUNT))  # held as the device was
    idx = np.clip(np.rint(t / dt).astype(int), 0, len(counts) - 1)
    return np.degrees(angle_from_counts(spec, counts[idx] + 0.5)).swapaxes(0, 1), duty[idx].swapaxes(0, 1)


def device_angles(run: Run, spec: DeviceSpec) -> np.ndarray:
    """The device's encoder angles, deg, mid-count (the encoder floors: the true angle is half a count up)."""
    return np.degrees(run.device.angle + 0.5 * spec.rad_per_count)


def window_means(t, x, width: float = DUTY_WINDOW) -> np.ndarray:
    """x (..., frames, hinges) replaced at each frame by its mean over the frame's window of `width` s of t (s)."""
    bins = np.floor(np.asarray(t) / width).astype(int)
    bins -= bins.min()
    n = np.maximum(np.bincount(bins), 1)
    x = np.asarray(x)
    flat = np.moveaxis(x, -2, 0).reshape(len(bins), -1)
    means = np.stack([(np.bincount(bins, weights=col) / n)[bins] for col in flat.T], axis=1)
    return np.moveaxis(means.reshape(np.moveaxis(x, -2, 0).shape), 0, -2)


def residual_blocks(run: Run, plants: list[DeviceSpec], spec: DeviceSpec, hinges=None,
                    nthread: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The fit's residual for one run, per plant (`replays`), frame and hinge (plants, frames, n): the angle
    error (deg), and the error of the duty's window mean x DUTY_WEIGHT."""
    angle, duty = replays(run, plants, spec, hinges, nthread)
    t = run.device.time
    return angle - device_angles(run, spec), DUTY_WEIGHT * (window_means(t, duty) - window_means(t, run.device.duty))


def group_costs(run: Run, plants: list[DeviceSpec], spec: DeviceSpec, hinges=None, nthread: int = 0) -> np.ndarray:
    """The fit's cost (sum of squared residuals, deg^2) for one run and each plant (`replays`), split into
    groups: each hinge's, in JACKKNIFE_SEGMENTS consecutive stretches of the run ((plants, segments x n)). Their
    sum is the run's cost; the groups are what the intervals' jackknife leaves out one at a time."""
    sq = sum(b ** 2 for b in residual_blocks(run, plants, spec, hinges, nthread))
    segments = [c.sum(axis=1) for c in np.array_split(sq, JACKKNIFE_SEGMENTS, axis=1)]  # each (plants, n)
    return np.stack(segments, axis=1).reshape(len(sq), -1)


def trace_rmse(run: Run, plant: DeviceSpec, spec: DeviceSpec, hinges=None) -> np.ndarray:
    """Per-hinge RMSE, deg, between the device's hinge angles and the twin's replayed with `plant`.

    The overall figure quoted for a run is the RMS of these (every frame of every hinge alike)."""
    angle = replays(run, [plant], spec, [hinges])[0][0]
    return np.sqrt(np.mean((angle - device_angles(run, spec)) ** 2, axis=0))


def floor_deg(run: Run, spec: DeviceSpec) -> np.ndarray:
    """Per hinge, deg: the part of the angle error no parameter removes, from the encoder's resolution and the
    link's timing alone: twin and device each read a quantised encoder (a count's Delta^2 / 12 each, independent
    where the angles differ by more than a count), and each target takes effect within a firmware tick of the
    device's acknowledgement (speed x dt, uniform): sqrt(Delta^2 / 6 + mean(w^2) dt^2 / 12), w the device's
    hinge speed (rad/s, from its encoder). An estimate, not a bound: where twin and device agree within a count
    their roundings agree too and the error is smaller; stick-slip and missed edges add to it. (Replaying the
    emulator's true plant left 0.10-0.21 deg per hinge where this says 0.12-0.13.)"""
    t, angle = run.device.time, run.device.angle
    speed = np.diff(angle, axis=0) / np.maximum(np.diff(t), 1e-9)[:, None] if len(t) > 1 else np.zeros((1, angle.shape[1]))
    delta, dt = spec.rad_per_count, spec.firmware_dt
    return np.degrees(np.sqrt(delta ** 2 / 6 + np.mean(speed ** 2, axis=0) * dt ** 2 / 12))


def unexplained(rmse_deg, floor) -> np.ndarray:
    """The part of an RMSE (deg) above its floor (deg), in quadrature: what no parameter explains and the
    encoder and link do not either (0 where the RMSE is at or below the floor)."""
    return np.sqrt(np.maximum(np.asarray(rmse_deg) ** 2 - np.asarray(floor) ** 2, 0.0))


def compared_rows(before, after, floor, keys: tuple[str, str]) -> list[dict]:
    """Per hinge, two twins' RMSE on one run (deg: before, after, named by keys), its floor and what the second
    leaves unexplained: {"hinge", keys[0], keys[1], "floor_deg", "unexplained_deg"}, rounded to 1e-4 deg."""
    left = unexplained(after, floor)
    return [{"hinge": k, keys[0]: round(float(b), 4), keys[1]: round(float(a), 4), "floor_deg": round(float(f), 4),
             "unexplained_deg": round(float(u), 4)} for k, (b, a, f, u) in enumerate(zip(before, after, floor, left))]


def compared_lines(rows: list[dict], keys: tuple[str, str]) -> list[str]:
    """compared_rows' rows in words, a line per hinge: "hinge k: before -> after; floor f; unexplained u"."""
    return [f"  hinge {r['hinge']}: {r[keys[0]]:.3f} -> {r[keys[1]]:.3f}; floor {r['floor_deg']:.3f}; "
            f"unexplained {r['unexplained_deg']:.3f}" for r in rows]


def per_hinge_rmse(runs: list[Run], plant: DeviceSpec, spec: DeviceSpec, hinges=None) -> tuple[np.ndarray, np.ndarray]:
    """(RMSE, floor), each per hinge and deg, over every frame of the runs."""
    n = [len(r.device.time) for r in runs]
    rmse = np.sqrt(np.average([trace_rmse(r, plant, spec, hinges) ** 2 for r in runs], axis=0, weights=n))
    floor = np.sqrt(np.average([floor_deg(r, spec) ** 2 for r in runs], axis=0, weights=n))
    return rmse, floor


@dataclasses.dataclass
class CalibrationResult:
    spec: DeviceSpec  # calibrated
    estimates: dict  # parameter -> Estimate
    bounded: dict  # parameter -> Estimate (at its prior, its prior range): held, the intervals allow for it
    singular_values: list  # of the cost's Hessian in log parameters, scaled to a unit diagonal
    autocorrelation_frames: float  # residual autocorrelation time the intervals allow for, frames
    rmse_before: float  # deg, hinge angles, all training runs, frames and hinges
    rmse_after: float
    hinge_rmse_after: np.ndarray  # deg per hinge, all training runs (per_hinge_rmse)
    hinge_floor: np.ndarray  # deg per hinge: floor_deg over the training runs
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


def _quadratic_terms(X: np.ndarray) -> tuple[np.ndarray, list]:
    """The least-squares design matrix of a quadratic in X (samples, k): 1, x_i, x_i x_j (halved where i = j),
    and the (i, j) of each product column."""
    k = X.shape[1]
    pairs = [(i, j) for i in range(k) for j in range(i, k)]
    return np.concatenate([np.ones((len(X), 1)), X, np.stack([X[:, i] * X[:, j] * (0.5 if i == j else 1.0)
                                                            for i, j in pairs], axis=1)], axis=1), pairs


def quadratic_fit(X: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column of costs C (samples, groups) at points X (samples, k): the gradient g (groups, k) and
    Hessian H (groups, k, k) of the quadratic c0 + g.x + x.H.x / 2 that fits them best in least squares: the
    cost's shape at the scale of the samples, its roughness averaged out. The fit is linear in the costs, so
    the sum over groups is the fit of the summed cost."""
    k = X.shape[1]
    A, pairs = _quadratic_terms(X)
    coef = np.linalg.lstsq(A, C, rcond=None)[0].T  # (groups, features)
    H = np.zeros((len(coef), k, k))
    for (i, j), h in zip(pairs, coef[:, 1 + k:].T):
        H[:, i, j] = H[:, j, i] = h
    return coef[:, 1:1 + k], H


def bounded_fit(X: np.ndarray, C: np.ndarray, g: np.ndarray, H: np.ndarray, free: list, bounded: list):
    """`quadratic_fit` extended to parameters held at their prior while the search ran: per column of costs C
    (samples, groups) at points X (samples, k) where they vary, what the quadratic in the free ones (g (groups,
    len(free)), H (groups, len(free), len(free)), fitted where the held ones were at 0) leaves is fitted by the
    held ones' own terms and their products with the free ones. The free ones' quadratic is kept as it was.
    Returns the gradient (groups, k) and Hessian (groups, k, k) in all k."""
    XF, XD = X[:, free], X[:, bounded]
    kf, kd = len(free), len(bounded)
    own = [(i, j) for i in range(kd) for j in range(i, kd)]
    A = np.concatenate([np.ones((len(X), 1)), XD,
                        np.stack([XD[:, i] * XD[:, j] * (0.5 if i == j else 1.0) for i, j in own], axis=1),
                        np.stack([XF[:, i] * XD[:, j] for i in range(kf) for j in range(kd)], axis=1)], axis=1)
    known = XF @ g.T + 0.5 * np.einsum("si,gij,sj->sg", XF, H, XF)
    coef = np.linalg.lstsq(A, C - known, rcond=None)[0].T  # (groups, features)
    grads, Hs = np.zeros((len(coef), X.shape[1])), np.zeros((len(coef), X.shape[1], X.shape[1]))
    grads[:, free], grads[:, bounded] = g, coef[:, 1:1 + kd]
    for a, i in enumerate(free):
        Hs[:, i, free] = H[:, a]
    for n, (i, j) in enumerate(own):
        Hs[:, bounded[i], bounded[j]] = Hs[:, bounded[j], bounded[i]] = coef[:, 1 + kd + n]
    cross = coef[:, 1 + kd + len(own):].reshape(len(coef), kf, kd)
    for a, i in enumerate(free):
        for c, j in enumerate(bounded):
            Hs[:, i, j] = Hs[:, j, i] = cross[:, a, c]
    return grads, Hs


def roughness(X: np.ndarray, c: np.ndarray) -> float:
    """The RMS of what the best quadratic in X (samples, k) leaves of the costs c (samples,): how far a cost
    may be from the smooth shape the quadratic fit gives it."""
    A, _ = _quadratic_terms(X)
    return float(np.sqrt(np.mean((c - A @ np.linalg.lstsq(A, c, rcond=None)[0]) ** 2)))


def prior_spread(limits) -> float:
    """The prior's standard deviation of log(value / prior) for a prior range (low, high) x the prior: half
    the farther end, so the whole range lies within two of them."""
    return max(abs(math.log(r)) for r in limits) / 2.0


def posterior_mode(grad, H, xb, s2: float, spread, held) -> tuple[np.ndarray, np.ndarray]:
    """(x, covariance) of log(value / prior) that minimises the quadratic's cost / (2 s2) (the runs' negative
    log likelihood) plus the prior's sum((x / spread)^2) / 2, the `held` ones at 0 (their prior); the
    covariance the inverse of that sum's Hessian (0 for the held ones)."""
    k = len(xb)
    A, P = H / (2.0 * s2), np.diag(1.0 / np.asarray(spread) ** 2)
    F = np.array([i for i in range(k) if i not in held], int)
    M = (A + P)[np.ix_(F, F)]
    x, cov = np.zeros(k), np.zeros((k, k))
    x[F] = np.clip(np.linalg.solve(M, (A @ xb - grad / (2.0 * s2))[F]), -LOG_BOUND, LOG_BOUND)
    cov[np.ix_(F, F)] = np.linalg.inv(M)
    return x, cov


def verdicts(grads, Hs, xb, s2: float, params, prior: dict, max_halfwidth: float = MAX_HALFWIDTH,
             ranges: dict | None = None, bounded=()):
    """What the runs show: (x, {parameter: Estimate}), x the log(value / prior) of each parameter (0 where left
    at its prior), from the search's per-group quadratics (quadratic_fit about xb, the best sample) and s2, the
    residual's variance per independent sample. ranges: each parameter's prior range, (low, high) x the prior
    (default SPREAD: how far a device differs from its spec). bounded: the indices of parameters held at their
    prior from the start (BOUNDED: the runs cannot show them), each widening the others' intervals by what it
    could move them within its range. See `calibrate`."""
    ranges = ranges or {p: SPREAD[p] for p in params}
    k, n_groups = len(params), len(grads)
    grad, H = grads.sum(axis=0), Hs.sum(axis=0)
    spread = np.array([prior_spread(ranges[p]) for p in params])
    held = list(bounded)
    notes = {params[i]: "bounded, not fitted: the runs cannot show it apart from the parameters it trades with, "
                        "and the others' intervals allow for it anywhere in its range" for i in bounded}
    while True:
        x, cov = posterior_mode(grad, H, xb, s2, spread, held)
        # the jackknife: the mode with each group's cost left out, spread about their mean
        loo = np.array([posterior_mode(grad - grads[j], H - Hs[j], xb, s2, spread, held)[0] for j in range(n_groups)])
        jack = np.sqrt((n_groups - 1) / n_groups * ((loo - loo.mean(axis=0)) ** 2).sum(axis=0))
        sigma = np.maximum(np.sqrt(np.maximum(np.diag(cov), 0.0)), jack)
        weak = [i for i in range(k) if i not in held and sigma[i] > NOT_SHOWN * spread[i]]
        if not weak:
            break
        i = max(weak, key=lambda i: sigma[i] / spread[i])
        notes[params[i]] = (f"not shown by the runs: the fit's 95 % interval would be x{math.exp(-1.96 * sigma[i]):.2f} .. "
                            f"x{math.exp(1.96 * sigma[i]):.2f}, the hinges disagreeing beyond its prior; left at its prior")
        held.append(i)
    # each fitted parameter's interval (log, about x), widened by how far it would move were the held ones
    # anywhere in their prior ranges (the mode moves by -(A + P)_FF^-1 A_FD dx_D); the runs' interval (what the
    # twin with the bounded ones at their values may be) by the others held only
    lo, hi = x - 1.96 * sigma, x + 1.96 * sigma
    runs_lo, runs_hi = lo.copy(), hi.copy()
    F = np.array([i for i in range(k) if i not in held], int)
    if held and len(F):
        S = -cov[np.ix_(F, F)] @ H[np.ix_(F, held)] / (2.0 * s2)  # cov_FF is (A + P)_FF^-1
        ends = np.log([ranges[params[j]] for j in held])  # (held, 2)
        moves = np.minimum(S * ends[:, 0], S * ends[:, 1]), np.maximum(S * ends[:, 0], S * ends[:, 1])
        lo[F] += moves[0].sum(axis=1)
        hi[F] += moves[1].sum(axis=1)
        shown = [n for n, j in enumerate(held) if j not in bounded]
        runs_lo[F] += moves[0][:, shown].sum(axis=1)
        runs_hi[F] += moves[1][:, shown].sum(axis=1)
    estimates = {}
    for i, p in enumerate(params):
        lo_p, hi_p = ranges[p]
        if i in F:
            with np.errstate(over="ignore"):  # a fit the runs do not constrain: an interval of x0 .. x inf
                below, above = float(np.exp(lo[i] - x[i])), float(np.exp(hi[i] - x[i]))
            pinned = bool(max(x[i] - lo[i], hi[i] - x[i]) <= math.log1p(max_halfwidth))
            # no wider than the search's bounds: the runs were never compared with a plant beyond them
            low, high = prior[p] * math.exp(max(lo[i], -LOG_BOUND)), prior[p] * math.exp(min(hi[i], LOG_BOUND))
            runs = (prior[p] * math.exp(max(runs_lo[i], -LOG_BOUND)), prior[p] * math.exp(min(runs_hi[i], LOG_BOUND)))
            note = f"fitted; the fit's own 95 % interval x{below:.3f} .. x{above:.3f} of the fitted value"
            if not pinned:  # the fit's interval need not hold the truth where model errors load onto it
                low, high = min(low, prior[p] * lo_p), max(high, prior[p] * hi_p)
                note += (f", wider than x(1 -+ {max_halfwidth:g}): not identifiable; the fitted value kept, its "
                         f"prior range x{lo_p:g} .. x{hi_p:g} left open with it")
            if bounded:
                note += (f"; the twin's value that reproduces the runs (the bounded ones at their values) "
                         f"x{runs[0] / prior[p]:.3f} .. x{runs[1] / prior[p]:.3f}")
            estimates[p] = Estimate(prior[p] * math.exp(x[i]), prior[p], low, high, pinned, note, *runs)
        else:
            estimates[p] = Estimate(prior[p], prior[p], prior[p] * lo_p, prior[p] * hi_p, False,
                                    notes[p] + f"; prior range x{lo_p:.3g} .. x{hi_p:.3g}")
    return x, estimates


def calibrate(runs: list[Run], base: DeviceSpec, params=PARAMS, population: int = 24, generations: int = 8,
              seed: int = 0, max_halfwidth: float = MAX_HALFWIDTH, progress=None,
              bounded: dict | None = None, nthread: int = 0) -> CalibrationResult:
    """Fit `params` (log(value / base value), within x1/3 .. x3) to the runs' device traces (angles and duty),
    and say what the runs show.

    The cost (the residual's sum of squares) is rough at small scales: the encoder quantises the closed loop
    and the hinges stick and slip, so a gradient method stalls (Levenberg-Marquardt through
    mujoco.minimize.least_squares stopped after 6-10 iterations with "insufficient reduction", well short of
    the truth, on the emulator's drawn plants). So: a cross-entropy search (population x generations
    replays), then a quadratic fitted to the costs of the samples near the best (the cost's shape at the
    scale of the search, its roughness averaged out). The estimate is that quadratic's likelihood's mode with
    a prior about the spec's values (`posterior_mode`): a parameter the runs barely show stays near its
    prior, the others take what the runs say, and none is held at a prior that may be off (held there, it
    drags the ones it trades with: on the emulator's seed 1, friction drawn x1.46 and held at x1.0 pulled
    rotor inertia 20-24 % off). Each parameter's standard error is the larger of the posterior's and a
    delete-one-group jackknife's over each hinge's stretches of the runs (group_costs), which holds what the
    noise model misses (stick-slip, missed edges, a model error the hinges show differently). A parameter
    on which the groups disagree beyond NOT_SHOWN times its prior's spread is left at its prior, and each
    other's interval widened by how far it would move were that one anywhere in its prior range. A fitted
    parameter is identifiable when its interval is within x(1 -+ max_halfwidth); otherwise it keeps its
    fitted value, said so, with its prior range left open as well as its interval (a model error can load
    onto a loosely shown parameter and pull its interval off the truth: backlash, on the emulator's plants).
    bounded ({field: (low, high) x the prior}; default twin.device.variation.bounded_ranges): what the runs
    cannot show apart from `params` (the cogging, the winding's resistance, the back-driven efficiency): held at
    its prior, sampled within its range about where the search ended, each fitted parameter's interval widened
    by how far it would move were these anywhere in their ranges.
    progress(generation, best cost) is called as the search goes. Each generation's replays run together on
    the batch twin, on nthread of MuJoCo's threads (0: every core).
    """
    fitted_params = tuple(params)
    bounded = bounded_ranges(base) if bounded is None else bounded
    params = fitted_params + tuple(bounded)
    prior = {p: float(getattr(base, p)) for p in params}
    count = [0]

    def plant(x):  # x (1, k): one value per parameter, shared by every hinge
        return scaled(base, {p: math.exp(float(xi)) for p, xi in zip(params, x[0])})

    def costs(X):  # X (m, 1, k)
        count[0] += len(X)
        plants = [plant(x) for x in X]
        return np.concatenate([group_costs(r, plants, base, nthread=nthread) for r in runs], axis=1)

    def residuals(x):
        return [b[0] for run in runs for b in residual_blocks(run, [plant(x)], base, nthread=nthread)]

    def angle_rmse(p):
        return float(np.sqrt(np.mean(np.concatenate([trace_rmse(r, p, base) ** 2 for r in runs]))))

    [(x, estimates, H, tau)] = fit_blocks(costs, residuals, [len(r.device.time) for r in runs],
                                          [list(range(base.n_hinges))], params, [prior],
                                          {p: SPREAD[p] for p in fitted_params} | dict(bounded), population,
                                          generations, seed, max_halfwidth, progress,
                                          bounded=range(len(fitted_params), len(params)))
    fitted = plant(x[None])
    hinge_rmse, hinge_floor = per_hinge_rmse(runs, fitted, base)
    norms = np.sqrt(np.maximum(np.diag(H), 1e-300))
    sv = np.linalg.svd(H / np.outer(norms, norms), compute_uv=False)
    return CalibrationResult(
        spec=fitted, estimates={p: estimates[p] for p in fitted_params},
        bounded={p: estimates[p] for p in bounded}, singular_values=[float(v) for v in sv], autocorrelation_frames=tau,
        rmse_before=angle_rmse(base), rmse_after=angle_rmse(fitted), hinge_rmse_after=hinge_rmse,
        hinge_floor=hinge_floor, iterations=generations, evaluations=count[0])


def fit_blocks(costs, residuals, frames, blocks, params, priors, ranges, population, generations, seed, max_halfwidth,
               progress, bounded=()) -> list:
    """The search and the verdicts of `calibrate`, for blocks of hinges each with its own values of `params`
    (one block of every hinge: values shared; a block per hinge: each hinge's own). costs(X) takes samples X
    (m, blocks, k), log(value / prior), and gives each one's runs' group costs (group_costs, run after run;
    (m, groups)); residuals(x) takes one (blocks, k) and gives its runs' residual_blocks; frames: each run's
    number of device frames. Each block is ranked, its search distribution refitted and its verdicts made on
    its own hinges' groups. The quadratic's mode is then
    replayed and kept only where it costs no more than the best sample plus ACCEPT_ROUGHNESS x the cost's
    roughness about the quadratic; elsewhere the best sample is kept, not identifiable (`_sample_kept`: on the
    emulator, the rough cost's quadratic fit, indefinite, put its mode where the replay was no better than
    the prior). bounded: the indices of parameters held at their prior (`verdicts`): the search leaves them
    there, then BOUNDED_SAMPLES x population more replays about where it ended draw each anywhere in its prior
    range, so that the quadratic holds how they trade with the others (`bounded_fit`). Returns per block (x (k,),
    {param: Estimate}, the summed quadratic's Hessian (k, k), the residual's autocorrelation time, frames)."""
    k, n = len(params), sum(len(b) for b in blocks)
    group_hinge = np.concatenate([np.tile(np.arange(n), JACKKNIFE_SEGMENTS) for _ in frames])
    mine = [np.isin(group_hinge, b) for b in blocks]
    rng = np.random.default_rng(seed)
    search = CrossEntropy(np.zeros((len(blocks), k)), SEARCH_STD, floor=STD_FLOOR, low=-LOG_BOUND, high=LOG_BOUND)
    first = costs(search.mean[None])[0]
    best_x, best = search.mean.copy(), np.array([first[m].sum() for m in mine])
    X, G = [search.mean.copy()], [first]
    bounded = list(bounded)
    for g in range(generations):
        pop = search.draw(rng, population, first=best_x)
        pop[:, :, bounded] = 0.0  # the search moves the fitted parameters only
        drawn = costs(pop[1:])
        X.extend(pop[1:])
        G.extend(drawn)
        for b, m in enumerate(mine):
            c = np.array([best[b]] + [float(gc[m].sum()) for gc in drawn])
            order = np.argsort(c)
            if c[order[0]] < best[b]:
                best[b], best_x[b] = c[order[0]], pop[order[0], b]
            search.refit(pop[order[:ELITE]], b)
        if progress:
            progress(g, float(best.sum()))
    searched = len(X)
    if bounded:  # then how the bounded ones trade with the others: samples about where the search ended, each
        # bounded one anywhere in its range
        ends = np.log([ranges[params[i]] for i in bounded])
        extra = search.draw(rng, BOUNDED_SAMPLES * population)
        extra[:, :, bounded] = rng.uniform(ends[:, 0], ends[:, 1], (len(extra), len(blocks), len(bounded)))
        X.extend(extra)
        G.extend(costs(extra))
    X, G = np.array(X), np.array(G)
    at_best = residuals(best_x)
    spread = np.array([prior_spread(ranges[p]) for p in params])
    free = [i for i in range(k) if i not in bounded]
    n_near = max(searched // 2, 3 * (1 + len(free) * (len(free) + 3) // 2))  # the searched samples a quadratic is
    # fitted to, those nearest the best

    def posterior_cost(c, x, s2):  # the runs' negative log likelihood (c: cost) plus the prior's, at x (log)
        return c / (2.0 * s2) + 0.5 * ((x / spread) ** 2).sum(axis=-1)

    out = []
    for b, m in enumerate(mine):
        near = np.argsort(G[:searched, m].sum(axis=1))[:n_near]
        grads, Hs = quadratic_fit(X[near][:, b, free] - best_x[b, free], G[near][:, m])
        if bounded:  # the bounded ones' terms, from the samples where they vary
            grads, Hs = bounded_fit(X[searched:, b] - best_x[b], G[searched:][:, m], grads, Hs, free, bounded)
        tau = autocorrelation_time([r[:, blocks[b]] for r in at_best])
        s2 = best[b] * tau / max(sum(frames) * 2 * len(blocks[b]) - k, 1)
        x, estimates = verdicts(grads, Hs, best_x[b], s2, params, priors[b], max_halfwidth, ranges, bounded)
        out.append([x, estimates, Hs.sum(axis=0), tau, s2])
    # the acceptance test: each block's mode, replayed, against the best sample by the same posterior cost,
    # allowing for the cost's roughness (ACCEPT_ROUGHNESS x the RMS of what the quadratic leaves)
    at_modes = costs(np.array([o[0] for o in out])[None])[0]
    for b, m in enumerate(mine):
        x, estimates, _, _, s2 = out[b]
        sampled = posterior_cost(G[:searched, m].sum(axis=1), X[:searched, b], s2)  # (the bounded at their prior)
        i = int(np.argmin(sampled))
        near = np.argsort(sampled)[:n_near]
        rough = roughness(X[near, b], sampled[near])
        if posterior_cost(float(at_modes[m].sum()), x, s2) > sampled[i] + ACCEPT_ROUGHNESS * rough:
            out[b][:2] = X[i, b], _sample_kept(estimates, X[i, b], priors[b], params, ranges, bounded)
    return [tuple(o[:4]) for o in out]


def _sample_kept(estimates: dict, x, prior: dict, params, ranges: dict, bounded=()) -> dict:
    """The estimates where the quadratic's mode, replayed, cost more than the best sample (the cost too rough
    at the search's scale for a quadratic to follow): that sample's values (x, log(value / prior)), none
    identifiable, each interval the quadratic's or the prior range's, whichever is wider (as multiples of its
    value), about that sample's value, within the search's bounds, joined with the prior range; the runs'
    interval alike, not joined with it. The bounded ones (indices) keep their estimates (at their prior)."""
    kept = {params[i]: estimates[params[i]] for i in bounded}
    for p, xi in zip(params, x):
        if p in kept:
            continue
        e, value = estimates[p], prior[p] * math.exp(float(xi))
        lo_p, hi_p = ranges[p]
        # at least the prior range's width about the value, within the search's bounds, and the prior range (which
        # may reach past them: the backlash's)
        low = min(max(value * min(e.low / e.value, lo_p), prior[p] * math.exp(-LOG_BOUND)), prior[p] * lo_p)
        high = max(min(value * max(e.high / e.value, hi_p), prior[p] * math.exp(LOG_BOUND)), prior[p] * hi_p)
        runs = (max(value * min(e.runs_range[0] / e.value, lo_p), prior[p] * math.exp(-LOG_BOUND)),
                min(value * max(e.runs_range[1] / e.value, hi_p), prior[p] * math.exp(LOG_BOUND)))
        kept[p] = Estimate(value, prior[p], low, high, False,
                           f"the best of the search's samples (the fitted quadratic's mode, replayed, cost more): not "
                           f"identifiable; prior range x{lo_p:g} .. x{hi_p:g} left open", *runs)
    return kept


HINGE_PARAMS = ("no_load_speed", "gear_friction", "gear_damping", "rotor_inertia")  # what a hinge's own motor changes
HINGE_RANGE = (0.8, 1.25)  # x the shared value: how far one hinge's motor and gearbox differ from the others'
# (an assumption: micro metal gearmotors of one batch commonly differ by 10-20 % in speed and friction)


@dataclasses.dataclass
class HingeCalibration:
    """Each hinge's own values about a shared calibration (`calibrate_hinges`)."""

    hinges: list  # per hinge, its DeviceSpec (the shared one with its own values)
    estimates: list  # per hinge, {parameter: Estimate}, the prior the shared value
    rmse_before: np.ndarray  # deg per hinge, the shared twin, all training runs
    rmse_after: np.ndarray  # deg per hinge, the per-hinge twin
    floor: np.ndarray  # deg per hinge (floor_deg)
    evaluations: int


def calibrate_hinges(runs: list[Run], shared: DeviceSpec, params=HINGE_PARAMS, population: int = 24,
                     generations: int = 8, seed: int = 0, max_halfwidth: float = MAX_HALFWIDTH,
                     progress=None, shared_estimates: dict | None = None, nthread: int = 0) -> HingeCalibration:
    """Each hinge's own values of `params` about `shared` (a calibration's spec), where the runs show them:
    the search and verdicts of `calibrate` with a block per hinge (`fit_blocks`), each hinge ranked and judged on
    its own stretches of the runs, its prior the shared value within HINGE_RANGE. A hinge's parameter the runs
    do not show stays at the shared value (left at its prior). All hinges move in every replay, so what one
    hinge's flaps do to its neighbours is in every score. shared_estimates: the shared calibration's
    (`calibrate`); a hinge's interval is its own times the shared value's (an error of the shared value is in
    every hinge's), and it is identifiable only where that product is within x(1 -+ max_halfwidth). nthread: as
    `calibrate`'s."""
    params = tuple(params)
    n = shared.n_hinges
    count = [0]

    def hinges(x):  # x (n, k)
        return [scaled(shared, {p: math.exp(float(v)) for p, v in zip(params, x[h])}) for h in range(n)]

    def costs(X):  # X (m, n, k)
        count[0] += len(X)
        each = [hinges(x) for x in X]
        return np.concatenate([group_costs(r, [shared] * len(X), shared, each, nthread) for r in runs], axis=1)

    def residuals(x):
        return [b[0] for run in runs for b in residual_blocks(run, [shared], shared, [hinges(x)], nthread)]

    prior = {p: float(getattr(shared, p)) for p in params}
    fits = fit_blocks(costs, residuals, [len(r.device.time) for r in runs], [[h] for h in range(n)], params,
                      [prior] * n, {p: HINGE_RANGE for p in params}, population, generations, seed, max_halfwidth,
                      progress)
    fitted = hinges(np.array([x for x, _, _, _ in fits]))
    before, floor = per_hinge_rmse(runs, shared, shared)
    after, _ = per_hinge_rmse(runs, shared, shared, fitted)
    estimates = [{p: _with_shared(e, (shared_estimates or {}).get(p), max_halfwidth) for p, e in est.items()}
                 for _, est, _, _ in fits]
    return HingeCalibration(fitted, estimates, before, after, floor, count[0])


def _with_shared(own: Estimate, shared: Estimate | None, max_halfwidth: float) -> Estimate:
    """A hinge's estimate with the shared value's uncertainty: its interval x the shared one's (relative to
    the shared value), identifiable only where the product is still within x(1 -+ max_halfwidth); its runs'
    interval x the shared runs' interval alike."""
    if shared is None:
        return own
    lo, hi = own.low * shared.low / shared.value, own.high * shared.high / shared.value
    runs = (own.runs_range[0] * shared.runs_range[0] / shared.value,
            own.runs_range[1] * shared.runs_range[1] / shared.value)
    pinned = own.identifiable and max(own.value / lo, hi / own.value) <= 1 + max_halfwidth
    note = own.note + f"; with the shared value's interval x{lo / own.value:.3f} .. x{hi / own.value:.3f}"
    if own.identifiable and not pinned:
        note += ": not identifiable"
    return Estimate(own.value, own.prior, lo, hi, pinned, note, *runs)
