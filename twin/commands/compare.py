"""`vrscroll compare RUN_A RUN_B ...`: HIL runs of one scenario side by side (e.g. before and after calibration):
per hinge and run the device-twin RMSE, largest error, settle times and overshoots, and a plot."""

from __future__ import annotations

from twin.commands.options import add_device_option, add_json, opened, output_file, write_json
from twin.errors import UserError
from twin.formats.run import read_run
from twin.hil.compare import METRICS, compare, metrics_text
from viz.traces import runs_figure


def add_arguments(p) -> None:
    p.add_argument("runs", nargs="+", metavar="RUN", help="HIL run folders (vrscroll hil --out), two or more")
    p.add_argument("--png", default="compare.png", type=output_file,
                   help="plot: per hinge RMSE of each run, and device - twin over time (default compare.png)")
    add_json(p, "the metrics per run and what each means")
    add_device_option(p)


def run(args) -> int:
    if len(args.runs) < 2:
        raise UserError("compare needs two or more run folders")
    profile, spec = opened(args)
    runs = [read_run(r, spec, incomplete=True) for r in args.runs]
    for path, r in zip(args.runs, runs):
        if r.twin is None or not len(r.device.time) or not len(r.twin.time):
            what = "no device frames" if not len(r.device.time) else "no twin.csv" if r.twin is None else \
                "no twin rows"
            raise UserError(f"{path}: {what}: a run is compared device against twin, both recorded")
    if len({r.scenario for r in runs}) > 1:
        print("note: the runs played different scenarios (" + ", ".join(sorted({r.scenario for r in runs}))
              + "): their metrics are compared, the traces not time-aligned")
    table = {}
    for path, r in zip(args.runs, runs):
        rows = compare(spec, r.device, r.twin, [t for t, _ in r.changes] or [0.0])
        table[path] = rows
        print(f"\n{path} ({r.scenario}, {r.status}, device profile {r.meta.get('device_profile', 'not recorded')})")
        print(metrics_text(rows))
    base, last = table[args.runs[0]], table[args.runs[-1]]
    print(f"\nRMSE device - twin, {args.runs[-1]} against {args.runs[0]}: "
          + "  ".join(f"h{a['hinge']} x{b['rmse_deg'] / a['rmse_deg']:.2f}" if a["rmse_deg"] > 0 else f"h{a['hinge']} -"
                      for a, b in zip(base, last)))
    runs_figure(args.png, [(p, r) for p, r in zip(args.runs, runs)], table, spec.n_hinges)
    print(f"plot: {args.png} (what each metric means: a run's report.md, or --json)")
    write_json(args.json, {"runs": table, "metrics": {k: m for k, _, m in METRICS}})
    return 0
