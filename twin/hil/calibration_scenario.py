"""The calibration scenario: timed hinge targets that show calibration what it fits, timed for the gains
the device has, safe on every plant the device may be and for how it is held (docs/tuning-hil-calibration.md,
"The calibration scenario").

Each cycle, every hinge (its own angles, drawn from a seed) makes
- a large move (20-50 deg, the sign alternating from cycle to cycle): the acceleration at full duty
  shows the rotor inertia, the speed reached shows the no-load speed;
- then a slow ramp RAMP up and back down (targets a count or so apart, RAMP_TIME each way): whatever the
  gains, the hinge must creep, and the duty that keeps it creeping is the gravity load plus the gear
  friction, with the friction's sign changing between the two ramps: the window means of the duty
  (calibration.py) show the friction; each reversal crosses the backlash.
Lying flat (mount "flat") no flap may go below the table: the large moves alternate between 20-50 deg and
FLAT_LOW (a few degrees above the table) instead of changing sign, so every hinge still moves both ways.
Each move is gated on every plant given (the nominal and the corners of the spread the device may be in:
twin.device.variation.corners), each twin held as the device is, and held until the slowest of them has
settled, plus HOLD, so the scenario suits the gains the device has whatever its plant: a large move on
which the gains would brake harder than the driver's peak current on some plant is made in halves; any
other refusal (gains too weak to settle in time, a target the table stops) names the move and the plant.
"""

from __future__ import annotations

import math

import numpy as np

from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec
from twin.device.variation import Plant
from twin.formats.scenario import Scenario
from twin.sim.gate import check_move
from twin.sim.twin import Twin

LARGE = (math.radians(20.0), math.radians(50.0))  # rad, range of the large moves' end angles (either sign)
FLAT_LOW = (math.radians(2.0), math.radians(8.0))  # rad, lying flat: the low end of the large moves, above the table
RAMP = math.radians(8.0)  # rad, how far each ramp goes
RAMP_TIME = 1.0  # s each way: 8 deg/s, a creep for every gain the firmware takes
RAMP_STEPS = 40  # targets per ramp (25 ms apart, 0.2 deg: less than a count)
HOLD = 0.4  # s held after the twin settles: two duty windows at rest


def calibration_scenario(spec: DeviceSpec, gains, seed: int = 0, cycles: int = 2, name: str = "calibration",
                         mount: str = DEFAULT_MOUNT, plants: list[Plant] | None = None, progress=None) -> Scenario:
    """The scenario (angles in rad, times s) for a device held as `mount`, each move gated on every plant of
    `plants` (default: the spec's alone; e.g. variation.corners of the spread). progress(line): once the twins
    are built and after each cycle. ValueError naming the move (and plant) the gate refuses."""
    rng = np.random.default_rng(seed)
    n = spec.n_hinges
    plants = plants or [Plant(spec)]
    twins = [Twin(p.spec, gains, hinges=None if p.hinges is None else list(p.hinges), mount=mount) for p in plants]
    if progress:
        progress(f"{len(twins)} twins held {mount}")
    times, targets, t, prev = [], [], 0.0, np.zeros(n)

    def hold(target, duration):
        nonlocal t
        times.append(round(t, 3))
        targets.append(np.asarray(target, float))
        t += duration

    for c in range(cycles):
        centre = _centre(rng, c, n, mount)
        for step, settle in _timed(spec, gains, twins, prev, centre):
            hold(step, settle + HOLD)
        top = centre + RAMP * np.sign(centre)
        settle = max(d for _, d in _timed(spec, gains, twins, centre, top))  # the ramp, made as one step
        for a, b in ((centre, top), (top, centre)):
            for i in range(1, RAMP_STEPS + 1):
                hold(a + (b - a) * i / RAMP_STEPS, RAMP_TIME / RAMP_STEPS if i < RAMP_STEPS else settle + HOLD)
        prev = centre
        if progress:
            progress(f"cycle {c + 1} of {cycles} gated on every twin ({t:.1f} s of scenario)")
    return Scenario(name, np.zeros(n), times, targets, round(t, 3))


def _centre(rng, cycle: int, n: int, mount: str) -> np.ndarray:
    """Cycle `cycle`'s large move's end angles (rad): LARGE, positive then negative; lying flat, LARGE then
    FLAT_LOW, never below the table."""
    if mount == "flat":
        return rng.uniform(*(LARGE if cycle % 2 == 0 else FLAT_LOW), size=n)
    return (1.0 if cycle % 2 == 0 else -1.0) * rng.uniform(*LARGE, size=n)


def _timed(spec: DeviceSpec, gains, twins: list[Twin], start, target) -> list:
    """[(target rad, time s the slowest twin takes to settle there)] for a move the gate passes on every twin:
    the move itself, or, where the gains draw more than the driver's peak current braking from a long move on
    some twin, the move split in halves. ValueError naming the move and the plant for any other refusal."""
    reports = [check_move(spec, start, target, gains, twin=tw) for tw in twins]
    failed = [(i, r) for i, r in enumerate(reports) if not r.passed]
    if not failed:
        return [(np.asarray(target, float), max(r.prediction.duration for r in reports))]
    if all([c.name for c in r.failed] == ["peak_current"] for _, r in failed) and np.abs(target - start).max() > RAMP:
        mid = (np.asarray(start) + target) / 2
        return _timed(spec, gains, twins, start, mid) + _timed(spec, gains, twins, mid, target)
    i, report = failed[0]
    plant = "the nominal plant" if i == 0 else f"plant {i} of {len(twins)} (a corner of the spread)"
    raise ValueError(f"the calibration scenario's move to {np.degrees(target).round(1).tolist()} deg is refused by "
                     f"the gate with these gains on {plant}: {report.refusal()}")
