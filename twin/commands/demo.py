"""`vrscroll demo`: the whole path once. Approximate a shape or a mesh (--mesh) from its default start (or --start),
validate the move on the twin (the gate: range, collisions, settling, current),
simulate the morph with the firmware in the loop, check the pen redirection the
reached shape needs against the perception thresholds (a warning, or with --strict
a refusal), report all, write a picture.
"""

from __future__ import annotations

import numpy as np

import math

from twin.commands.approximate import target_and_start
from twin.commands.options import (
    add_device_option,
    add_json,
    add_mount,
    add_rerun,
    add_target,
    output_file,
    profile_line,
    profile_of,
    profile_twin,
    write_json,
)
from twin.device.kinematics import flap_frames
from twin.evaluation.morph_outcome import morph_outcome
from twin.formats.move_report import move_rows
from twin.formats.target import approximation_json
from twin.morphpatch.approximation import VARIANTS, approximate, measured
from twin.morphpatch.fields import build_fields
from twin.morphpatch.shapes import shape_names
from twin.morphpatch.surface_metrics import inside_text, match_json
from twin.sim.gate import redirection_check
from viz.render import target_view
from viz.scene import render_approximation
from viz.traces import hinge_figure
from viz.viewer import show_angles


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
    add_rerun(p)
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile = profile_of(args)
    spec = profile.spec
    print(profile_line(profile), flush=True)
    if not args.mesh and not args.shape:
        args.shape = "cylinder"
    name, mesh, start, pose = target_and_start(args)
    print(f"[1/5] fields of {name} (cached after the first run) ...", flush=True)
    fields = build_fields(mesh)
    approximate(fields, pose, spec, args.variant)  # warm-up: loads compiled code
    approx = measured(spec, mesh, approximate(fields, pose, spec, args.variant))
    print(f"[2/5] {args.variant} approximated in {approx.time * 1e3:.2f} ms: MSD {approx.msd * 1e3:.2f} mm, "
          f"HD {approx.hd * 1e3:.2f} mm; hinges {np.degrees(approx.angles).round(1).tolist()} deg", flush=True)
    print(f"      {approx.inside:.0%} of the touch surface inside the target, up to {approx.depth * 1e3:.1f} mm deep"
          + ("" if approx.rests is not False else "; ours found no pose resting on it from outside"), flush=True)

    print("[3/5] validating and simulating the morph on the twin (firmware PID at 1 kHz) ...", flush=True)
    outcome = morph_outcome(spec, mesh, fields, approx, profile_twin(profile), profile.gains)
    gate, trace, report, end, redirection = (outcome.gate, outcome.gate.prediction, outcome.report, outcome.end,
                                             outcome.redirection)
    end_angles = outcome.reached
    hinges = move_rows(report) if report is not None else []
    settle = round(outcome.settle_time, 4)
    final_err = (round(math.degrees(np.abs(report.steady_state_error).max()), 3) if report is not None
                 else float("nan"))
    # the residual mismatch where the twin ended, as the pen redirection must cover it
    gate.checks.append(redirection_check(redirection, strict=args.strict))
    print(gate.text())
    print(f"      morph settled in {settle:.3f} s (slowest hinge), largest final error {final_err:.2f} deg; "
          f"MSD where the twin ended {end.msd * 1e3:.2f} mm (HD {end.hd * 1e3:.2f} mm); {inside_text(end)}")
    print(f"[4/5] pen redirection over the reached shape: {redirection['share_within']:.1%} of the touch surface "
          f"within {redirection['position_threshold_mm']:g} mm / {redirection['rotation_threshold_deg']:g} deg "
          f"(largest {redirection['largest_offset_mm']:.1f} mm, {redirection['largest_rotation_deg']:.1f} deg)")

    frames = flap_frames(spec, end_angles, approx.root_pose, approx.widths)
    start_frames = flap_frames(spec, np.zeros(spec.n_hinges), pose, approx.widths)
    notes = [f"start (outlined): {', '.join(f'{v:g}' for v in start)} (x y z mm, roll pitch yaw deg)",
             "approximation: " + " ".join(f"{a:.1f}" for a in np.degrees(approx.angles)) + " deg",
             "twin ended at:  " + " ".join(f"{a:.1f}" for a in np.degrees(end_angles)) + " deg"]
    failed = "; ".join(([] if gate.passed else ["the gate refused: " + ", ".join(c.name for c in gate.failed)])
                       + ([] if approx.rests is not False else ["no pose resting from outside"])) or None
    render_approximation(spec, mesh, frames, approx.widths, args.png, notes=notes, start_frames=start_frames,
                         title=f"{name}, {args.variant}: twin after the morph, MSD {end.msd * 1e3:.2f} mm, "
                               f"HD {end.hd * 1e3:.2f} mm", failed=failed)
    print(f"[5/5] picture: {args.png}")
    if trace is not None:
        hinge_figure(args.plot, f"demo: {name} morph on the twin", [("twin", trace)], range(spec.n_hinges),
                     math.degrees(spec.settle_band * spec.rad_per_count),
                     settle={"twin": report.settle_time})
        print(f"      step response: {args.plot}")
        if args.rerun:
            from viz.rerun_log import log_move

            print("      " + log_move(args.rerun, spec, trace, mesh, approx.root_pose, approx.widths))
    if args.view:
        target = target_view(spec, mesh, approx.root_pose, end_angles, approx.widths)
        if trace is None:  # the gate refused the move before simulating it: the device stays flat (shown for 1 s)
            t, angles = np.array([0.0, 1.0]), np.tile(end_angles, (2, 1))
        else:
            t, angles = trace.time, trace.true_angle
        print("      " + show_angles(spec, t, angles, args.view_out, target=target, failed=failed))
    report = {
        "device_profile": profile.label,
        "target": name,
        "start_mm_deg": start,
        "approximation": approximation_json(approx),
        "gate": gate.to_dict(),
        "redirection": redirection,
        "morph": {"settle_time_s": settle, "largest_final_error_deg": final_err, "hinges": hinges,
                  **match_json(end, "_after_morph")},
        "png": args.png,
        "step_png": args.plot if trace is not None else None,
    }
    write_json(args.json, report)
    return 0 if gate.passed else 1
