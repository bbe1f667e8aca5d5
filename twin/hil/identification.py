"""Identify each hinge's drive train from open-loop duty programs the device's firmware runs: the
experiments, and the fit on the twin's replays of them (docs/tuning-hil-calibration.md, "Identification").

The physics of one hinge, the others braked, at the gearbox output (q rad, w rad/s, u = duty x drive_cap V,
the core compensating for the battery it reads):

    J w' = eta K N (u - K N w) / R - b w - tau_c sgn(w) - tau_g(q)

J = rotor_inertia N^2 + the flaps' own inertia, tau_g the flaps' weight (their masses and lengths are the
spec's: a torque known in absolute terms), eta the gearbox's efficiency (1 / the back-driven efficiency where
the flap drives the motor). What each experiment shows (`programs`: the device lying flat, each flap raised
from the table to the top of its window and driven back down, at duties the prior predicts give four
speeds):
- the speed along a move: (eta K N u / R - tau_c - tau_g) / (eta K^2 N^2 / R + b): the no-load speed
  (1 / K N) from how it grows with the duty, and R from how much the weight's torque, which changes along
  the move, slows it;
- raised against the weight, lowered with it: the friction's sign turns with the motion, the weight's does
  not: tau_c;
- each move's first 30-50 ms (a step from rest to its speed): J / (eta K^2 N^2 / R + b), so J.
What none shows apart (held at the profile's value; each anywhere in its range widens the fitted values'
intervals, `HELD`): the viscous part b beside the motor's own electrical damping (4 % of it at the spec's
values), the cogging (its period spans 2 encoder counts: the encoder sees it as a drag) and the gearbox's
back-driven efficiency (`vrscroll holding` measures it).

The fit (`fit_hinge`): the twin's MuJoCo replay of each move (the recorded duties applied from rest at the
move's first angle; twin.sim.plant's model, the twin's values but hinge k's) against the device's encoder,
compared as speeds over SPEED_TICKS windows. Levenberg-Marquardt on log scales of FITTED from the best of a
few no-load speeds, sensitivities by replays STEP apart; intervals from the Jacobian (Gauss-Newton
covariance scaled by the residual and its autocorrelation) or a delete-one-move jackknife, the wider.
"""

from __future__ import annotations

import dataclasses
import math
import random

import mujoco
import numpy as np

from twin.device.mjcf import load_model
from twin.device.spec import DeviceSpec
from twin.device.variation import BOUNDED, SPREAD
from twin.hil.calibration import Estimate
from twin.sim.hinges import Hinges, place_hinges
from twin.sim.plant import HingeDraw, Plant, PlantOptions

WINDOW_DEG = (12.0, 75.0)  # the flap's travel, deg off the table (lying flat: positive raises every flap)
SPEEDS = (6.0, 9.0, 13.0, 18.0)  # rad/s at the output: each pair of moves' speed at the window's middle as the
# prior predicts it (fast enough that the cogging and the Stribeck friction are small beside the drive; at most
# about half the no-load speed, so that a move lasts several mechanical time constants)
MIN_DOWN_DUTY = 0.1  # |duty| of a move down at least (slower, the weight alone would drive it)
MAX_DUTY = 0.75  # |duty| at most (PROGRAM_MAX_DUTY is 0.8; the core's I2t budget lasts seconds at this)
MOVE_S = 1.5  # s: a move's longest (the window ends it sooner)
SETTLE_S = 0.3  # s braked before each move (the flap comes to rest): a program's first segment, not fitted
SPEED_TICKS = 10  # ticks per window the fit compares speeds over (10 ms: 1 count in it is 0.5 rad/s)
FITTED = ("no_load_speed", "gear_friction", "rotor_inertia", "resistance")  # per hinge (the winding's
# resistance: a warm winding's is up to x1.25 the datasheet's, and the device's torque with it)
HELD = {"gear_damping": SPREAD["gear_damping"], "cogging": BOUNDED["cogging"],
        "backdrive_efficiency": BOUNDED["backdrive_efficiency"]}  # x the profile's value
STEP = 0.1  # log: the replays the sensitivities come from are this far apart
SPEED_GRID = (0.65, 0.8, 1.0, 1.2, 1.45)  # x the prior's no-load speed: the search starts at the best of these
# (the speed moves every replay most; from the prior alone it can end in a valley the resistance makes up for)
NEWTON = 4  # Levenberg-Marquardt iterations, each its sensitivities and at least one replay
LM_DAMPING = 0.01  # the first iteration's damping, x the normal matrix's diagonal
LOG_BOUND = math.log(3.0)  # the values searched, x1/3 .. x3 the prior's
Z95 = 1.959964


@dataclasses.dataclass(frozen=True)
class Program:
    """One open-loop program for the device (Link.run_program's arguments): on `hinge`, segments of
    (duty, s) in turn, ended early when its counts leave window (low, high) or after timeout_s."""

    hinge: int
    segments: tuple
    window: tuple
    timeout_s: float


def weight_torque(spec: DeviceSpec, k: int, angle: float) -> float:
    """N*m the flaps' weight loads hinge k with, lying flat with hinge k at angle (rad), the others flat:
    MuJoCo's qfrc_bias at rest (positive against raising)."""
    model = load_model(spec)
    data = mujoco.MjData(model)
    hinges = Hinges(model, spec.n_hinges)
    angles = np.zeros(spec.n_hinges)
    angles[k] = angle
    place_hinges(data.qpos, hinges, angles)
    mujoco.mj_forward(model, data)
    return float(data.qfrc_bias[hinges.dadr[k]])


def programs(spec: DeviceSpec, k: int) -> list[Program]:
    """Hinge k's experiments, the device lying flat, within WINDOW_DEG off the table: raised from the table
    to the window's top, then driven down to its bottom, in turn, each pair at duties the prior predicts give
    one of SPEEDS at the window's middle. Each program starts SETTLE_S braked."""
    lo, hi = (int(round(math.radians(a) / spec.rad_per_count)) for a in WINDOW_DEG)
    edge = int(round(spec.hinge_limit / spec.rad_per_count))
    kn = spec.motor_constant * spec.gear_ratio
    per_duty = spec.gearbox_efficiency * kn * spec.drive_cap / spec.drive_resistance  # N*m per unit duty, stalled
    damping = spec.gearbox_efficiency * kn ** 2 / spec.drive_resistance + spec.gear_damping
    weight = weight_torque(spec, k, math.radians(sum(WINDOW_DEG) / 2))
    out = []
    for w in SPEEDS:
        up = min((damping * w + spec.gear_friction + weight) / per_duty, MAX_DUTY)
        down = -min(max((damping * w + spec.gear_friction - weight) / per_duty, MIN_DOWN_DUTY), MAX_DUTY)
        for duty, window in ((up, (-edge, hi)), (down, (lo, edge))):
            out.append(Program(k, ((0.0, SETTLE_S), (round(float(duty), 4), MOVE_S)), window, SETTLE_S + MOVE_S))
    return out


@dataclasses.dataclass
class Move:
    """One move of a program's run, from its first tick after the settle: per tick the duty and the encoder
    counts (float; NaN where the sample was lost on the link)."""

    hinge: int
    duty: np.ndarray
    counts: np.ndarray


def move_of(run, spec: DeviceSpec) -> Move | None:
    """The move in a program's run (controllers.program.ProgramRun: a sample per tick, some maybe lost), from
    the end of its settle; None where it has no tick after it."""
    dt = spec.firmware_dt
    ticks = np.rint(np.asarray(run.time_s) / dt).astype(int)
    start = int(round(SETTLE_S / dt))
    if len(ticks) == 0 or ticks[-1] <= start:
        return None
    n = ticks[-1] + 1
    duty, counts = np.full(n, np.nan), np.full(n, np.nan)
    duty[ticks], counts[ticks] = run.duty, run.counts
    duty = _filled(duty)
    if np.isnan(counts[start]):
        return None
    return Move(run.hinge, duty[start:], counts[start:])


def _filled(x: np.ndarray) -> np.ndarray:
    """x with each NaN the last value before it (0 at the start): a lost sample's duty is its neighbour's."""
    idx = np.where(np.isnan(x), 0, np.arange(len(x)))
    np.maximum.accumulate(idx, out=idx)
    out = x[idx]
    return np.where(np.isnan(out), 0.0, out)


def twin_options(spec: DeviceSpec, k: int, scales: dict) -> PlantOptions:
    """The twin of `spec` lying flat, hinge k's values x scales (no_load_speed, gear_friction, rotor_inertia,
    gear_damping, cogging, backdrive_efficiency): the MuJoCo model and drive the emulator's plant is built on,
    without what the twin leaves out (no warming winding, no friction ripple)."""
    nominal = HingeDraw(cogging=spec.cogging, cogging_phase=spec.cogging_phase)
    mine = dataclasses.replace(nominal, cogging=spec.cogging * scales.get("cogging", 1.0),
                               speed=scales.get("no_load_speed", 1.0), friction=scales.get("gear_friction", 1.0),
                               armature=scales.get("rotor_inertia", 1.0), damping=scales.get("gear_damping", 1.0))
    return PlantOptions(backlash_deg=math.degrees(spec.backlash), lying_flat=True, warming=False,
                        backdrive_scale=scales.get("backdrive_efficiency", 1.0),
                        hinges=tuple(mine if h == k else nominal for h in range(spec.n_hinges)))


def replay(spec: DeviceSpec, k: int, scales: dict, moves: list[Move]) -> list[np.ndarray]:
    """The twin's encoder counts through each move on hinge k, unrounded (the device's floor to a count; the
    twin's, unrounded, move smoothly with its values, so that their sensitivities do): its duties applied
    from rest at its first count's angle (the other hinges flat and braked, as the core drives them in IDLE),
    as long as it lasted.
    scales: as `twin_options`', and resistance (x the winding's: a warm winding, its motor constant kept)."""
    hot = spec.resistance * scales.get("resistance", 1.0)
    # the spec derives K from the datasheet's no-load point and the resistance: the no-load speed moves to keep K
    v, i0 = spec.rated_voltage, spec.no_load_current
    keep_k = (v - hot * i0) / (v - spec.resistance * i0)
    body = spec.replace(resistance=hot, no_load_speed=spec.no_load_speed * keep_k)
    plant = Plant(body, twin_options(body, k, scales), random.Random(0))
    n = spec.n_hinges
    brake = np.ones(n, np.uint8)
    out = []
    for m in moves:
        mujoco.mj_resetDataKeyframe(plant.model, plant.data, plant.model.key("flat").id)
        angles = np.zeros(n)
        angles[k] = m.counts[0] * spec.rad_per_count
        place_hinges(plant.data.qpos, plant.hinges, angles)
        mujoco.mj_forward(plant.model, plant.data)  # (the twin's encoder misses no edge: its counts are the shaft's)
        counts = np.zeros(len(m.duty))
        pwm = np.zeros(n)
        per_rad = spec.counts_per_motor_rev / (2 * math.pi)
        for i, d in enumerate(m.duty):
            plant.sense()
            counts[i] = plant.data.sensordata[plant.hinges.enc[k]] * per_rad  # unrounded: smooth in the values
            pwm[k] = max(-1.0, min(1.0, d * spec.drive_cap / plant.bus))
            plant.actuate(pwm, brake)
        out.append(counts - counts[0] + m.counts[0] + 0.5)
    return out


def speeds(counts, spec: DeviceSpec) -> np.ndarray:
    """The encoder's mean speed, rad/s, over consecutive SPEED_TICKS-tick windows (NaN where an end was lost)."""
    ends = np.asarray(counts, float)[::SPEED_TICKS]
    return np.diff(ends) * spec.rad_per_count / (SPEED_TICKS * spec.firmware_dt)


def residual(spec: DeviceSpec, k: int, scales: dict, moves: list[Move]) -> tuple[np.ndarray, np.ndarray]:
    """The twin's replay (`replay`) of the moves less the device's: the encoder's mean speed over each
    SPEED_TICKS window (rad/s; a speed, not the angle: a start a tick apart would offset every angle after
    it), and each window's move (index into moves); windows with a lost sample left out."""
    res, which = [], []
    for i, (twin, m) in enumerate(zip(replay(spec, k, scales, moves), moves)):
        r = speeds(twin, spec) - speeds(m.counts, spec)
        res.append(r[np.isfinite(r)])
        which.append(np.full(len(res[-1]), i))
    return np.concatenate(res), np.concatenate(which)


@dataclasses.dataclass
class HingeFit:
    """One hinge's identified values (SI, the spec's fields), each one's 95 % interval, and what was held."""

    hinge: int
    values: dict  # field -> value
    low: dict
    high: dict
    sd: dict  # field -> log standard error, the moves' scatter alone (before the held values' ranges)
    held: dict  # field -> (value, low, high) SI: held at the profile's value, the intervals allowing for it
    rms_speed: float  # rad/s: the residual at the fit
    windows: int  # speed windows compared
    replays: int


def fit_hinge(moves: list[Move], spec: DeviceSpec, progress=None) -> HingeFit:
    """One hinge's FITTED values from its moves: Levenberg-Marquardt on the twin's replays (`residual`), log
    scales of the profile's values, from the best of SPEED_GRID's no-load speeds; the sensitivities by
    replays STEP apart. Each value's 95 % interval: the Jacobian's covariance scaled by the residual and its
    autocorrelation, or a delete-one-move jackknife of the last step, whichever is wider, 1.96 sigma in log,
    widened by what each HELD value anywhere in its range would move it (the values that fit as well were
    it there). progress(message) is told each replay. ValueError where the moves show nothing."""
    if not moves:
        raise ValueError("no move to fit")
    k = moves[0].hinge
    m = len(FITTED)
    count = [0]

    def run(x, extra=None):
        count[0] += 1
        if progress:
            progress(f"hinge {k}: twin replay {count[0]}")
        return residual(spec, k, {p: math.exp(v) for p, v in zip(FITTED, x)} | (extra or {}), moves)[0]

    def fitted_jacobian(x, r):
        return np.stack([(run(x + STEP * np.eye(m)[j]) - r) / STEP for j in range(m)], axis=1)

    tried = [(run(math.log(s) * np.eye(m)[0]), math.log(s) * np.eye(m)[0]) for s in SPEED_GRID]
    r, x = min(tried, key=lambda t: float(t[0] @ t[0]))
    lam = LM_DAMPING
    for _ in range(NEWTON):
        A = fitted_jacobian(x, r)
        g, H = A.T @ r, A.T @ A
        while lam < 1e6:
            trial = np.clip(x - np.linalg.solve(H + lam * np.diag(np.diag(H)), g), -LOG_BOUND, LOG_BOUND)
            r_trial = run(trial)
            if r_trial @ r_trial < r @ r:
                x, r, lam = trial, r_trial, lam / 3
                break
            lam *= 4
        else:
            break
    A = fitted_jacobian(x, r)
    B = np.stack([(run(x, {p: math.exp(STEP)}) - r) / STEP for p in HELD], axis=1)
    which = residual_moves(moves, spec)
    s2 = float(r @ r) / max(len(r) - m, 1) * autocorrelation(r, which)
    inv = np.linalg.pinv(A.T @ A)
    sd_residual = np.sqrt(np.diag(s2 * inv))
    jk = np.array([np.linalg.lstsq(A[which != i], r[which != i], rcond=None)[0] for i in np.unique(which)])
    sd_jackknife = np.sqrt((len(jk) - 1) / len(jk) * ((jk - jk.mean(axis=0)) ** 2).sum(axis=0))
    sd = np.maximum(sd_residual, sd_jackknife)
    lo_shift, hi_shift, held = np.zeros(m), np.zeros(m), {}
    for j, (p, ends) in enumerate(HELD.items()):
        moved = [-inv @ A.T @ B[:, j] * math.log(e) for e in ends]
        lo_shift += np.minimum(0.0, np.minimum(*moved))
        hi_shift += np.maximum(0.0, np.maximum(*moved))
        held[p] = tuple(float(getattr(spec, p) * f) for f in (1.0, *ends))
    values = np.array([getattr(spec, p) for p in FITTED]) * np.exp(x)
    low, high = values * np.exp(-Z95 * sd + lo_shift), values * np.exp(Z95 * sd + hi_shift)
    return HingeFit(k, dict(zip(FITTED, values)), dict(zip(FITTED, low)), dict(zip(FITTED, high)),
                    dict(zip(FITTED, sd)), held, float(np.sqrt(np.mean(r ** 2))), len(r), count[0])


def residual_moves(moves: list[Move], spec: DeviceSpec) -> np.ndarray:
    """Each residual window's move (index), as `residual` lays them out."""
    return np.concatenate([np.full(int(np.isfinite(speeds(mv.counts, spec)).sum()), i) for i, mv in enumerate(moves)])


def autocorrelation(res: np.ndarray, which: np.ndarray) -> float:
    """1 + 2 x the sum of the residual's autocorrelation within moves, up to its first fall below 0.05: how
    many windows carry about one independent residual (at least 1)."""
    x = res - res.mean()
    e = float(x @ x)
    total = 1.0
    for lag in range(1, len(x)):
        same = which[lag:] == which[:-lag]
        rho = float((x[lag:] * x[:-lag])[same].sum()) / e if e > 0 else 0.0
        if rho < 0.05:
            break
        total += 2 * rho
    return total


def experiments(run_program, spec: DeviceSpec, hinges=None, progress=None) -> tuple[dict, float]:
    """Run each hinge's `programs` with run_program(hinge, segments, window_counts, timeout_s) -> ProgramRun
    (Link.run_program on the device), back to back. hinges: which (default all). progress(message). Returns
    {hinge: [Move]} and the programs' device time, s."""
    moves, device_s = {}, 0.0
    for k in (range(spec.n_hinges) if hinges is None else hinges):
        todo = programs(spec, k)
        moves[k] = []
        for i, p in enumerate(todo):
            if progress:
                progress(f"hinge {k}: move {i + 1}/{len(todo)}")
            run = run_program(p.hinge, p.segments, p.window, p.timeout_s)
            device_s += len(run.time_s) * spec.firmware_dt
            move = move_of(run, spec)
            if move is not None and len(move.duty) > 2 * SPEED_TICKS:
                moves[k].append(move)
    return moves, device_s


PROFILED = FITTED[:3]  # what the profile keeps per hinge (the resistance is the winding's now: it warms and
# cools with use, so the profile keeps the datasheet's and the fit says what it found)


def estimates(fit: HingeFit, spec: DeviceSpec, max_halfwidth: float) -> dict:
    """A hinge's fit as calibration's estimates ({field: twin.hil.calibration.Estimate}, the prior the
    profile's value): identifiable where its 95 % interval is within x(1 -+ max_halfwidth) of its value."""
    out = {}
    held = ", ".join(HELD)
    for p in FITTED:
        v, lo, hi = float(fit.values[p]), float(fit.low[p]), float(fit.high[p])
        pinned = bool(v / lo <= 1 + max_halfwidth and hi / v <= 1 + max_halfwidth)
        out[p] = Estimate(v, float(getattr(spec, p)), lo, hi, pinned,
                          f"open-loop moves, replayed on the twin; interval x{lo / v:.3f} .. x{hi / v:.3f} of the "
                          f"value ({held} held, anywhere in their ranges)" + ("" if pinned else ": not identifiable"))
    return out


def shared_estimates(per_hinge: list[dict]) -> dict:
    """One estimate per field for the device as a whole: the hinges' geometric mean, the interval spanning
    every hinge's, identifiable where every hinge's is (the profile's shared values; each hinge keeps its own)."""
    out = {}
    for p in per_hinge[0]:
        es = [h[p] for h in per_hinge]
        v = math.exp(sum(math.log(e.value) for e in es) / len(es))
        out[p] = Estimate(v, es[0].prior, min(e.low for e in es), max(e.high for e in es),
                          all(e.identifiable for e in es),
                          "the hinges' geometric mean, the interval spanning each hinge's own")
    return out
