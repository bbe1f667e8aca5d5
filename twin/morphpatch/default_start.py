"""The default start for a mesh (issue 37): of the starts a person would bring the device to it from (one facing
each of its sides, over the open surface nearest its middle: twin.morphpatch.shapes.side_starts), the one from
which ours rests on it best.

A person looking at an object brings the device to its broad, open sides and keeps the one where it fits; the
broadest side alone is not always that one (a torus thinner than the device is wide fits it edge on, not from
above: 16 mm against 26 mm MSD). Each side's start is approximated with ours; the one whose pose rests on the
target from outside (the search's own bound) with the lowest objective (twin.morphpatch.refinement.objective,
the grid's sum of squared residuals: cheap, no exact mesh) is taken; where none rests, the broadest side's.
About 7 approximations, once per mesh (docs/approximation.md, "Starts").
"""

from __future__ import annotations

import numpy as np
import trimesh

from twin.device.spec import DeviceSpec
from twin.morphpatch.approximation import approximate, pose_from_mm_deg
from twin.morphpatch.fields import Fields
from twin.morphpatch.refinement import objective
from twin.morphpatch.sampling import SAMPLE_SPACING, grid_layout
from twin.morphpatch.shapes import side_starts


def default_start(mesh: trimesh.Trimesh, fields: Fields, spec: DeviceSpec) -> list[float]:
    """The default start [x, y, z mm, roll, pitch, yaw deg] for a mesh and its fields (module docstring)."""
    starts = side_starts(mesh)
    widths = np.full(spec.n_flaps, spec.flap_pitch)
    local = grid_layout(spec, SAMPLE_SPACING).local(widths)
    best, best_cost = starts[0], np.inf
    for start in starts:
        result = approximate(fields, pose_from_mm_deg(start), spec, "refined")
        cost = objective(fields, spec, local, result.root_pose, result.angles, widths) if result.rests else np.inf
        if cost < best_cost:
            best, best_cost = start, cost
    return best
