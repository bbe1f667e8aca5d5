"""`vrscroll hil SCENARIO --serial PORT`: one scenario on the device and on the twin, compared (docs/tuning-hil-calibration.md;
twin.hil.hil_run)."""

from __future__ import annotations

import sys

from twin.commands.options import add_device_option, add_mount, add_rerun, add_serial, add_tolerance_deg, opened, within
from twin.formats.gains import read_gains
from twin.formats.scenario import read_scenario
from twin.hil.compare import metrics_text, not_followed
from twin.hil.device_gains import device_session
from twin.hil.hil_run import record_hil, run_folder
from viz.hil_report import write_report


def add_arguments(p) -> None:
    p.add_argument("scenario", help="scenario file, TOML or JSON (docs/tuning-hil-calibration.md)")
    add_serial(p, required=True)
    p.add_argument("--out", help="run folder (default hil-<scenario>-<time>); one that holds a run is refused "
                   "unless --overwrite")
    p.add_argument("--overwrite", action="store_true", help="record over the run already in --out (it is lost)")
    p.add_argument("--telemetry-hz", type=within(1, 1000, "Hz", whole=True), default=500, help="telemetry rate (default %(default)s)")
    p.add_argument("--gains", help="gains file (vrscroll tune --out) to push to the device before the run "
                   "(default: the device profile's gains, if it holds any)")
    p.add_argument("--log", help="session log, JSON lines (default <out>/session.jsonl)")
    add_tolerance_deg(p)
    add_rerun(p)
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile, spec = opened(args)
    scenario = read_scenario(args.scenario, spec)
    gains = read_gains(args.gains, spec.n_hinges).hinges if args.gains else \
        profile.gains if profile.gains_from != "spec" else None
    out = run_folder(scenario, args.out, args.overwrite)
    log = args.log or str(out / "session.jsonl")
    spec, run_, rows = record_hil(device_session(args.serial, spec, log), profile, scenario, args.scenario, out, gains,
                                  args.gains or profile.gains_from, log, args.telemetry_hz, args.tolerance_deg,
                                  lambda line: print(line, flush=True))
    report = write_report(spec, out, rows)
    print(metrics_text(rows))
    print(f"report: {report} (each column defined there)")
    warning = not_followed(rows)
    if warning:
        print(f"vrscroll hil: warning: {warning}", file=sys.stderr)
    if args.rerun:
        from viz.rerun_log import log_run

        print(log_run(args.rerun, spec, run_))
    return 0
