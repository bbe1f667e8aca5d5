"""`vrscroll calibrate RUN... --holdout RUN`: fit the twin's plant to recorded HIL runs, say what the runs
show and what they do not; `vrscroll calibrate --scenario FILE`: write the scenario to record them with
(docs/tuning-hil-calibration.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from twin.errors import UserError
from twin.commands.options import add_device_option, profile_line
from twin.device.profile import profile_dir, set_default
from twin.device.spec import SPEC_PATH
from twin.formats.gains import read_gains
from twin.formats.profile import select_profile, spec_defaults, write_profile_spec
from twin.formats.run import read_run
from twin.formats.scenario import write_scenario
from twin.device.spec_toml import write_spec_toml
from twin.hil.calibration import calibrate, trace_rmse
from twin.hil.calibration_scenario import calibration_scenario
from twin.hil.device_gains import device_gains
from twin.link.serial_link import Link, LinkError


def add_arguments(p) -> None:
    p.add_argument("runs", nargs="*", metavar="RUN", help="HIL run folders (vrscroll hil --out) to fit to")
    p.add_argument("--holdout", metavar="RUN", help="a HIL run folder not fitted to: fit error before/after")
    p.add_argument("--out", help="also write the calibrated spec to this TOML (without a device profile: default "
                                 "spec.calibrated.toml)")
    p.add_argument("--generations", type=int, default=8,
                   help="cross-entropy generations of the search (default %(default)s)")
    p.add_argument("--population", type=int, default=24, help="twin replays per generation (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--incomplete", action="store_true",
                   help="also fit runs that did not complete (killed or interrupted while recorded): what they "
                        "recorded is used, and each is named (default: such a run is refused)")
    p.add_argument("--scenario", metavar="FILE",
                   help="instead of fitting: write the calibration scenario (TOML) for the gains the device has "
                        "(--port reads them; --gains FILE; default: the profile's), to record with `vrscroll hil`")
    p.add_argument("--port", help="with --scenario: read the device's gains from it")
    p.add_argument("--gains", help="with --scenario: a gains file instead of the device's")
    p.add_argument("--seed", type=int, default=0, help="with --scenario: which angles (default %(default)s)")
    p.add_argument("--cycles", type=int, default=2,
                   help="with --scenario: cycles of a large move and a slow ramp out and back (default %(default)s)")
    add_device_option(p)


def _profile(args):
    """The profile calibrated (a new one for a --device not there yet), and whether it is new."""
    if args.device and not profile_dir(args.device).is_dir():
        return spec_defaults(), True
    return select_profile(args.device), False


def write_calibration_scenario(args, profile) -> int:
    spec = profile.spec
    if args.gains:
        gains = read_gains(args.gains, spec.n_hinges)
    elif args.port:
        try:
            with Link(args.port) as link:
                gains = device_gains(link, spec.n_hinges)
        except LinkError as exc:
            raise UserError(f"link: {exc}") from None
    else:
        gains = profile.gains
    if args.cycles < 1:
        raise UserError("--cycles must be at least 1")
    scenario = calibration_scenario(spec, gains, seed=args.seed, cycles=args.cycles,
                                    name=f"calibration-{args.seed}")
    write_scenario(args.scenario, scenario)
    print(f"calibration scenario written to {args.scenario}: {len(scenario.times)} steps, {scenario.duration:.2f} s "
          f"(timed for the gains of {args.gains or args.port or profile.gains_from}); record it with "
          f"`vrscroll hil {args.scenario} --port PORT`")
    return 0


def run(args) -> int:
    profile, new = _profile(args)
    name = args.device or profile.name
    if args.scenario:
        if args.runs:
            raise UserError("--scenario writes the calibration scenario; give the RUN folders without it")
        print(profile_line(profile))
        return write_calibration_scenario(args, profile)
    if not args.runs:
        raise UserError("give the HIL run folders to fit to (or --scenario FILE to write the scenario to record)")
    spec = profile.spec
    try:
        runs = [read_run(r, spec, incomplete=args.incomplete) for r in args.runs]
        holdout = read_run(args.holdout, spec, incomplete=args.incomplete) if args.holdout else None
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot read a HIL run: {exc}" + ("" if args.incomplete or "did not complete" not in str(exc)
                                                            else " (--incomplete uses what it recorded)")) from None
    for r in runs + ([holdout] if holdout else []):
        if r["meta"]["status"] != "complete":
            print(f"note: {r['dir']} did not complete (status {r['meta']['status']!r}); using the "
                  f"{len(r['device']['time_s'])} device frames it recorded", file=sys.stderr)
        if len(r["device"]["time_s"]) < 10:
            raise UserError(f"{r['dir']}: fewer than 10 device frames; nothing to fit")
        if "before" not in r["meta"]:
            raise UserError(f"{r['dir']}: recorded without the device's state before the run; record it again")
    res = calibrate(runs, spec, population=args.population, generations=args.generations,
                    progress=None if args.json else lambda g, c: print(
                        f"generation {g + 1}/{args.generations}: best cost {c:.4g}", flush=True))
    source = "calibrated from " + ", ".join(str(Path(r).resolve()) for r in args.runs) + " (vrscroll calibrate)"
    fitted = {p: e.value for p, e in res.estimates.items() if e.fitted}
    written = []
    if name:
        calibration = {"runs": [str(Path(r).resolve()) for r in args.runs],
                       "parameters": {p: e.to_json() for p, e in res.estimates.items()}}
        written.append(str(write_profile_spec(name, fitted, source, calibration)))
        set_default(name)
    if args.out or not name:
        out = args.out or "spec.calibrated.toml"
        template = profile.folder / "spec.toml" if profile.folder else SPEC_PATH
        write_spec_toml(out, template, fitted, source,
                        header="Calibrated device spec, written by `vrscroll calibrate` (see "
                               "docs/tuning-hil-calibration.md).")
        written.append(out)
    out = {"device_profile": name or profile.label, "prior": "spec defaults" if new else profile.label,
           "written": written,
           "parameters": {p: e.to_json() for p, e in res.estimates.items()},
           "scales": {k: round(v, 4) for k, v in res.scales.items()},
           "singular_values": [round(s, 4) for s in res.singular_values],
           "autocorrelation_frames": round(res.autocorrelation_frames, 1),
           "fit_rmse_deg": {"before": round(res.rmse_before, 4), "after": round(res.rmse_after, 4)},
           "iterations": res.iterations, "replays": res.evaluations}
    if holdout:
        before, after = trace_rmse(holdout, spec, spec), trace_rmse(holdout, res.spec, spec)
        out["holdout"] = {"run": args.holdout, "rmse_before_deg": before.round(4).tolist(),
                          "rmse_after_deg": after.round(4).tolist(),
                          "overall_before_deg": round(float(np.sqrt(np.mean(before ** 2))), 4),
                          "overall_after_deg": round(float(np.sqrt(np.mean(after ** 2))), 4)}
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"device profile: {out['device_profile']} (prior: {out['prior']})")
    print(f"fitted in {res.iterations} generations ({res.evaluations} twin replays); x prior value, 95 % interval:")
    for p, e in res.estimates.items():
        print(f"  {p:<14} x{e.value / e.prior:.3f}  = {e.value:.6g}  interval x{e.low / e.prior:.3f} .. "
              f"x{e.high / e.prior:.3f}  {'identifiable' if e.identifiable else 'NOT IDENTIFIABLE'}: {e.note}")
    print("singular values of the cost's Hessian (log parameters, unit diagonal): "
          + " ".join(f"{s:.3g}" for s in res.singular_values)
          + f"; residual autocorrelation {res.autocorrelation_frames:.0f} frames")
    print(f"fit RMSE (training runs, hinge angles): {res.rmse_before:.3f} deg -> {res.rmse_after:.3f} deg")
    if holdout:
        h = out["holdout"]
        print("held-out RMSE per hinge, deg: before " + " ".join(f"{x:.3f}" for x in h["rmse_before_deg"]))
        print("                              after  " + " ".join(f"{x:.3f}" for x in h["rmse_after_deg"]))
        print(f"held-out RMSE overall (every frame of every hinge), deg: {h['overall_before_deg']:.3f} -> "
              f"{h['overall_after_deg']:.3f}")
    print("calibrated spec written to " + ", ".join(written))
    return 0
