"""`vrscroll cbs`: the collision-based simulation baseline in MuJoCo, as JSON like `approximate`'s.

The target becomes static collision geometry (convex parts from CoACD, cached),
the device is pressed onto it from the start pose and its motors bend the flaps
until contact stops each one. `collision_error_mm` says how far the collision
shape is from the mesh.
"""

from __future__ import annotations

from twin.commands.approximate import add_target_arguments, target_and_start, write_result
from twin.device.spec import load_spec
from twin.evaluation.cbs import CbsSimulator
from twin.morphpatch.approximation import measured


def add_arguments(p) -> None:
    add_target_arguments(p)


def run(args) -> int:
    spec = load_spec()
    name, mesh, start, pose = target_and_start(args)
    sim = CbsSimulator(spec, mesh)
    result = measured(spec, mesh, sim.run(pose))
    extra = {
        "collision_parts": sim.parts,
        "collision_error_mean_mm": round(sim.error.mean * 1e3, 3),
        "collision_error_max_mm": round(max(sim.error.mesh_to_parts_max, sim.error.parts_outside_max) * 1e3, 3),
        "touching_flaps": sim.last_touching,
    }
    write_result(args, name, start, result, mesh, spec, extra)
    return 0
