"""`vrscroll simulate`: move the twin's hinges to targets (deg), report each hinge's step response and plot it."""

from __future__ import annotations

import math
import sys

from twin.commands.options import (
    add_device_option,
    add_json,
    add_rerun,
    json_to_stdout,
    output_file,
    profile_line,
    profile_of,
    within,
    write_json,
)
from twin.sim.response import move_report
from twin.sim.twin import Twin
from viz.traces import hinge_figure
from viz.viewer import show_move


def add_arguments(p) -> None:
    p.add_argument("targets", nargs="+", type=float, metavar="DEG",
                   help="hinge targets in degrees, one per hinge (hinge 0 first); positive bends concave")
    p.add_argument("--max-time", type=within(0.01, 60, "s"), default=3.0, help="longest the move may take, s (default 3)")
    p.add_argument("--hold", action="store_true", help="run the full --max-time instead of stopping once settled")
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


def run(args) -> int:
    profile = profile_of(args)
    twin = Twin(profile.spec, profile.gains)
    if len(args.targets) != twin.spec.n_hinges:
        raise ValueError(f"expected {twin.spec.n_hinges} hinge targets in degrees, got {len(args.targets)}")
    trace = twin.move_to([math.radians(a) for a in args.targets], max_time=args.max_time,
                         stop_when_settled=not args.hold)
    rows = move_report(twin.spec, trace)
    summary = {
        "device_profile": profile.label,
        "simulated_s": round(trace.duration, 3),
        "wall_s": round(trace.wall_time, 4),
        "real_time_factor": round(trace.real_time_factor, 1),
        "settled": all(not math.isnan(r["settle_time_s"]) for r in rows),
        "hinges": rows,
    }
    if args.trace:
        trace.write_csv(args.trace, twin.spec)
        summary["trace_csv"] = args.trace
    band = math.degrees(twin.spec.settle_band * twin.spec.rad_per_count)
    hinge_figure(args.plot, f"simulate: the twin's step response ({profile.label})", [("twin", trace)],
                 range(twin.spec.n_hinges), band, settle={"twin": [r["settle_time_s"] for r in rows]})
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
        return 0
    print(profile_line(profile))
    print(f"{'hinge':>5} {'target_deg':>10} {'final_deg':>9} {'settle_time_s':>13} {'overshoot_deg':>13} "
          f"{'ss_err_deg':>10} {'ss_err_counts':>13} {'peak_A':>6}")
    for r in rows:
        print(f"{r['hinge']:>5} {r['target_deg']:>10.2f} {r['final_deg']:>9.2f} {r['settle_time_s']:>13.3f} "
              f"{r['overshoot_deg']:>13.2f} {r['steady_state_error_deg']:>10.2f} "
              f"{r['steady_state_error_counts']:>13.1f} {r['peak_current_A']:>6.2f}")
    print(f"simulated {summary['simulated_s']} s in {summary['wall_s']} s wall "
          f"({summary['real_time_factor']}x real time); settled: {summary['settled']}")
    if args.trace:
        print(f"trace: {args.trace}")
    print(f"step response: {args.plot}" + "".join("\n" + line for line in lines))
    return 0
