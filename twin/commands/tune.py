"""`vrscroll tune`: robust PID gains per hinge on the twin of the device profile in use, over the parameter
ranges its calibration left open (each hinge about its own values, where calibrated per hinge); stored in the
profile; with --serial, confirmed on the device. Exit 1 where the best gains found still break a limit on some
plant (each named; with --serial they are not pushed). The work and its report: twin.tuning.tuned_gains."""

from __future__ import annotations

import contextlib

from twin.commands.options import (add_device_option, add_json, add_mount, add_serial, add_threads, json_to_stdout,
                                   opened, output_file, within, write_json)
from twin.errors import UserError
from twin.evaluation.backends import BACKENDS, WORKERS_PER_CORE, make_backend
from twin.hil.confirm import confirmed
from twin.hil.device_gains import device_session
from twin.hil.identification import narrowing
from twin.tuning.tuned_gains import goal_of, ranges_line, tune_profile


def add_arguments(p) -> None:
    p.add_argument("--max-overshoot-deg", type=within(0.01, 90, "deg"), default=1.0,
                   help="largest overshoot allowed on any plant, deg (default %(default)s)")
    p.add_argument("--tolerance-pct", type=within(0, 99, "%"), default=20.0, metavar="PCT",
                   help="uncalibrated device: motor constant and gear friction +- this percent: the plants tuned "
                        "for are the nominal and the 4 corners, the cost is the worst (default %(default)s); a "
                        "calibrated profile's intervals replace it")
    p.add_argument("--step-deg", type=float, default=30.0,
                   help="step every hinge takes from flat, deg (default %(default)s)")
    p.add_argument("--duration-s", type=within(0.1, 10, "s"), default=1.0,
                   help="s simulated per candidate, and the window of the reported metrics (default %(default)s)")
    p.add_argument("--population", type=within(4, 1000, whole=True), default=32, help="candidates per generation (default %(default)s)")
    p.add_argument("--generations", type=within(1, 100, whole=True), default=8, help="cross-entropy generations (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    add_threads(p)
    p.add_argument("--backend", choices=BACKENDS,
                   help="run each plant's batch as a task on local worker processes or on Ray (RAY_ADDRESS, or a "
                        "local Ray; the ray extra) (default: every plant in one batch here, on --threads)")
    p.add_argument("--workers", type=int, help="with --backend: worker processes, or a local Ray's CPUs, at most "
                                               f"{WORKERS_PER_CORE} per core (default all cores)")
    p.add_argument("--out", type=output_file,
                   help="also write the gains to this file, JSON (default: into the device profile; gains.json "
                        "without one)")
    add_serial(p, required=False, what="also push the gains to this device and run the same step on it")
    p.add_argument("--log", default="vrscroll-tune.jsonl", help="session log with --serial (default %(default)s)")
    add_json(p, "the summary")
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile, spec = opened(args)
    stated = {"max_overshoot_deg": args.max_overshoot_deg, "step_deg": args.step_deg, "duration_s": args.duration_s}
    goal = goal_of(profile, args.max_overshoot_deg, args.tolerance_pct, args.step_deg, args.duration_s)
    say = None if json_to_stdout(args) else (lambda line: print(line, flush=True))
    if say:
        say(ranges_line(profile, goal))
    with make_backend(args.backend, args.workers) if args.backend else contextlib.nullcontext() as backend:
        tuned = tune_profile(profile, goal, stated, args.out, not args.serial, population=args.population,
                             generations=args.generations, seed=args.seed, nthread=args.threads, backend=backend,
                             progress=say)
    worst = "its worst case set by " + narrowing(tuned.worst_case) if tuned.broken else ""
    if say:
        print("\n".join(tuned.report.lines + ([worst] if worst else [])))
    if args.serial and tuned.broken:
        write_json(args.json, tuned.report.doc)
        raise UserError(f"not pushed to {args.serial}: the tuned gains break a limit on a plant the tuning covered "
                        f"(printed above), {worst}: narrow those intervals (`calibrate --serial` lying flat) or "
                        "loosen the goal")
    if args.serial:
        rows, lines = confirmed(device_session(args.serial, spec, args.log), tuned.gains.hinges, goal.step,
                                args.duration_s, lambda: tuned.keep_in(profile), profile.hinges, profile.mount, args.log)
        tuned.report.doc["device"] = rows
        if say:
            print("\n".join(lines))
    write_json(args.json, tuned.report.doc)
    return 1 if tuned.broken else 0
