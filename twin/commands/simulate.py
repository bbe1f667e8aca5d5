"""`vrscroll simulate`: move the twin's hinges to targets (deg), or to an approximation's (APPROX.json, from
`vrscroll approximate --json`), from flat or --from; gate the move, report each hinge's step response and plot
it; for an approximation, the MSD where the twin ended on its target."""

from __future__ import annotations

import sys

from twin.commands.options import (add_device_option, add_json, add_mount, add_rerun, add_slowmo, json_to_stdout,
                                   output_file, within, write_json)
from twin.evaluation.twin_move import move_lines, move_targets, simulate_move
from twin.formats.profile import chosen_profile, profile_line
from twin.formats.trace import write_trace
from twin.sim.twin import profile_twin
from viz.traces import step_figure
from viz.viewer import MIN_PLAYED_S, show_move


def add_arguments(p) -> None:
    p.add_argument("targets", nargs="+", metavar="DEG|APPROX.json",
                   help="hinge targets in degrees, one per hinge (hinge 0 first; positive bends concave), or one "
                        "approximation file (vrscroll approximate --json): its hinge angles, and its target for the MSD")
    p.add_argument("--from", dest="start", metavar="DEG,...",
                   help="the hinge angles the move starts from, degrees, comma-separated (default flat)")
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
    add_slowmo(p, MIN_PLAYED_S)
    add_rerun(p)
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile = chosen_profile(args.device, args.mount)
    spec = profile.spec
    targets, start, approx = move_targets(spec, args.targets, args.start)
    move = simulate_move(profile_twin(profile), profile.gains, start, targets, args.max_time_s, args.hold, approx,
                         args.targets[0])
    summary = move.to_json(profile.label)
    if args.trace:
        write_trace(args.trace, move.trace)
        summary["trace_csv"] = args.trace
    step_figure(args.plot, f"simulate: the twin's step response ({profile.label})", spec, move.trace,
                move.report.settle_time)
    summary["plot_png"] = args.plot
    lines = []
    if args.rerun:
        from viz.rerun_log import log_move

        lines.append(log_move(args.rerun, spec, move.trace))
    if args.view:
        lines.append(show_move(spec, move.trace, args.view_out, slowmo=args.slowmo))
    write_json(args.json, summary)
    if json_to_stdout(args):
        print("\n".join(lines), file=sys.stderr)
    else:
        print("\n".join([profile_line(profile), *move_lines(move, summary)] + ([f"trace: {args.trace}"] if args.trace
                                                                                else [])
                        + [f"step response: {args.plot}", *lines]))
    return 0 if move.gate.passed else 1
