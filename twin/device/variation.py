"""How a built device differs from its spec: the plant parameters, how far each may be off, and the
plants a range spans. One home for plant variation: the emulator draws its plant within SPREAD
(twin.sim.plant), calibration's prior is SPREAD (twin.hil.calibration), the tuner tunes over the
corners of a box of ranges (twin.tuning.tuner), a sweep draws its plants with `drawn_scales`
(twin.evaluation.sweep).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

from twin.device.spec import DeviceSpec
from twin.records.ranges import Ranges

# the spec fields a profile may hold other values of than the spec's: the plant parameters calibration fits
# (gear_stiction moves with gear_friction), how the gearbox passes a load that drives it, which a release
# under gravity measures (`vrscroll holding`, twin.hil.holding), and what the runs cannot show (the cogging,
# where its detents sit, the winding's resistance: a user who measures them may set them). Every other value
# (hinge range, settle band, flap count, limits) is the device's design, the same for every device built to
# the spec: a profile that changes one is refused.
PLANT_FIELDS = ("no_load_speed", "gear_friction", "gear_stiction", "gear_damping", "rotor_inertia", "backlash",
                "backdrive_efficiency", "cogging", "cogging_phase", "resistance")
# the spec fields that move with a parameter, in proportion: the static friction keeps its ratio to the
# Coulomb friction (one gearbox's friction)
MOVES_WITH = {"gear_friction": ("gear_stiction",)}
HOLDING = ("backdrive_efficiency",)  # measured by a release (twin.hil.holding), not by the HIL runs' fit
# x the spec's value: what calibration bounds but does not fit (twin.hil.calibration), the runs cannot show it
# apart from the parameters it trades with: the cogging (its period spans 2 encoder counts, so the device's own
# sensor sees it as drag, as friction; the spec's 3 % of the stall torque about 1-5 %), the winding's resistance
# (from the datasheet's, at 25 deg C, to a winding 60 K warmer: copper's 0.393 %/K; a device that has been
# running, a motor that works hard), and the gearbox's back-driven efficiency (a flap falling under gravity
# drives its motor: it moves as a faster motor would; `vrscroll holding` measures it, the HIL runs do not show
# it apart; 0.3-0.7 about the spec's 0.5, at most 1). Each widens the fitted parameters' intervals by what it
# could move them.
BOUNDED = {"cogging": (1 / 3, 5 / 3), "resistance": (1.0, 1.25), "backdrive_efficiency": (0.6, 1.4)}
# the plant parameters calibration fits from HIL runs: less those that move with another, the holding's, the
# bounded ones, and where the cogging's detents sit (a period spans 2 encoder counts: no run shows it)
PARAMS = tuple(p for p in PLANT_FIELDS if p not in HOLDING + tuple(BOUNDED) + ("cogging_phase",)
               and not any(p in moved for moved in MOVES_WITH.values()))
# x the spec's value: how far a device may differ from its datasheet (an assumption: the spread of a batch of
# micro metal gearmotors and of their assembly; the backlash 0.01 .. 0.5 deg about the spec's 0.25 deg: not 0,
# which the MJCF makes a rigid coupling, another model layout). The emulator draws its plant within it (its
# backlash from 0 up), calibration takes it as its prior, docs/device.md "The emulator's plant" states it.
SPREAD = {"no_load_speed": (0.7, 1.3), "gear_friction": (0.7, 1.6), "gear_damping": (0.7, 1.6),
          "rotor_inertia": (0.7, 1.4), "backlash": (0.04, 2.0)}


def scaled(spec: DeviceSpec, scales: dict) -> DeviceSpec:
    """The spec with each field in `scales` (field -> x its value) scaled, and those that move with it
    (MOVES_WITH) alike unless `scales` names them too."""
    moved = {f: getattr(spec, f) * float(x) for p, x in scales.items() for f in MOVES_WITH.get(p, ())}
    return spec.replace(**(moved | {p: getattr(spec, p) * float(x) for p, x in scales.items()}))


def prior_ranges(spec: DeviceSpec) -> Ranges:
    """What is known of an uncalibrated device: each parameter within SPREAD of the spec's value, SI."""
    return Ranges({p: (getattr(spec, p) * lo, getattr(spec, p) * hi) for p, (lo, hi) in SPREAD.items()},
                  "the spread about the spec")


def bounded_ranges(spec: DeviceSpec) -> dict:
    """BOUNDED about the spec's values, {field: (low, high) x the value}: a back-driven efficiency at most 1 (a
    gearbox passes no more than it is given)."""
    return {p: (lo, min(hi, 1.0 / spec.backdrive_efficiency) if p == "backdrive_efficiency" else hi)
            for p, (lo, hi) in BOUNDED.items()}


def tolerance_ranges(spec: DeviceSpec, tolerance: float) -> Ranges:
    """The ranges of an uncalibrated spec, SI: motor constant and gear friction each x (1 +- tolerance). The
    motor constant is derived from the no-load speed (K ~ V / (N w0)), so a motor constant x (1 + t) is a no-load
    speed / (1 + t)."""
    return Ranges({"no_load_speed": (spec.no_load_speed / (1 + tolerance), spec.no_load_speed / (1 - tolerance)),
                   "gear_friction": (spec.gear_friction * (1 - tolerance), spec.gear_friction * (1 + tolerance))},
                  f"uncalibrated, +-{tolerance * 100:g} %")


class Plant(NamedTuple):
    """One plant to simulate: the device's spec, and where its hinges differ each hinge's own (a tuple of
    n_hinges specs, as twin.sim.twin.Twin takes them), else None."""

    spec: DeviceSpec
    hinges: tuple | None = None


def at_ends(spec: DeviceSpec, ranges: Ranges, ends: dict, hinges=None) -> Plant:
    """The plant with each field p of `ends` at one end of its range (ends[p]: 0 low, 1 high). hinges: each
    hinge's own spec, or None: a hinge goes to the end of its own range (ranges.hinges) where it has one, or,
    for a field it has no range of, to the shared range's end as a multiple of the shared value."""
    shared = scaled(spec, {p: float(ranges.shared[p][e]) / getattr(spec, p) for p, e in ends.items()})
    if hinges is None:
        return Plant(shared)
    own = []
    for h, hs in enumerate(hinges):
        mine = ranges.hinges[h] if ranges.hinges else {}
        own.append(scaled(hs, {p: float(mine[p][e]) / getattr(hs, p) if p in mine
                               else float(ranges.shared[p][e]) / getattr(spec, p) for p, e in ends.items()}))
    return Plant(shared, tuple(own))


def corners(spec: DeviceSpec, ranges: Ranges, hinges=None) -> list[Plant]:
    """The nominal plant, then every corner of the box `ranges` spans: 2^k plants for k shared ranges, each hinge
    at its own ranges' corners where hinges (each hinge's own spec) and ranges.hinges give them (`at_ends`). A
    field that moves another (MOVES_WITH) moves it in proportion."""
    plants = [Plant(spec, None if hinges is None else tuple(hinges))]
    names = list(ranges.shared)
    for corner in itertools.product((0, 1), repeat=len(names)):
        plants.append(at_ends(spec, ranges, dict(zip(names, corner)), hinges))
    return plants


def drawn_scales(tolerance: dict, seed: int, draw: int) -> dict:
    """Draw number `draw` (from 1) of a set: {field: x the value}, each uniform within 1 +- tolerance[field]
    (a fraction); it depends on the seed and the draw's number only, so a set can grow or resume."""
    rng = np.random.default_rng([seed, draw])
    return {k: round(1.0 + tolerance[k] * rng.uniform(-1, 1), 6) for k in sorted(tolerance)}
