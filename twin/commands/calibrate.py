"""`vrscroll calibrate --serial PORT --device NAME`: run the device's identification experiments (open-loop
programs its firmware runs, the device lying flat) and fit each hinge's drive train on the twin's replays of
them; `vrscroll calibrate RUN... --holdout RUN`: fit the twin's plant to recorded HIL runs. Each says what it
shows and what it does not (docs/tuning-hil-calibration.md; `vrscroll scenario` writes the scenario to record).
The work and its report: twin.hil.calibration_report."""

from __future__ import annotations

import sys
from pathlib import Path

from twin.commands.options import (
    add_device_option,
    add_json,
    add_refused,
    add_serial,
    add_threads,
    json_to_stdout,
    output_file,
    within,
    write_json,
)
from twin.errors import UserError
from twin.formats.profile import profile_or_new
from twin.hil.calibration_report import calibrate_runs, check_lying_flat, identify
from twin.hil.device_gains import device_session

MAX_GENERATIONS = 100  # cross-entropy generations: the search settles in under ten
MAX_POPULATION = 1000  # twin replays per generation


def add_arguments(p) -> None:
    p.add_argument("runs", nargs="*", metavar="RUN", help="HIL run folders (vrscroll hil --out) to fit to")
    add_serial(p, required=False, what="the device to identify instead, lying flat on a table with its zero "
                                       "confirmed there (`vrscroll zero`): it runs its own open-loop experiments, "
                                       "each hinge raised off the table and driven back")
    p.add_argument("--log", help="with --serial: the session log, JSON lines")
    p.add_argument("--holdout", metavar="RUN", help="a HIL run folder not fitted to: fit error before/after")
    p.add_argument("--out", type=output_file,
                   help="also write the calibrated spec to this TOML (without a device profile: default "
                        "spec.calibrated.toml)")
    p.add_argument("--generations", type=within(1, MAX_GENERATIONS, whole=True), default=8,
                   help="cross-entropy generations of the search (default %(default)s)")
    p.add_argument("--population", type=within(4, MAX_POPULATION, whole=True), default=24, help="twin replays per generation (default %(default)s)")
    add_threads(p)
    p.add_argument("--per-hinge", action="store_true",
                   help="then fit each hinge's own no-load speed, friction, damping and rotor inertia about the "
                        "shared values, where the runs show them: kept in the device profile, whose twin then "
                        "gives each hinge its own (--out's TOML holds the shared values only)")
    add_json(p, "the result")
    p.add_argument("--incomplete", action="store_true",
                   help="also fit runs that did not complete (killed or interrupted while recorded): what they "
                        "recorded is used, and each is named (default: such a run is refused)")
    add_refused(p, "--scenario", "`vrscroll scenario FILE`")
    add_device_option(p)


def run(args) -> int:
    profile, new = profile_or_new(args.device)  # a --device not there yet: a new profile
    name, prior = args.device or profile.name, "spec defaults" if new else profile.label
    say = None if json_to_stdout(args) else (lambda line: print(line, flush=True))
    if args.serial:
        if args.runs or args.holdout or args.per_hinge:
            raise UserError("--serial identifies the device itself: give no runs, --holdout or --per-hinge with it")
        if not new:
            check_lying_flat(profile)
        report = identify(device_session(args.serial, profile.spec, args.log), profile, name, prior, say)
    else:
        if not args.runs:
            raise UserError("give the HIL run folders to fit to (`vrscroll scenario FILE` writes the scenario to record)")
        if args.holdout and any(Path(args.holdout).resolve() == Path(r).resolve() for r in args.runs):
            raise UserError(f"--holdout {args.holdout} is one of the runs fitted to: hold out a run recorded apart")
        report = calibrate_runs(profile, name, prior, args.runs, args.holdout, per_hinge=args.per_hinge,
                                out=args.out, incomplete=args.incomplete, population=args.population,
                                generations=args.generations, nthread=args.threads, progress=say,
                                note=lambda line: print(line, file=sys.stderr))
    write_json(args.json, report.doc)
    if say:
        print("\n".join(report.lines))
    return 0
