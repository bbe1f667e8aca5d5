"""PID tuning on the twin: robust per-hinge gains by many parallel simulations.

Goal (the default, and the only one for now): the fastest settle time (encoder
counts inside the firmware's settle band, spec [firmware] settle_band, for
settle_hold s) with overshoot under a stated limit, on the *worst* of a set of
plants, with the peak winding current under the stall current (the gate's
limit, so tuned moves are never refused), on the nominal spec and the corners of its tolerances (motor constant and
gear friction each +-tolerance %, so 4 corners + nominal = 5 plants).

Why a cross-entropy method per hinge: the hinges are driven by separate motors
and their costs separate (a hinge's settle time depends on its own gains, the
coupling through the flaps is small), so one population of candidate gain sets
is evaluated for all hinges at once (simulation i runs candidate i on every
hinge) and each hinge keeps its own elite and its own sampling distribution.
That gives six independent searches for the price of one batch. CEM needs no
gradient (the settle time is a step function of the gains: the encoder is
quantised) and its batches map directly onto TwinBatch (MuJoCo's Batch thread
pool): candidates x plants simulations per generation, in lockstep.
scipy's differential_evolution would search the 18-dimensional joint space
and could not exploit the separation.

Search space per hinge: log kp, log ki, log kd (the derivative cutoff, integral
limit, deadband and hold band stay the spec's: they are firmware structure,
not loop shaping).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

from controllers.pid import PidGains, gains_table
from twin.spec import DeviceSpec

# log-space bounds of the search, per gain (duty per count, per count-s, per count/s)
BOUNDS = {"kp": (0.003, 0.5), "ki": (0.0, 2.0), "kd": (1e-5, 0.01)}
KI_FLOOR = 1e-4  # ki is searched in log space above this; below it counts as 0


@dataclasses.dataclass
class TuneGoal:
    """What the tuner minimises: worst-plant settle time with overshoot under max_overshoot (rad)."""

    max_overshoot: float = math.radians(1.0)  # rad
    tolerance: float = 0.20  # +- fraction on motor constant and gear friction
    step: float = math.radians(30.0)  # rad, every hinge steps from flat to this
    duration: float = 0.6  # s simulated per candidate


def plant_corners(spec: DeviceSpec, tolerance: float) -> list[DeviceSpec]:
    """The nominal plant and the four corners: motor constant and gear friction each x (1 +- tolerance).

    The motor constant is derived from the no-load speed (K ~ V / (N w0)), so a
    motor constant x (1 + t) is a no-load speed / (1 + t).
    """
    plants = [spec]
    for kscale in (1 - tolerance, 1 + tolerance):
        for fscale in (1 - tolerance, 1 + tolerance):
            plants.append(spec.replace(no_load_speed=spec.no_load_speed / kscale,
                                       gear_friction=spec.gear_friction * fscale))
    return plants


def batch_step_metrics(spec: DeviceSpec, time_s: np.ndarray, angle: np.ndarray, counts: np.ndarray,
                       target: np.ndarray):
    """Settle time (s; inf when never settled) and overshoot (rad, >= 0) of (ticks, ...) step traces.

    Same definitions as twin.response.step_metrics with the settle band in
    counts (as move_report does), vectorised over every simulation and hinge.
    The step starts at time_s[0] from flat (target > 0 assumed sign-free: the
    overshoot is measured past the target in the step's direction).
    """
    tgt_counts = np.rint(target / spec.rad_per_count)
    outside = np.abs(counts - tgt_counts) > spec.settle_band  # (ticks, ...)
    ticks = outside.shape[0]
    rev = outside[::-1]
    last_out = ticks - 1 - np.argmax(rev, axis=0)  # index of the last tick outside the band
    any_out = outside.any(axis=0)
    settle = np.where(any_out, time_s[np.minimum(last_out + 1, ticks - 1)] - time_s[0], 0.0)
    hold = int(round(spec.settle_hold / spec.firmware_dt))
    settle = np.where(any_out & (last_out >= ticks - 1 - hold), np.inf, settle)  # needs settle_hold in band
    direction = np.sign(target)
    direction = np.where(direction == 0, 1.0, direction)
    overshoot = np.maximum(0.0, np.max(direction * (angle - target), axis=0))
    return settle, overshoot


@dataclasses.dataclass
class TuneResult:
    gains: list[PidGains]  # per hinge
    cost: np.ndarray  # per hinge, worst-plant cost of the chosen gains (s)
    settle: np.ndarray  # per hinge, worst-plant settle time, s
    overshoot: np.ndarray  # per hinge, worst-plant overshoot, rad
    generations: int
    simulations: int
    wall_time: float  # s
    history: list[float]  # best mean cost per generation


def cost_of(settle, overshoot, goal: TuneGoal):
    """Cost, s: settle time; + a penalty that grows with the excess overshoot; never settled = 2 x duration."""
    never = ~np.isfinite(settle)
    c = np.where(never, 2.0 * goal.duration, settle)
    excess = np.maximum(0.0, overshoot - 0.95 * goal.max_overshoot)  # 5 % margin: batch and Twin differ slightly
    return c + np.where(excess > 0, goal.duration + 10.0 * excess / goal.max_overshoot * goal.duration, 0.0)


class RobustEvaluator:
    """Evaluates candidate gain sets (one PidGains per hinge each) on every plant, with TwinBatch."""

    def __init__(self, spec: DeviceSpec, goal: TuneGoal, population: int, nthread: int = 0):
        from twin.simulation import TwinBatch

        self.spec, self.goal, self.population = spec, goal, population
        self.plants = plant_corners(spec, goal.tolerance)
        self.nplant = len(self.plants)
        nsim = population * self.nplant
        # simulation index = candidate * nplant + plant
        specs = [p for _ in range(population) for p in self.plants]
        self.batch = TwinBatch(nsim, spec, specs=specs, nthread=nthread)
        self.simulations = 0

    def evaluate(self, kp, ki, kd):
        """kp, ki, kd: (population, n_hinges). Returns worst-plant cost, settle, overshoot, each (population, n)."""
        s, g = self.spec, self.goal
        P, n = kp.shape
        base = PidGains.from_spec(s).row(s.firmware_dt)
        table = np.tile(base, (P, n, 1))
        table[..., 0], table[..., 1], table[..., 2] = kp, ki, kd
        table = np.repeat(table, self.nplant, axis=0)  # (P * nplant, n, 7)
        self.batch.set_gains(table)
        self.batch.reset()
        target = np.full(n, g.step)
        out = self.batch.run(np.tile(target, (P * self.nplant, 1)), g.duration)
        self.simulations += P * self.nplant
        settle, over = batch_step_metrics(s, out["time"], out["angle"], out["counts"],
                                          np.broadcast_to(target, out["angle"].shape[1:]))
        settle = settle.reshape(P, self.nplant, n)
        over = over.reshape(P, self.nplant, n)
        cost = cost_of(settle, over, g)
        # the gate refuses moves whose peak current passes the motor's stall current: so must the tuner
        peak = np.abs(out["current"]).max(axis=0).reshape(P, self.nplant, n)
        cost = cost + np.where(peak > s.stall_current, g.duration * (1.0 + peak / s.stall_current), 0.0)
        return cost.max(axis=1), settle.max(axis=1), over.max(axis=1)


def _to_x(kp, ki, kd):
    return np.stack([np.log(kp), np.log(np.maximum(ki, KI_FLOOR)), np.log(kd)], axis=-1)


def _from_x(x):
    kp = np.exp(np.clip(x[..., 0], *np.log(BOUNDS["kp"])))
    ki = np.exp(np.clip(x[..., 1], math.log(KI_FLOOR), math.log(BOUNDS["ki"][1])))
    ki = np.where(ki <= KI_FLOOR * 1.0001, 0.0, ki)
    kd = np.exp(np.clip(x[..., 2], *np.log(BOUNDS["kd"])))
    return kp, ki, kd


def tune(spec: DeviceSpec, goal: TuneGoal | None = None, population: int = 32, generations: int = 8,
         elite: int = 6, seed: int = 0, nthread: int = 0, start: PidGains | None = None,
         progress=None) -> TuneResult:
    """Cross-entropy search per hinge; the spec's gains are candidate 0 of the first generation.

    Returns the best gains seen per hinge (by worst-plant cost), never worse than
    the starting gains on that cost.
    """
    goal = goal or TuneGoal()
    start = start or PidGains.from_spec(spec)
    rng = np.random.default_rng(seed)
    n = spec.n_hinges
    t0 = time.perf_counter()
    ev = RobustEvaluator(spec, goal, population, nthread)
    mean = np.tile(_to_x(np.array(start.kp), np.array(start.ki), np.array(start.kd)), (n, 1))  # (n, 3)
    std = np.tile([1.0, 1.5, 1.0], (n, 1))
    best_x = mean.copy()
    best_cost = np.full(n, np.inf)
    best_settle = np.full(n, np.nan)
    best_over = np.full(n, np.nan)
    history = []
    for gen in range(generations):
        x = mean[None] + std[None] * rng.standard_normal((population, n, 3))
        if gen == 0:
            x[0] = mean  # the starting gains
        else:
            x[0] = best_x  # the incumbent, re-evaluated alongside (costs are deterministic)
        kp, ki, kd = _from_x(x)
        cost, settle, over = ev.evaluate(kp, ki, kd)
        for h in range(n):
            order = np.argsort(cost[:, h], kind="stable")
            i = order[0]
            if cost[i, h] < best_cost[h]:
                best_cost[h], best_x[h] = cost[i, h], x[i, h]
                best_settle[h], best_over[h] = settle[i, h], over[i, h]
            el = x[order[:elite], h]
            mean[h] = el.mean(axis=0)
            std[h] = np.maximum(0.7 * std[h] + 0.3 * el.std(axis=0), 0.05)
        history.append(float(best_cost.mean()))
        if progress:
            progress(gen, best_cost, time.perf_counter() - t0)
    kp, ki, kd = _from_x(best_x)
    gains = [start.replace(kp=float(kp[h]), ki=float(ki[h]), kd=float(kd[h])) for h in range(n)]
    return TuneResult(gains, best_cost, best_settle, best_over, generations, ev.simulations,
                      time.perf_counter() - t0, history)


# ---- gains files --------------------------------------------------------------------------

GAINS_FORMAT = "vrscroll-gains/1"
_UNITS = {"kp": "duty/count", "ki": "duty/(count*s)", "kd": "duty/(count/s)", "derivative_cutoff_hz": "Hz",
          "integral_limit": "duty", "deadband_duty": "duty", "hold_band_counts": "count"}


def write_gains(path, gains: list[PidGains], meta: dict | None = None) -> None:
    """A gains file (JSON, documented in docs/tuning-hil-calibration.md): one entry per hinge, units in the field names/`units`."""
    doc = {
        "format": GAINS_FORMAT,
        "units": _UNITS,
        "hinges": [{"hinge": k, "kp": g.kp, "ki": g.ki, "kd": g.kd, "derivative_cutoff_hz": g.derivative_cutoff,
                    "integral_limit": g.integral_limit, "deadband_duty": g.deadband_duty,
                    "hold_band_counts": int(g.hold_band)} for k, g in enumerate(gains)],
        **({"meta": meta} if meta else {}),
    }
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".part")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    tmp.replace(path)


def read_gains(path, n: int | None = None) -> list[PidGains]:
    """Per-hinge gains from a gains file; ValueError when malformed or for the wrong hinge count."""
    doc = json.loads(Path(path).read_text())
    if doc.get("format") != GAINS_FORMAT:
        raise ValueError(f"{path}: not a {GAINS_FORMAT} gains file")
    out = [PidGains(float(h["kp"]), float(h["ki"]), float(h["kd"]), float(h["derivative_cutoff_hz"]),
                    float(h["integral_limit"]), float(h["deadband_duty"]), int(h["hold_band_counts"]))
           for h in sorted(doc["hinges"], key=lambda h: h["hinge"])]
    if n is not None and len(out) != n:
        raise ValueError(f"{path}: gains for {len(out)} hinges, the device has {n}")
    return out


def step_report(spec: DeviceSpec, gains, step: float, duration: float = 1.5, plant: DeviceSpec | None = None):
    """move_report rows (settle s, overshoot deg, ...) of one twin step from flat to `step` rad on every hinge."""
    from twin.simulation import Twin, move_report

    twin = Twin(plant or spec, gains)
    trace = twin.move_to(np.full(spec.n_hinges, step), max_time=duration, stop_when_settled=False)
    return move_report(spec, trace), trace


def gains_rows(gains, n: int, dt: float) -> np.ndarray:
    return gains_table(gains, n, dt)
