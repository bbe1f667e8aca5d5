"""`vrscroll tune`: robust PID gains per hinge on the twin of the device profile in use, over the parameter
ranges its calibration left open (each hinge about its own values, where calibrated per hinge); stored in the
profile; with --serial, confirmed on the device. Exit 1 where the best gains found still break a limit on some
plant (each named; with --serial they are not pushed)."""

from __future__ import annotations

import contextlib
import math

import numpy as np

from twin.commands.options import (
    add_device_option,
    add_json,
    add_mount,
    add_serial,
    add_threads,
    device_session,
    json_to_stdout,
    link_errors,
    opened,
    output_file,
    within,
    write_json,
)
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import SPEC_PATH
from twin.device.spec_toml import shown_range, spec_units
from twin.errors import UserError
from twin.evaluation.backends import BACKENDS, WORKERS_PER_CORE, make_backend
from twin.formats.gains import write_gains
from twin.formats.move_report import move_rows
from twin.formats.profile import write_profile_gains
from twin.hil.confirm import confirm_step
from twin.hil.identification import narrowing
from twin.hil.mirror import DeviceNotReady
from twin.records.gains import Gains
from twin.sim.gate import GateRefused
from twin.tuning.tuner import profile_goal, step_report, tune, tuned_summary


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


def _line(label, rows):
    return f"{label:<16}" + "  ".join(f"{r['settle_time_s'] * 1000:6.0f} ms {r['overshoot_deg']:5.2f} deg"
                                      if not math.isnan(r['settle_time_s']) else f"{'unsettled':>9} "
                                      f"{r['overshoot_deg']:5.2f} deg" for r in rows)


def run(args) -> int:
    profile, spec = opened(args)
    step = math.radians(args.step_deg)
    if not abs(step) <= spec.hinge_limit:
        raise UserError(f"--step-deg {args.step_deg}: outside the hinge range")
    smallest = 2 * spec.settle_band * spec.rad_per_count  # a step inside the settle band is settled before it starts
    if not abs(step) >= smallest:
        raise UserError(f"--step-deg {args.step_deg}: a step must leave the settle band to test anything: at least "
                        f"{math.degrees(smallest):.2f} deg (twice the band of {spec.settle_band} counts)")
    goal = profile_goal(profile, math.radians(args.max_overshoot_deg), args.tolerance_pct / 100, step, args.duration_s)
    ranges = goal.ranges
    before = profile.gains
    quiet = json_to_stdout(args)
    if not quiet:
        units = spec_units(SPEC_PATH)
        print(("calibrated: the twin's values that reproduce its runs" if ranges.calibrated else ranges.what)
              + ": tuned over " + ", ".join(f"{p} {shown_range(lo, hi, units.get(p, ''))}"
                                           for p, (lo, hi) in ranges.shared.items())
              + f" ({2 ** len(ranges.shared) + 1} plants: nominal and corners)"
              + ("; each hinge about its own calibrated values, at its own intervals' corners" if profile.hinges
                 else ""))
    with make_backend(args.backend, args.workers) if args.backend else contextlib.nullcontext() as backend:
        result = tune(spec, goal, population=args.population, generations=args.generations, seed=args.seed,
                      nthread=args.threads, start=before, backend=backend,
                      progress=None if quiet else lambda g, c, t: print(
                          f"generation {g + 1}/{args.generations}: worst-plant cost per hinge "
                          + " ".join(f"{x * 1000:5.0f}" for x in c) + f" ms  ({t:.1f} s)", flush=True))
    rows_before = move_rows(step_report(spec, before, goal, hinges=profile.hinges)[0])
    rows_after = move_rows(step_report(spec, result.gains, goal, hinges=profile.hinges)[0])
    meta = {"device_profile": profile.label, **tuned_summary(goal, result, {
        "max_overshoot_deg": args.max_overshoot_deg, "step_deg": args.step_deg, "duration_s": args.duration_s})}
    written = []
    if args.out or not profile.name:
        written.append(args.out or "gains.json")
        write_gains(written[-1], Gains(result.gains, meta))

    def into_profile() -> None:  # with --serial, only once the device holds them: the profile says what it has
        if profile.name:
            written.insert(0, str(write_profile_gains(profile.name, Gains(result.gains, meta))))

    if not args.serial:
        into_profile()
    summary = {"gains_files": written, "before": rows_before, "after": rows_after, **meta}
    if not quiet:
        print(f"tuned in {result.wall_time:.1f} s ({result.simulations} simulations of {args.duration_s} s); "
              f"nominal twin, step to {args.step_deg} deg, per hinge settle / overshoot:")
        print(_line("before", rows_before))
        print(_line("tuned", rows_after))
        print("worst plant     " + "  ".join(f"{s * 1000:6.0f} ms {math.degrees(o):5.2f} deg"
                                          for s, o in zip(result.settle, result.overshoot)))
        print("worst case set by (each range's ends, one at a time): " + "; ".join(
            f"hinge {h} {r['parameter']} {r['end']}" for h, r in enumerate(result.sensitivity)))
        print("every limit kept on every plant" if not result.broken else
              "NOT KEPT on its worst plant (the best the search found):\n  " + "\n  ".join(result.broken)
              + "\nits worst case set by " + narrowing(result.sensitivity, np.flatnonzero(result.cost >= goal.duration)))
        print("gains written to " + (", ".join(written) if written else
                                     f"device profile {profile.name} once the device holds them"))
    if args.serial and result.broken:
        write_json(args.json, summary)
        raise UserError(f"not pushed to {args.serial}: the tuned gains break a limit on a plant the tuning covered "
                        "(printed above), its worst case set by "
                        + narrowing(result.sensitivity, np.flatnonzero(result.cost >= goal.duration))
                        + ": narrow those intervals (`calibrate --serial` lying flat) or loosen the goal")
    if args.serial:
        summary["device"] = confirm_on_device(args, spec, result.gains, step, into_profile, quiet=quiet,
                                               hinges=profile.hinges, mount=profile.mount)
        summary["gains_files"] = written
    write_json(args.json, summary)
    return 1 if result.broken else 0


def confirm_on_device(args, spec, gains, step, pushed, quiet=False, hinges=None, mount=DEFAULT_MOUNT) -> list[dict]:
    """The tuned gains pushed and a step run on the device beside the twin's prediction (twin.hil.confirm),
    printed; pushed() is called once the device holds them."""
    held = []  # once the device holds the tuned gains

    def hold() -> None:
        pushed()
        held.append(True)

    try:
        with link_errors(f" (session log: {args.log})"), device_session(args, spec) as (link, spec):
            rows, message = confirm_step(link, spec, gains, np.full(spec.n_hinges, step), args.duration_s, hold,
                                         hinges, mount)
    except (GateRefused, DeviceNotReady) as exc:
        raise UserError(f"{exc} (" + ("the tuned gains are on the device and in its profile" if held else
                                      "nothing pushed: the device holds the gains it had") + ")") from None
    if not quiet:
        print(f"device at {args.serial}: {message}")
        print(f"{'hinge':>5} {'device settle s':>15} {'twin settle s':>13} {'device over deg':>15} "
              f"{'twin over deg':>13}")
        for r in rows:
            print(f"{r['hinge']:>5} {r['device_settle_s']:>15.3f} {r['twin_settle_s']:>13.3f} "
                  f"{r['device_overshoot_deg']:>15.3f} {r['twin_overshoot_deg']:>13.3f}")
    return rows
