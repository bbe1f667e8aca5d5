"""A design: the device spec with some values changed, checked for what the device cannot be.

`design_spec(base, overrides)` takes overrides by DeviceSpec field (SI) and returns the design's spec;
the MJCF is generated from it as from any spec (twin.device.mjcf). Two values follow the design unless
given: the root flap stays the central one when the flap count changes, and the total mass keeps the
base's flap material (its density) with the design's flaps, motors and electronics.

`impossible(spec)` gives the reasons a spec cannot be built, each one sentence; `design_spec` refuses
those with ValueError. Flaps are hinged on their touch surface: to bend convex by the hinge limit a,
each flap's back edges are bevelled by a/2, which takes thickness * tan(a/2) off both ends of its back,
and some of the back must be left to carry the motor.
"""

from __future__ import annotations

import dataclasses
import math

from twin.device.spec import DeviceSpec, sizes_beyond_bounds

FIELDS = tuple(f.name for f in dataclasses.fields(DeviceSpec))
INTEGER_FIELDS = {f.name for f in dataclasses.fields(DeviceSpec) if f.type in (int, "int")}
# what the total mass is made of: a design changing one of these, and not mass_total, gets a new total
_MASS_PARTS = {"n_flaps", "length", "depth", "thickness", "mass_motor", "mass_electronics"}
# SI values that must be above zero for any device
_POSITIVE = ("length", "depth", "thickness", "usable_depth", "hinge_limit", "motor_diameter", "motor_length",
             "mass_total", "mass_motor", "gear_ratio", "no_load_speed", "stall_torque", "stall_current",
             "resistance", "rotor_inertia", "rated_voltage", "supply_voltage", "drive_cap", "loop_rate", "timestep")


def design_spec(base: DeviceSpec, overrides: dict) -> DeviceSpec:
    """The base spec with `overrides` (DeviceSpec field -> SI value); ValueError naming an unknown field,
    or giving why the design cannot be built."""
    for key in overrides:
        if key not in FIELDS:
            raise ValueError(f"{key!r} is not a spec value (the spec's are: {', '.join(FIELDS)})")
    changes = dict(overrides)
    for key in INTEGER_FIELDS & changes.keys():
        value = changes[key]
        if isinstance(value, bool) or float(value) != int(value):
            raise ValueError(f"{key} = {value!r}: expected a whole number")
        changes[key] = int(value)
    if "n_flaps" in changes and changes["n_flaps"] < 2:  # before the spec divides by it
        raise ValueError(f"the device cannot be built: n_flaps = {changes['n_flaps']}: a device needs at least "
                         "2 flaps (one hinge)")
    if "n_flaps" in changes and "root_flap" not in changes:
        changes["root_flap"] = (changes["n_flaps"] - 1) // 2
    spec = dataclasses.replace(base, **changes)
    if "mass_total" not in changes and _MASS_PARTS & changes.keys():
        spec = dataclasses.replace(spec, mass_total=_mass_with_base_density(base, spec))
    reasons = impossible(spec)
    if reasons:
        raise ValueError("the device cannot be built: " + "; ".join(reasons))
    return spec


def _mass_with_base_density(base: DeviceSpec, spec: DeviceSpec) -> float:
    """Total mass, kg, of `spec` built from the base's flap material: flaps + motors + electronics."""
    density = base.flap_mass / (base.flap_pitch * base.depth * base.thickness)  # kg/m^3
    flaps = spec.n_flaps * density * spec.flap_pitch * spec.depth * spec.thickness
    return flaps + spec.n_hinges * spec.mass_motor + spec.mass_electronics


def bevel_limit(spec: DeviceSpec) -> float:
    """The largest hinge limit, rad, the flaps' thickness allows: bevels t*tan(a/2) at both ends of a
    flap's back leave nothing of it at a = 2*atan((pitch - gap) / (2*t))."""
    return 2.0 * math.atan((spec.flap_pitch - spec.flap_gap) / (2.0 * spec.thickness))


def impossible(spec: DeviceSpec) -> list[str]:
    """Why the device of this spec cannot be built (empty if it can), in the spec's units at the edge (mm, deg)."""
    reasons = [f"{k} = {getattr(spec, k):g} must be above zero" for k in _POSITIVE if not getattr(spec, k) > 0]
    if spec.n_flaps < 2:
        reasons.append(f"n_flaps = {spec.n_flaps}: a device needs at least 2 flaps (one hinge)")
    if not 0 <= spec.root_flap < spec.n_flaps:
        reasons.append(f"root_flap = {spec.root_flap} is not one of the {spec.n_flaps} flaps")
    if reasons:
        return reasons  # the checks below divide by these
    if spec.flap_gap < 0:
        reasons.append(f"flap_gap = {spec.flap_gap * 1e3:g} mm: neighbouring flaps would overlap ({spec.n_flaps} flaps "
                       f"{(spec.flap_pitch - spec.flap_gap) * 1e3:.1f} mm wide make "
                       f"{spec.n_flaps * (spec.flap_pitch - spec.flap_gap) * 1e3:.1f} mm, more than the "
                       f"{spec.length * 1e3:g} mm length)")
    width = spec.flap_pitch - spec.flap_gap
    if width < spec.motor_diameter:
        reasons.append(f"a flap {width * 1e3:.1f} mm wide (pitch {spec.flap_pitch * 1e3:.1f} mm less the "
                       f"{spec.flap_gap * 1e3:g} mm gap) is narrower than its motor ({spec.motor_diameter * 1e3:g} mm)")
    if spec.hinge_limit >= math.pi:
        reasons.append(f"hinge_limit = {math.degrees(spec.hinge_limit):g} deg: neighbouring flaps fold onto each "
                       "other at 180 deg")
    elif spec.hinge_limit > bevel_limit(spec):
        bevel = spec.thickness * math.tan(spec.hinge_limit / 2)
        reasons.append(f"hinge_limit = {math.degrees(spec.hinge_limit):g} deg is beyond what {spec.thickness * 1e3:g} mm "
                       f"thick flaps allow ({math.degrees(bevel_limit(spec)):.1f} deg at a {spec.flap_pitch * 1e3:.1f} mm "
                       f"pitch: the bevels, {bevel * 1e3:.1f} mm at each end, would take the whole back)")
    if spec.usable_depth > spec.depth:
        reasons.append(f"usable_depth = {spec.usable_depth * 1e3:g} mm is more than the depth {spec.depth * 1e3:g} mm")
    if spec.flap_mass <= 0:
        reasons.append(f"mass_total = {spec.mass_total * 1e3:g} g leaves nothing for the flaps after "
                       f"{spec.n_hinges} motors and the electronics")
    if spec.drive_cap > spec.supply_voltage:
        reasons.append(f"drive_cap = {spec.drive_cap:g} V is more than the supply's {spec.supply_voltage:g} V")
    return reasons + sizes_beyond_bounds(spec)

