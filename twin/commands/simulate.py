"""`vrscroll simulate`: move the twin's hinges to targets (deg), or to an approximation's (APPROX.json, from
`vrscroll approximate --json`), from flat or --from; gate the move, report each hinge's step response and plot
it; for an approximation, the MSD where the twin ended on its target."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from twin.commands.options import (
    add_device_option,
    add_json,
    add_mount,
    add_rerun,
    json_to_stdout,
    output_file,
    profile_line,
    profile_of,
    profile_twin,
    within,
    write_json,
)
from twin.checks import cell, hinge_angles
from twin.errors import UserError
from twin.formats.move_report import move_rows
from twin.formats.target import read_approximation
from twin.formats.trace import write_trace
from twin.morphpatch.shapes import load_mesh, load_shape, shape_names
from twin.morphpatch.surface_metrics import match, match_json
from twin.records.approximation import Approximation
from twin.sim.gate import check_move
from twin.sim.response import move_report
from twin.sim.targets import check_targets
from viz.traces import hinge_figure
from viz.viewer import show_move


def add_arguments(p) -> None:
    p.add_argument("targets", nargs="+", metavar="DEG|APPROX.json",
                   help="hinge targets in degrees, one per hinge (hinge 0 first; positive bends concave), or one "
                        "approximation file (vrscroll approximate --json): its hinge angles, and its target for the MSD")
    p.add_argument("--from", dest="start", metavar="DEG,...",
                   help="the hinge angles the move starts from, degrees, comma-separated (default flat; "
                        "write --from=-30,0,... when the first is negative)")
    p.add_argument("--max-time-s", type=within(0.01, 60, "s"), default=3.0, help="longest the move may take, s (default 3)")
    p.add_argument("--hold", action="store_true", help="run the full --max-time-s instead of stopping once settled")
    p.add_argument("--trace", metavar="CSV", type=output_file, help="write the firmware-rate trace to this CSV file")
    add_json(p, "the report")
    p.add_argument("--plot", metavar="PNG", type=output_file, default="simulate.png",
                   help="step-response plot to write: per hinge angle and target, error against the settle band, "
                        "duty, current (default simulate.png)")
    p.add_argument("--view", action="store_true",
                   help="then play the move in MuJoCo's viewer; without a display, write --view-out.mp4 and .png")
    p.add_argument("--view-out", metavar="STEM", type=output_file, default="simulate_view",
                   help="video and contact sheet of --view without a display (default simulate_view)")
    add_rerun(p)
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile = profile_of(args)
    spec = profile.spec
    approx = None
    if len(args.targets) == 1 and not _number(args.targets[0]):
        approx = read_approximation(args.targets[0], spec)
        targets = approx.angles
    else:
        targets = np.radians([cell(v, f"target {k}") for k, v in enumerate(args.targets)])
    check_targets(spec, targets)
    start = np.zeros(spec.n_hinges) if not args.start else hinge_angles(
        [cell(v, f"--from[{k}]") for k, v in enumerate(args.start.split(","))], spec.n_hinges, spec.hinge_limit, "--from")
    twin = profile_twin(profile)
    gate = check_move(spec, start, targets, profile.gains, settle_limit=args.max_time_s, twin=twin)
    if gate.prediction is None:
        raise UserError(gate.refusal())
    trace = gate.prediction  # the move until settled, as simulated by the gate
    if args.hold:  # ... or the whole --max-time-s
        twin.reset(start)
        trace = twin.move_to(targets, max_time=args.max_time_s, stop_when_settled=False)
    report = move_report(twin.spec, trace)
    rows = move_rows(report)
    summary = {
        "device_profile": profile.label,
        "simulated_s": round(trace.duration, 3),
        "wall_s": round(trace.wall_time, 4),
        "real_time_factor": round(trace.real_time_factor, 1),
        "settled": report.settled,
        "start_deg": np.degrees(start).round(3).tolist(),
        "gate": gate.to_dict(),
        "hinges": rows,
    }
    if approx is not None:
        summary.update(_on_target(spec, approx, trace, args.targets[0]))
    if args.trace:
        write_trace(args.trace, trace)
        summary["trace_csv"] = args.trace
    band = math.degrees(twin.spec.settle_band * twin.spec.rad_per_count)
    hinge_figure(args.plot, f"simulate: the twin's step response ({profile.label})", [("twin", trace)],
                 range(twin.spec.n_hinges), band, settle={"twin": report.settle_time})
    summary["plot_png"] = args.plot
    lines = []
    if args.rerun:
        from viz.rerun_log import log_move

        lines.append(log_move(args.rerun, twin.spec, trace))
    if args.view:
        lines.append(show_move(twin.spec, trace, args.view_out))
    write_json(args.json, summary)
    if json_to_stdout(args):
        print("\n".join(lines), file=sys.stderr)
        return 0 if gate.passed else 1
    print(profile_line(profile))
    print(gate.text())
    print(f"{'hinge':>5} {'target_deg':>10} {'final_deg':>9} {'settle_time_s':>13} {'overshoot_deg':>13} "
          f"{'ss_err_deg':>10} {'ss_err_counts':>13} {'peak_A':>6}")
    for r in rows:
        print(f"{r['hinge']:>5} {r['target_deg']:>10.2f} {r['final_deg']:>9.2f} {r['settle_time_s']:>13.3f} "
              f"{r['overshoot_deg']:>13.2f} {r['steady_state_error_deg']:>10.2f} "
              f"{r['steady_state_error_counts']:>13.1f} {r['peak_current_A']:>6.2f}")
    print(f"simulated {summary['simulated_s']} s in {summary['wall_s']} s wall "
          f"({summary['real_time_factor']}x real time); settled: {summary['settled']}")
    if "msd_after_morph_mm" in summary:
        print(f"on {summary['target']}: MSD where the twin ended {summary['msd_after_morph_mm']} mm "
              f"(HD {summary['hd_after_morph_mm']} mm; the approximation's own {summary['approximation_msd_mm']} mm); "
              f"{summary['inside_after_morph_percent']} % of the touch surface inside the target, up to "
              f"{summary['inside_depth_after_morph_mm']} mm deep")
    elif approx is not None:
        print(f"no MSD: {summary['target_note']}")
    if args.trace:
        print(f"trace: {args.trace}")
    print(f"step response: {args.plot}" + "".join("\n" + line for line in lines))
    return 0 if gate.passed else 1


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _on_target(spec, approx: Approximation, trace, path: str) -> dict:
    """The MSD, HD (mm) and the share of the touch surface inside the target (match_json) where the twin ended, on the approximation's target (a shape's name, or a mesh path
    relative to the approximation file or the working folder); a note where the target cannot be read."""
    target = approx.target
    out = {"target": target, "approximation_msd_mm": None if approx.msd is None else round(approx.msd * 1e3, 3)}
    if target is None:
        return {**out, "target_note": f"{path} names no target"}
    if target in shape_names():
        mesh = load_shape(target)
    else:
        mesh_path = next((p for p in (Path(path).parent / target, Path(target)) if p.is_file()), None)
        if mesh_path is None:
            return {**out, "target_note": f"its target {target!r} is neither a shape nor a mesh file found here"}
        mesh = load_mesh(mesh_path)
    return {**out, **match_json(match(spec, mesh, approx.root_pose, trace.true_angle[-1], approx.widths),
                                "_after_morph")}
