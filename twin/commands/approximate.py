"""`vrscroll approximate`: MorphPatch's surface approximation of one target from one start; prints JSON.

The target is a named shape (models/shapes/shapes.toml) or a mesh file in metres.
The start is the anchor's pose as x,y,z (mm), roll,pitch,yaw (deg, fixed axes:
R = Rz(yaw) Ry(pitch) Rx(roll)); by default the shape's own `start` from
shapes.toml, or for a mesh file 40 mm out from the side of it ours rests on best, over that
side's middle (twin.morphpatch.default_start: the sides along its principal axes and from above). The JSON carries MSD and HD (mm) on the exact mesh, how much of
the touch surface lies inside the target and how deep (inside_percent, inside_depth_mm,
inside_over_2mm_percent), the smallest gap between flaps two or more apart (flap_gap_mm),
flaps through the target, and time_ms of a warm call (the process's first call, which
loads compiled code, is run once before and not reported).

A pose whose flaps meet (any variant), or for ours (refined) one that does not rest on the
target from outside (twin.morphpatch.resting), is refused: one line saying why, exit 2, no
JSON written.
"""

from __future__ import annotations

import json

from twin.commands.options import add_json, add_target, output_file
from twin.device.spec import load_spec
from twin.errors import UserError
from twin.evaluation.starts import parse_start, target_and_start as target_start
from twin.formats.target import approximation_json, write_approximation
from twin.morphpatch.approximation import VARIANTS, approximate, frames, measured
from twin.morphpatch.fields import build_fields
from twin.morphpatch.resting import refusal, resting, resting_json
from twin.morphpatch.shapes import shape_names
from viz.scene import render_approximation

def add_arguments(p) -> None:
    add_target_arguments(p)
    p.add_argument("--variant", choices=VARIANTS, default="full", help="pipeline variant (default full)")


def add_target_arguments(p) -> None:
    """--shape/--mesh, --start, --png, --json: shared with `vrscroll cbs`. The result's JSON is always printed."""
    add_target(p, shape_names(), required=True)
    p.add_argument("--png", metavar="FILE", type=output_file,
                   help="also write an off-screen picture of the device on the target")
    add_json(p, "the result (it is printed on standard output in any case)")


def target_and_start(args):
    """(name, mesh, start as [x,y,z mm, roll,pitch,yaw deg], start pose 4x4) from --shape/--mesh and --start
    (twin.evaluation.starts.target_and_start)."""
    return target_start(args.shape, args.mesh, parse_start(args.start) if args.start else None)


def write_result(args, name, start, result, mesh, spec, extra: dict | None = None) -> None:
    """Print the result's JSON (and write --json, --png) with the target, start and any extra fields."""
    out = {"target": name, "start_mm_deg": start, **approximation_json(result), **(extra or {})}
    text = json.dumps(out, indent=2)
    print(text)
    if args.json not in (None, "-"):
        write_approximation(args.json, out)
    if args.png:
        render_approximation(spec, mesh, frames(spec, result), result.widths, args.png,
                             title=f"{name} ({result.variant}): MSD {out['msd_mm']:.1f} mm, HD {out['hd_mm']:.1f} mm")


def run(args) -> int:
    spec = load_spec()
    name, mesh, start, pose = target_and_start(args)
    fields = build_fields(mesh)
    approximate(fields, pose, spec, args.variant)  # warm-up: the first call in a process loads compiled code
    result = measured(spec, mesh, approximate(fields, pose, spec, args.variant))
    rest = resting(spec, mesh, fields, result)
    why = refusal(spec, mesh, rest, args.variant, result.rests)
    if why:
        raise UserError(why)
    write_result(args, name, start, result, mesh, spec, resting_json(rest))
    return 0
