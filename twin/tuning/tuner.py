"""PID tuning on the twin: robust per-hinge gains by many parallel simulations.

Goal (the default, and the only one for now): the fastest settle time with
overshoot under a stated limit, on the *worst* of a set of plants: the nominal
spec and the corners of the parameter ranges it is tuned over: the intervals
calibration left open (a device profile's), or, uncalibrated, motor constant
and gear friction each +-tolerance % (4 corners + nominal = 5 plants). Every candidate is scored
with the report's own metrics (twin.sim.response.hinge_metrics, i.e.
twin.sim.response.step_metrics) over the same window as the report (the goal's
duration), and must also pass the gate's current checks as the gate makes them
(peak winding current within the driver's peak rating, mean current over the
last settle_hold s within the continuous rating), so the goal is met by
construction and tuned moves are never refused.

Why a cross-entropy method per chain of hinges: the root flap is held, so the
hinges left of it and those right of it are two chains that move each other only
through the pack they share (on a stiff pack the left chain's angles are the same
to 1e-15 rad whatever the right chain's gains; with the pack's sag, within
0.7 deg on a 30 deg step). Each chain is ranked on its own hinges' costs, and
every candidate is simulated with both chains together, so that coupling is in
every score. Within a chain they are not independent: each hinge carries the flaps
beyond it, and a hinge's overshoot changed by up to 0.6 deg with its
neighbours' gains, so gains picked per hinge from different candidates
misbehaved together. So one population of candidate gain sets is evaluated for
both chains at once (simulation i runs candidate i on every hinge), and each
chain keeps its own elite and sampling distribution, ranked by the sum of its
hinges' costs: two searches for the price of one batch. CEM needs no gradient
(the settle time is a step function of the gains: the encoder is quantised) and
its batches map directly onto TwinBatch (MuJoCo's Batch thread pool):
candidates x plants simulations per generation, in lockstep.

Search space per hinge: log kp, log ki, log kd (the derivative cutoff, integral
limit, deadband and hold band stay the spec's: they are firmware structure,
not loop shaping).

What is returned: the best whole gain set the search evaluated, every hinge's gains from one
simulation, ranked first by how many hinges break a limit on their worst plant, then by the sum of
the costs. The chains' bests, taken from different candidates, are also put together and evaluated
once more, and win only where that evaluation ranks first (the chains move each other a little
through the pack, so their sum is not the evaluation's). Where a hinge breaks a limit on its worst
plant even so, the result says which limit on which plant, and for every hinge which parameter's
range sets its worst case (`range_sensitivity`: each range's ends, one at a time).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from controllers.core import per_hinge
from controllers.encoder import target_counts
from controllers.pid import PidGains
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec
from twin.device.variation import Plant, at_ends, corners, tolerance_ranges
from twin.records.ranges import Ranges
from twin.search import CrossEntropy
from twin.sim.batch import TwinBatch
from twin.sim.gate import current_limits
from twin.sim.response import hinge_metrics, move_report
from twin.sim.twin import Twin

# log-space bounds of the search, per gain (duty per count, per count-s, per count/s)
BOUNDS = {"kp": (0.003, 0.5), "ki": (0.0, 2.0), "kd": (1e-5, 0.01)}
KI_FLOOR = 1e-4  # ki is searched in log space above this; below it counts as 0
STD_FLOOR = 0.05  # log gain: the search's least spread (5 %: finer than the encoder's quantisation shows)


@dataclasses.dataclass
class TuneGoal:
    """What the tuner minimises: worst-plant settle time with overshoot under max_overshoot (rad), over the
    plants `ranges` spans (twin.records.ranges.Ranges), e.g. the intervals calibration left open
    (twin.records.profile.Profile.ranges); None: +-tolerance on motor constant and gear friction. With
    `hinges`, every plant gives each hinge its own values, at its own intervals' corners (variation.corners).
    mount: how the device is held (twin.device.mount): every plant's twin is held so."""

    max_overshoot: float = math.radians(1.0)  # rad
    tolerance: float = 0.20  # +- fraction on motor constant and gear friction, where no ranges are given
    step: float = math.radians(30.0)  # rad, every hinge steps from flat to this
    duration: float = 1.0  # s simulated per candidate: the window of the tuner's and the report's metrics
    ranges: Ranges | None = None  # the plants' intervals, SI (each hinge's own where it has them)
    hinges: tuple | None = None  # each hinge's own spec (a per-hinge calibration's), or None: all the spec's
    mount: str = DEFAULT_MOUNT

    def plant_ranges(self, spec: DeviceSpec) -> Ranges:
        """The ranges tuned over: the goal's, or +-tolerance about the spec's motor constant and gear friction."""
        return self.ranges or tolerance_ranges(spec, self.tolerance)


def profile_goal(profile, max_overshoot: float, tolerance: float, step: float, duration: float) -> TuneGoal:
    """The goal over a device profile's plants (twin.records.profile.Profile): the twin's values that reproduce
    its calibration's runs (Profile.ranges; uncalibrated, motor constant and gear friction +-tolerance about its
    spec), each hinge its own plant and intervals where it was calibrated per hinge (Profile.hinges), held as the
    profile says. max_overshoot, step rad; duration s."""
    return TuneGoal(max_overshoot, tolerance, step, duration,
                    profile.ranges(tolerance_ranges(profile.spec, tolerance)),
                    None if profile.hinges is None else tuple(profile.hinges), profile.mount)


def step_scores(spec: DeviceSpec, out: dict, target: np.ndarray) -> dict:
    """Per simulation and hinge, from TwinBatch.run's output of a step to target (rad, (n,)):

    settle (s, inf when not settled at the window's end), overshoot (rad), peak
    current (A) and hold current (A, mean |current| over the last settle_hold s),
    each (nsim, n). Settle and overshoot are the report's (hinge_metrics).
    """
    t, angle, counts, current = out["time"], out["angle"], out["counts"], out["current"]
    _, nsim, n = angle.shape
    tc = target_counts(spec, target)
    settle, over = np.zeros((nsim, n)), np.zeros((nsim, n))
    for i in range(nsim):
        for h in range(n):
            c, a = hinge_metrics(spec, t, float(tc[h]), counts[:, i, h], float(target[h]), angle[:, i, h])
            settle[i, h] = c.settle_time if math.isfinite(c.settle_time) else math.inf
            over[i, h] = a.overshoot
    hold = int(round(spec.settle_hold / spec.firmware_dt))
    return {"settle": settle, "overshoot": over, "peak_current": np.abs(current).max(axis=0),
            "hold_current": np.abs(current[-hold:]).mean(axis=0)}


def cost_of(scores: dict, spec: DeviceSpec, goal: TuneGoal) -> np.ndarray:
    """Cost, s: the settle time when every limit holds (always < duration); else duration + a penalty
    growing with the relative excess over the overshoot, peak current and hold current limits."""
    settle = scores["settle"]
    c = np.where(np.isfinite(settle), settle, goal.duration)
    excess = sum(np.maximum(0.0, scores[k] / limit - 1.0) for k, limit in limits(spec, goal).items())
    bad = (excess > 0) | ~np.isfinite(settle)
    return c + np.where(bad, goal.duration * (1.0 + 10.0 * excess), 0.0)


def limits(spec: DeviceSpec, goal: TuneGoal) -> dict:
    """Each limit a tuned step keeps, by the step_scores key it bounds: overshoot (rad), peak and holding
    current (A, the gate's: twin.sim.gate.current_limits)."""
    peak, hold = current_limits(spec)
    return {"overshoot": goal.max_overshoot, "peak_current": peak, "hold_current": hold}


LIMIT_WORDS = {  # a limit's score in words, in the command line's units
    "overshoot": lambda x: f"overshoots {math.degrees(x):.2f} deg",
    "peak_current": lambda x: f"peak current {x:.2f} A",
    "hold_current": lambda x: f"holding current {x:.2f} A",
}


def broken_limits(scores: dict, spec: DeviceSpec, goal: TuneGoal) -> list[str]:
    """The limits one simulation's hinge breaks, as words: scores are one (simulation, hinge)'s step_scores."""
    out = [f"does not settle within {goal.duration:g} s"] if not math.isfinite(scores["settle"]) else []
    for k, limit in limits(spec, goal).items():
        if scores[k] > limit:
            shown = math.degrees(limit) if k == "overshoot" else limit
            out.append(f"{LIMIT_WORDS[k](scores[k])} (limit {shown:g})")
    return out


@dataclasses.dataclass
class TuneResult:
    gains: list[PidGains]  # per hinge
    cost: np.ndarray  # per hinge, worst-plant cost of the chosen gains (s; < duration: every limit met)
    settle: np.ndarray  # per hinge, worst-plant settle time, s
    overshoot: np.ndarray  # per hinge, worst-plant overshoot, rad
    peak_current: np.ndarray  # per hinge, worst-plant peak winding current, A
    generations: int
    simulations: int
    wall_time: float  # s
    history: list[float]  # the best whole candidate's total cost (sum over hinges, s) after each generation
    worst_plant: list[str]  # per hinge, the plant its worst case is on, in words
    broken: list[str]  # per hinge that breaks a limit on a plant: "hinge k: <limits> (over the plants; worst on <plant>)"
    sensitivity: list[dict]  # per hinge, range_sensitivity's row


class RobustEvaluator:
    """Evaluates candidate gain sets (one PidGains per hinge each) on every plant, with TwinBatch."""

    def __init__(self, spec: DeviceSpec, goal: TuneGoal, population: int, nthread: int = 0, base=None,
                 backend=None, plants=None):
        """base: the gains whose kp, ki, kd the candidates replace (one PidGains or one per hinge; default the
        spec's): their derivative cutoff, integral limit, deadband and hold band are kept. backend: None runs
        every plant here in one TwinBatch; a twin.evaluation.backends backend runs each plant's batch as a
        task on its workers (the same numbers). plants: the plants (variation.Plant) to evaluate on; default
        the nominal and the corners of the goal's ranges."""
        self.spec, self.goal, self.population = spec, goal, population
        self.base = per_hinge(base or PidGains.from_spec(spec), spec.n_hinges)
        self.plants = plants or corners(spec, goal.plant_ranges(spec), goal.hinges)
        self.nplant = len(self.plants)
        self.backend = backend
        if backend is None:  # simulation index = candidate * nplant + plant
            every = [p for _ in range(population) for p in self.plants]
            self.batch = TwinBatch(population * self.nplant, spec, specs=[p.spec for p in every],
                                   hinges=[p.hinges for p in every], nthread=nthread, mount=goal.mount)
        self.simulations = 0

    def costs(self, kp, ki, kd):
        """kp, ki, kd: (population, n_hinges). Returns the cost (cost_of) and scores (step_scores) on every
        plant, each (population, nplant, n)."""
        s, g = self.spec, self.goal
        P, n = kp.shape
        candidates = [[self.base[h].replace(kp=float(kp[c, h]), ki=float(ki[c, h]), kd=float(kd[c, h])) for h in range(n)]
                      for c in range(P)]
        target = np.full(n, g.step)
        if self.backend is None:
            self.batch.set_gains([g for g in candidates for _ in range(self.nplant)])
            self.batch.reset()
            out = self.batch.run(np.tile(target, (P * self.nplant, 1)), g.duration)
            scores = {k: v.reshape(P, self.nplant, n) for k, v in step_scores(s, out, target).items()}
        else:
            per_plant = dict(self.backend.map(plant_scores, [(s, p, g, candidates) for p in self.plants]))
            scores = {k: np.stack([per_plant[i][k] for i in range(self.nplant)], axis=1) for k in per_plant[0]}
        self.simulations += P * self.nplant
        return cost_of(scores, s, g), scores

    def evaluate(self, kp, ki, kd):
        """kp, ki, kd: (population, n_hinges). Returns the worst-plant cost and each score's worst over the plants,
        each (population, n), with "plant": the index of the plant with the highest cost (where a limit is
        broken, one that breaks it: a broken limit costs more than any kept)."""
        cost, scores = self.costs(kp, ki, kd)
        worst = {k: v.max(axis=1) for k, v in scores.items()}
        return cost.max(axis=1), {**worst, "plant": cost.argmax(axis=1)}


_PLANT_BATCHES: dict = {}  # per worker process: (plant, population) -> TwinBatch


def plant_scores(task) -> dict:
    """A backend task: (spec, plant, goal, candidates) -> step_scores of every candidate on one plant
    (variation.Plant), each (population, n); the firmware is the spec's, the physics the plant's."""
    spec, plant, goal, candidates = task
    key = (plant, len(candidates))
    if key not in _PLANT_BATCHES:
        _PLANT_BATCHES[key] = TwinBatch(len(candidates), spec, specs=[plant.spec] * len(candidates),
                                        hinges=[plant.hinges] * len(candidates), nthread=1, mount=goal.mount)
    batch = _PLANT_BATCHES[key]
    batch.set_gains(candidates)
    batch.reset()
    target = np.full(spec.n_hinges, goal.step)
    return step_scores(spec, batch.run(np.tile(target, (len(candidates), 1)), goal.duration), target)


def _to_x(kp, ki, kd):
    return np.stack([np.log(kp), np.log(np.maximum(ki, KI_FLOOR)), np.log(kd)], axis=-1)


def _from_x(x):
    kp = np.exp(np.clip(x[..., 0], *np.log(BOUNDS["kp"])))
    ki = np.exp(np.clip(x[..., 1], math.log(KI_FLOOR), math.log(BOUNDS["ki"][1])))
    ki = np.where(ki <= KI_FLOOR * 1.0001, 0.0, ki)
    kd = np.exp(np.clip(x[..., 2], *np.log(BOUNDS["kd"])))
    return kp, ki, kd


def chains(spec: DeviceSpec) -> list[list[int]]:
    """The hinges in two kinematic chains: those left of the root flap and those right of it.

    The root flap is held, so the chains do not move each other (only flap contact
    could couple them); within a chain every hinge carries the flaps beyond it.
    """
    return [list(range(spec.root_flap)), list(range(spec.root_flap, spec.n_hinges))]


def _rank(cost: np.ndarray, duration: float) -> tuple[int, float]:
    """A whole candidate's rank from its per-hinge worst-plant costs: (hinges breaking a limit, total cost)."""
    return int(np.sum(cost >= duration)), float(cost.sum())


def tune(spec: DeviceSpec, goal: TuneGoal | None = None, population: int = 32, generations: int = 8,
         elite: int = 6, seed: int = 0, nthread: int = 0, start=None,
         progress=None, backend=None) -> TuneResult:
    """Cross-entropy search per chain of hinges, on the sum of the chain's worst-plant costs; returns the best
    whole candidate evaluated (module docstring).

    The starting gains (start: one PidGains or one per hinge; default the spec's) are candidate 0 of the
    first generation, so the result is never worse than them; from then on candidate 0 is the chains' best
    found so far. backend: where the plants' batches run (RobustEvaluator). progress(generation, per-hinge
    cost of the best whole candidate so far, wall s).
    """
    goal = goal or TuneGoal()
    n = spec.n_hinges
    start = per_hinge(start or PidGains.from_spec(spec), n)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    ev = RobustEvaluator(spec, goal, population, nthread, start, backend=backend)
    search = CrossEntropy(_to_x(*(np.array([getattr(g, k) for g in start]) for k in ("kp", "ki", "kd"))),
                          np.tile([0.5, 1.0, 0.7], (n, 1)), floor=STD_FLOOR)  # (n, 3) in log gains
    best_x, best_cost = search.mean.copy(), np.full(n, math.inf)  # per chain: its best, from any candidate
    whole = None  # (rank, x, cost, worst): the best whole candidate evaluated
    history = []
    for gen in range(generations):
        x = search.draw(rng, population, first=best_x)  # gen 0's first: the starting gains
        cost, worst = ev.evaluate(*_from_x(x))
        for c in range(population):
            rank = _rank(cost[c], goal.duration)
            if whole is None or rank < whole[0]:
                whole = (rank, x[c].copy(), cost[c], {k: v[c] for k, v in worst.items()})
        for hinges in chains(spec):
            total = cost[:, hinges].sum(axis=1)
            order = np.argsort(total, kind="stable")
            if total[order[0]] < best_cost[hinges].sum():
                best_x[hinges], best_cost[hinges] = x[order[0], hinges], cost[order[0], hinges]
            search.refit(x[order[:elite]], hinges)
        history.append(whole[0][1])
        if progress:
            progress(gen, whole[2], time.perf_counter() - t0)
    final = RobustEvaluator(spec, goal, 1, nthread, start, backend=backend)
    cost, worst = final.evaluate(*(v[None] for v in _from_x(best_x)))  # the chains' bests, put together
    if _rank(cost[0], goal.duration) < whole[0]:
        whole = (_rank(cost[0], goal.duration), best_x, cost[0], {k: v[0] for k, v in worst.items()})
    _, x, cost, worst = whole
    kp, ki, kd = _from_x(x)
    gains = [start[h].replace(kp=float(kp[h]), ki=float(ki[h]), kd=float(kd[h])) for h in range(n)]
    names = [plant_name(spec, p) for p in ev.plants]
    broken = [f"hinge {h}: " + ", ".join(words) + f" (over the plants; worst on {names[worst['plant'][h]]})"
              for h in range(n)
              if (words := broken_limits({k: v[h] for k, v in worst.items()}, spec, goal))]
    sensitivity, simulations = range_sensitivity(spec, goal, gains, nthread, backend)
    return TuneResult(gains, cost, worst["settle"], worst["overshoot"], worst["peak_current"], generations,
                      ev.simulations + final.simulations + simulations, time.perf_counter() - t0, history,
                      [names[p] for p in worst["plant"]], broken, sensitivity)


def tuned_summary(goal: TuneGoal, result: TuneResult, stated: dict) -> dict:
    """What a tuning found, as JSON (a gains file's meta, `vrscroll tune --json`): the goal (`stated`: as the
    command line gave it, deg and s; its ranges SI) and, per hinge, the worst plant's numbers."""
    pairs = (lambda ranges: {p: [float(lo), float(hi)] for p, (lo, hi) in ranges.items()})
    ranges = goal.ranges
    return {"goal": {**stated, "ranges": pairs(ranges.shared) if ranges else {},
                     **({"hinge_ranges": [pairs(row) for row in ranges.hinges]} if ranges and ranges.hinges else {})},
            "worst_plant_settle_s": [round(float(x), 4) for x in result.settle],
            "worst_plant_overshoot_deg": [round(math.degrees(x), 4) for x in result.overshoot],
            "worst_plant_peak_current_A": [round(float(x), 3) for x in result.peak_current],
            "worst_plant": result.worst_plant, "limits_broken": result.broken, "worst_case_range": result.sensitivity,
            "simulations": result.simulations, "wall_time_s": round(result.wall_time, 2)}


def plant_name(spec: DeviceSpec, plant: Plant) -> str:
    """A plant in words: "nominal", or the fields its shared spec changes with their factor, e.g.
    "no_load_speed x0.83, gear_friction x1.2" (each hinge's own values, where it has them, at the same ends
    of their own ranges)."""
    plant = plant.spec
    changed = [f"{f.name} x{getattr(plant, f.name) / getattr(spec, f.name):.3g}" for f in dataclasses.fields(spec)
               if isinstance(getattr(spec, f.name), float) and getattr(spec, f.name) != 0
               and not math.isclose(getattr(plant, f.name), getattr(spec, f.name), rel_tol=1e-9)]
    return ", ".join(changed) or "nominal"


def range_sensitivity(spec: DeviceSpec, goal: TuneGoal, gains, nthread: int = 0, backend=None) -> tuple[list, int]:
    """Which parameter's range sets each hinge's worst case for these gains: every range's two ends, one at a
    time (the others nominal). Returns (per hinge {"parameter", "end" ("low"/"high"), "cost_s"}: the end with
    the highest cost (s, the tuner's), and the simulations run)."""
    ranges = goal.plant_ranges(spec)
    ends = [(p, end) for p in ranges.shared for end in ("low", "high")]
    plants = [at_ends(spec, ranges, {p: int(end == "high")}, goal.hinges) for p, end in ends]
    ev = RobustEvaluator(spec, goal, 1, nthread, gains, backend=backend, plants=plants)
    cost, _ = ev.costs(*(np.array([[getattr(g, k) for g in gains]]) for k in ("kp", "ki", "kd")))
    worst = cost[0].argmax(axis=0)  # per hinge, the end
    return [{"parameter": ends[e][0], "end": ends[e][1], "cost_s": round(float(cost[0, e, h]), 4)}
            for h, e in enumerate(worst)], ev.simulations


def step_report(spec: DeviceSpec, gains, goal: TuneGoal, plant: DeviceSpec | None = None, hinges=None):
    """The move report (twin.records.move_report) of one twin step from flat to goal.step on every
    hinge, over the tuner's window (goal.duration); and the trace. hinges: each hinge's own spec (Twin's)."""
    twin = Twin(plant or spec, gains, hinges=hinges, mount=goal.mount)
    trace = twin.move_to(np.full(spec.n_hinges, goal.step), max_time=goal.duration, stop_when_settled=False)
    return move_report(spec, trace), trace
