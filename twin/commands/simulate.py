"""`vrscroll simulate`: move the twin's hinges to targets (deg), or to an approximation's (APPROX.json, from
`vrscroll approximate --json`), from flat or --from; gate the move, report each hinge's step response and plot
it; for an approximation, the MSD where the twin ended on its target."""

from __future__ import annotations

import math
import sys

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
from twin.evaluation.twin_move import simulate_move
from twin.formats.target import read_approximation
from twin.formats.trace import write_trace
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
    move = simulate_move(profile_twin(profile), profile.gains, start, targets, args.max_time_s, args.hold, approx,
                         args.targets[0])
    gate, trace, summary = move.gate, move.trace, move.to_json(profile.label)
    if args.trace:
        write_trace(args.trace, trace)
        summary["trace_csv"] = args.trace
    hinge_figure(args.plot, f"simulate: the twin's step response ({profile.label})", [("twin", trace)],
                 range(spec.n_hinges), math.degrees(spec.settle_band * spec.rad_per_count),
                 settle={"twin": move.report.settle_time})
    summary["plot_png"] = args.plot
    lines = []
    if args.rerun:
        from viz.rerun_log import log_move

        lines.append(log_move(args.rerun, spec, trace))
    if args.view:
        lines.append(show_move(spec, trace, args.view_out))
    write_json(args.json, summary)
    if json_to_stdout(args):
        print("\n".join(lines), file=sys.stderr)
        return 0 if gate.passed else 1
    print(profile_line(profile))
    print(gate.text())
    print(f"{'hinge':>5} {'target_deg':>10} {'final_deg':>9} {'settle_time_s':>13} {'overshoot_deg':>13} "
          f"{'ss_err_deg':>10} {'ss_err_counts':>13} {'peak_A':>6}")
    for r in summary["hinges"]:
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
