"""The calibration scenario: timed hinge targets that show calibration what it fits, timed for the gains
the device has (docs/tuning-hil-calibration.md, "The calibration scenario").

Each cycle, every hinge (its own angles, drawn from a seed) makes
- a large move (20-50 deg, the sign alternating from cycle to cycle): the acceleration at full duty
  shows the rotor inertia, the speed reached shows the no-load speed;
- then a slow ramp RAMP up and back down (targets a count or so apart, RAMP_TIME each way): whatever the
  gains, the hinge must creep, and the duty that keeps it creeping is the gravity load plus the gear
  friction, with the friction's sign changing between the two ramps: the window means of the duty
  (calibration.py) show the friction; each reversal crosses the backlash.
Each move is held until the twin (the profile's spec, the device's gains) has settled, plus HOLD, so
the scenario suits the gains the device has: the gate checks each move as it times it; a large move
on which the gains would brake harder than the driver's peak current is made in halves; any other
refusal (gains too weak to settle in time) names the move.
"""

from __future__ import annotations

import math

import numpy as np

from twin.device.spec import DeviceSpec
from twin.formats.scenario import Scenario
from twin.sim.gate import check_move
from twin.sim.twin import Twin

LARGE = (math.radians(20.0), math.radians(50.0))  # rad, range of the large moves' end angles (either sign)
RAMP = math.radians(8.0)  # rad, how far each ramp goes
RAMP_TIME = 1.0  # s each way: 8 deg/s, a creep for every gain the firmware takes
RAMP_STEPS = 40  # targets per ramp (25 ms apart, 0.2 deg: less than a count)
HOLD = 0.4  # s held after the twin settles: two duty windows at rest


def calibration_scenario(spec: DeviceSpec, gains, seed: int = 0, cycles: int = 2,
                         name: str = "calibration") -> Scenario:
    """The scenario (angles in rad, times s); ValueError naming the move the gate refuses with these gains."""
    rng = np.random.default_rng(seed)
    n = spec.n_hinges
    twin = Twin(spec, gains)
    times, targets, t, prev = [], [], 0.0, np.zeros(n)

    def hold(target, duration):
        nonlocal t
        times.append(round(t, 3))
        targets.append(np.asarray(target, float))
        t += duration

    for c in range(cycles):
        centre = (1.0 if c % 2 == 0 else -1.0) * rng.uniform(*LARGE, size=n)
        for step, settle in _timed(spec, gains, twin, prev, centre):
            hold(step, settle + HOLD)
        top = centre + RAMP * np.sign(centre)
        settle = max(d for _, d in _timed(spec, gains, twin, centre, top))  # the ramp, made as one step
        for a, b in ((centre, top), (top, centre)):
            for i in range(1, RAMP_STEPS + 1):
                hold(a + (b - a) * i / RAMP_STEPS, RAMP_TIME / RAMP_STEPS if i < RAMP_STEPS else settle + HOLD)
        prev = centre
    return Scenario(name, np.zeros(n), times, targets, round(t, 3))


def _timed(spec: DeviceSpec, gains, twin: Twin, start, target) -> list:
    """[(target rad, time s the twin takes to settle there)] for a move the gate passes: the move itself, or,
    where the gains draw more than the driver's peak current braking from a long move, the move split in
    halves. ValueError naming the move for any other refusal."""
    report = check_move(spec, start, target, gains, twin=twin)
    if report.passed:
        return [(np.asarray(target, float), report.prediction.duration)]
    if [c.name for c in report.failed] == ["peak_current"] and np.abs(target - start).max() > RAMP:
        mid = (np.asarray(start) + target) / 2
        return _timed(spec, gains, twin, start, mid) + _timed(spec, gains, twin, mid, target)
    raise ValueError(f"the calibration scenario's move to {np.degrees(target).round(1).tolist()} deg is refused by "
                     f"the gate with these gains: {report.refusal()}")
