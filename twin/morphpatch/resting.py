"""Whether an approximation rests on its target from outside (issue 37), judged on the exact mesh, and why not.

A touched proxy must not lie in the virtual object it stands for: where its surface is inside it, the hand
passes through what it sees before it feels anything. The bar every pose of ours is held to, and the one
`vrscroll approximate` refuses a pose by:

- its touch surface at most DEEPEST_MAX inside the target (flat flaps cut a curve by a little), and at most
  DEEP_SHARE_MAX of it more than DEEP inside;
- no flap through the target (twin.morphpatch.refinement.flaps_through: a wall, a plate, a tube);
- flaps two or more apart at least FLAP_APART_MIN apart (twin.morphpatch.refinement.flap_gap), and for any
  variant, flaps that meet (closer than FLAP_MEET) are refused: the device cannot take that pose.

The paper's variants (full, no_hcevf) keep the paper's objective, which does not keep out of the target: they
are reported (inside share, deepest point), refused only where their flaps meet. Metres here.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import trimesh

from twin.device.spec import DeviceSpec
from twin.morphpatch.fields import Fields
from twin.morphpatch.refinement import ANCHOR_RADIUS, LIFT_REACH, flap_gap, flaps_through
from twin.morphpatch.surface_metrics import proxy_distances

DEEPEST_MAX = 3e-3  # m: ours' touch surface goes no deeper into the target than this (exact mesh)
DEEP = 2e-3  # m: ... and at most DEEP_SHARE_MAX of it deeper than this
DEEP_SHARE_MAX = 0.05
FLAP_APART_MIN = 3e-3  # m: ours keeps flaps two or more apart this far apart (its search keeps 3.5 mm)
FLAP_MEET = 0.5e-3  # m: flaps two or more apart closer than this meet (the spec's flap_gap between neighbours;
# the paper's pipeline curls a fat torus's flaps to 0.02 mm of each other, which the gate's MuJoCo finds in contact)


class Resting(NamedTuple):
    """How a pose lies on its target (m; a share 0..1; a count)."""

    deepest: float  # the deepest touch-surface point inside the target, 0 if none is
    deep_share: float  # the share of the touch surface more than DEEP inside
    through: int  # flaps through the target
    gap: float  # the smallest gap between flaps two or more apart; negative where they overlap


def resting(spec: DeviceSpec, mesh: trimesh.Trimesh, fields: Fields | None, result, through: bool = True) -> Resting:
    """How an Approximation's pose lies on the mesh (exact distances; flaps through on the fields' grid, unless
    `through` is False: then 0, and fields may be None)."""
    d = proxy_distances(spec, mesh, result.root_pose, result.angles, result.widths)
    return Resting(max(0.0, float(-d.min())), float(np.mean(d < -DEEP)),
                   flaps_through(fields, spec, result.root_pose, result.angles, result.widths) if through else 0,
                   flap_gap(spec, result.angles))


def refusal(spec: DeviceSpec, mesh: trimesh.Trimesh, r: Resting, variant: str, rests: bool | None = None) -> str | None:
    """Why a pose is refused, in one line, or None: flaps that meet (any variant); for ours, anything short of
    the bar in the module docstring, or a search that found no resting pose (`rests` False), said as what the
    target is to the device."""
    if r.gap < FLAP_MEET:
        return (f"the {variant} pose's flaps meet (two flaps two or more apart "
                + (f"overlap by {-r.gap * 1e3:.1f} mm" if r.gap < 0 else f"{r.gap * 1e3:.2f} mm apart")
                + "): the device cannot take it; try --variant refined or another --start")
    if variant != "refined":
        return None
    size = float(mesh.extents.max())
    if size < spec.flap_pitch:
        why = f"the target is smaller than a flap ({size * 1e3:.1f} mm across, a flap {spec.flap_pitch * 1e3:.1f} mm)"
    elif r.through:
        why = f"nothing reachable from this start without passing through the target ({r.through} flap(s) through it)"
    elif r.deepest > DEEPEST_MAX or r.deep_share > DEEP_SHARE_MAX:
        why = (f"the target is too thin or too curved here to rest on from outside (the touch surface "
               f"{r.deepest * 1e3:.1f} mm inside, {r.deep_share:.0%} of it more than {DEEP * 1e3:g} mm; at most "
               f"{DEEPEST_MAX * 1e3:g} mm and {DEEP_SHARE_MAX:.0%})")
    elif r.gap < FLAP_APART_MIN:
        why = f"its flaps come {r.gap * 1e3:.1f} mm close (at least {FLAP_APART_MIN * 1e3:g} mm)"
    elif rests is False:
        why = (f"no pose near where the device met it (within {ANCHOR_RADIUS * 1e3:g} mm, or lifted off it by up to "
               f"{LIFT_REACH * 1e3:g} mm) rests on it without passing through")
    else:
        return None
    return f"ours cannot rest on this target from outside: {why}; try another --start"


def resting_json(r: Resting) -> dict:
    """The JSON fields of a Resting: inside_over_2mm_percent, flap_gap_mm, flaps_through."""
    return {"inside_over_2mm_percent": round(r.deep_share * 100, 2), "flap_gap_mm": round(r.gap * 1e3, 2),
            "flaps_through": r.through}
