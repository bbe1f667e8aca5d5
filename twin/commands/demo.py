"""`vrscroll demo`: the whole path once. Approximate a shape or a mesh (--mesh) from its default start (or --start),
validate the move on the twin (the gate: range, collisions, settling, current),
simulate the morph with the firmware in the loop, check the pen redirection the
reached shape needs against the perception thresholds (a warning, or with --strict
a refusal), report all, write a picture. The path: twin.evaluation.demo_morph; its pictures: viz.demo_pictures.
"""

from __future__ import annotations

from twin.commands.approximate import target_and_start
from twin.commands.options import (add_device_option, add_json, add_mount, add_rerun, add_slowmo, add_target,
                                   output_file, write_json)
from twin.evaluation.demo_morph import demo_morph
from twin.formats.profile import chosen_profile, profile_line
from twin.morphpatch.approximation import VARIANTS
from twin.morphpatch.shapes import shape_names
from twin.sim.twin import profile_twin
from viz.demo_pictures import demo_pictures
from viz.viewer import MIN_PLAYED_S


def add_arguments(p) -> None:
    add_target(p, shape_names(), required=False, role="the target (default: the cylinder)")
    p.add_argument("--variant", choices=VARIANTS, default="full",
                   help="approximation: the paper's full, no_hcevf, or ours, refined (default full)")
    p.add_argument("--png", default="demo.png", type=output_file,
                   help="picture to write: the device where the twin ended on the target, coloured by distance, "
                        "its start outlined, the hinge angles (default demo.png)")
    p.add_argument("--plot", metavar="PNG", default="demo_step.png", type=output_file,
                   help="the morph's step response per hinge (default demo_step.png)")
    add_json(p, "the report")
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 1) when the pen redirection goes beyond the perception thresholds")
    p.add_argument("--view", action="store_true",
                   help="play the morph in MuJoCo's viewer beside the target (red where the touch surface ends inside "
                        "it; FAILED where the gate refused); without a display, write --view-out.mp4 and .png")
    p.add_argument("--view-out", metavar="STEM", type=output_file, default="demo_view",
                   help="video and contact sheet of --view without a display (default demo_view)")
    add_slowmo(p, MIN_PLAYED_S)
    add_rerun(p)
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile = chosen_profile(args.device, args.mount)
    print(profile_line(profile), flush=True)
    if not args.mesh and not args.shape:
        args.shape = "cylinder"
    name, mesh, start, pose = target_and_start(args)
    say = (lambda line: print(line, flush=True))
    demo = demo_morph(profile, profile_twin(profile), name, mesh, start, pose, args.variant, args.strict, say)
    pictures = demo_pictures(profile.spec, demo, name, mesh, start, pose, args.png, args.plot, args.rerun,
                             args.view_out if args.view else None, args.slowmo, say)
    write_json(args.json, {**demo.doc, **pictures})
    return 0 if demo.outcome.gate.passed else 1
