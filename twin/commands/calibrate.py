"""`vrscroll calibrate --serial PORT --device NAME`: run the device's identification experiments (open-loop
programs its firmware runs, the device lying flat) and fit each hinge's drive train on the twin's replays of
them; `vrscroll calibrate RUN... --holdout RUN`: fit the twin's plant to recorded HIL runs. Each says what it
shows and what it does not (docs/tuning-hil-calibration.md; `vrscroll scenario` writes the scenario to record)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from twin.commands.options import (
    add_device_option,
    add_json,
    add_refused,
    add_serial,
    add_threads,
    device_session,
    json_to_stdout,
    output_file,
    select_profile,
    within,
    write_json,
)
from twin.device.profile import profile_dir, set_default
from twin.device.spec import SPEC_PATH
from twin.device.spec_toml import shown, shown_range, spec_units, write_spec_toml
from twin.errors import UserError
from twin.formats.profile import spec_defaults, updated, write_profile
from twin.formats.run import read_run
from twin.hil.calibration import MAX_HALFWIDTH, calibrate, calibrate_hinges, floor_deg, trace_rmse, unexplained
from twin.hil.compare import not_followed
from twin.hil.identification import PROFILED, estimates, experiments, fit_hinge, shared_estimates
from twin.link.serial_link import LinkError, NackError
from twin.records.calibration import Calibration


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


MAX_GENERATIONS = 100  # cross-entropy generations: the search settles in under ten
MAX_POPULATION = 1000  # twin replays per generation


def _profile(args):
    """The profile calibrated (a new one for a --device not there yet), and whether it is new."""
    if args.device and not profile_dir(args.device).is_dir():
        return spec_defaults(), True
    return select_profile(args.device), False


def run(args) -> int:
    profile, new = _profile(args)
    name = args.device or profile.name
    if args.serial:
        if args.runs or args.holdout or args.per_hinge:
            raise UserError("--serial identifies the device itself: give no runs, --holdout or --per-hinge with it")
        return _identify(args, profile, name, new)
    if not args.runs:
        raise UserError("give the HIL run folders to fit to (`vrscroll scenario FILE` writes the scenario to record)")
    if args.holdout and any(Path(args.holdout).resolve() == Path(r).resolve() for r in args.runs):
        raise UserError(f"--holdout {args.holdout} is one of the runs fitted to: hold out a run recorded apart")
    spec = profile.spec
    try:
        runs = [read_run(r, spec, incomplete=args.incomplete) for r in args.runs]
        holdout = read_run(args.holdout, spec, incomplete=args.incomplete) if args.holdout else None
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot read a HIL run: {exc}" + ("" if args.incomplete or "did not complete" not in str(exc)
                                                            else " (--incomplete uses what it recorded)")) from None
    for r in runs + ([holdout] if holdout else []):
        if r.status != "complete":
            print(f"note: {r.dir} did not complete (status {r.status!r}); using the "
                  f"{len(r.device.time)} device frames it recorded", file=sys.stderr)
        if len(r.device.time) < 10:
            raise UserError(f"{r.dir}: fewer than 10 device frames; nothing to fit")
        if r.start.before_state is None:
            raise UserError(f"{r.dir}: recorded without the device's state before the run; record it again")
        warning = not_followed([{"hinge": k, "rmse_deg": float(x)} for k, x in enumerate(trace_rmse(r, spec, spec))])
        if warning:
            print(f"vrscroll calibrate: warning: {r.dir}: {warning}", file=sys.stderr)
    res = calibrate(runs, spec, population=args.population, generations=args.generations, nthread=args.threads,
                    progress=None if json_to_stdout(args) else lambda g, c: print(
                        f"generation {g + 1}/{args.generations}: best cost {c:.4g}", flush=True))
    hc = hinge_fit = None
    if args.per_hinge:
        hc = calibrate_hinges(runs, res.spec, population=args.population, generations=args.generations,
                              shared_estimates=res.estimates, nthread=args.threads,
                              progress=None if json_to_stdout(args) else lambda g, c: print(
                                  f"per hinge, generation {g + 1}/{args.generations}: best cost {c:.4g}", flush=True))
        hinge_fit = _hinge_fit(hc, holdout, res.spec)
    source = "calibrated from " + ", ".join(str(Path(r).resolve()) for r in args.runs) + " (vrscroll calibrate)"
    fitted = {p: e.value for p, e in res.estimates.items() if e.fitted}
    written = []
    if name:
        calibration = Calibration([str(Path(r).resolve()) for r in args.runs], res.estimates,
                                  hc.estimates if hinge_fit and hinge_fit["kept"] else None)
        written.append(str(write_profile(updated(profile, fitted, source, name=name, calibration=calibration))))
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
           "bounded": {p: e.to_json() for p, e in res.bounded.items()},
           "scales": {k: round(v, 4) for k, v in res.scales.items()},
           "singular_values": [round(s, 4) for s in res.singular_values],
           "autocorrelation_frames": round(res.autocorrelation_frames, 1),
           "fit_rmse_deg": {"before": round(res.rmse_before, 4), "after": round(res.rmse_after, 4)},
           "per_hinge": _per_hinge(res.hinge_rmse_after, res.hinge_floor),
           "iterations": res.iterations, "replays": res.evaluations}
    if holdout:
        before, after = trace_rmse(holdout, spec, spec), trace_rmse(holdout, res.spec, spec)
        out["holdout"] = {"run": args.holdout, "rmse_before_deg": before.round(4).tolist(),
                          "rmse_after_deg": after.round(4).tolist(),
                          "per_hinge": _per_hinge(after, floor_deg(holdout, spec)),
                          "overall_before_deg": round(float(np.sqrt(np.mean(before ** 2))), 4),
                          "overall_after_deg": round(float(np.sqrt(np.mean(after ** 2))), 4)}
    if hinge_fit:
        out["per_hinge_fit"] = hinge_fit
    write_json(args.json, out)
    if json_to_stdout(args):
        return 0
    print(f"device profile: {out['device_profile']} (prior: {out['prior']})")
    units = spec_units(SPEC_PATH)
    print(f"fitted in {res.iterations} generations ({res.evaluations} twin replays); each parameter in the spec "
          "file's unit, its 95 % interval, and both as multiples of the prior:")
    for p, e in res.estimates.items():
        unit = units.get(p, "")
        print(f"  {p:<14} {shown(e.value, unit)}  interval {shown_range(e.low, e.high, unit)}  "
              f"(x{e.value / e.prior:.3f}, x{e.low / e.prior:.3f} .. x{e.high / e.prior:.3f})  "
              f"{'identifiable' if e.identifiable else 'NOT IDENTIFIABLE'}: {e.note}")
    for p, e in res.bounded.items():
        unit = units.get(p, "")
        print(f"  {p:<14} {shown(e.value, unit)}  within {shown_range(e.low, e.high, unit)} "
              f"(x{e.low / e.prior:.3g} .. x{e.high / e.prior:.3g}): {e.note}")
    print(f"residual autocorrelation {res.autocorrelation_frames:.0f} frames (the intervals allow for it; the "
          "Hessian's singular values are in --json)")
    print(f"fit RMSE (training runs, hinge angles): {res.rmse_before:.3f} deg -> {res.rmse_after:.3f} deg")
    _print_per_hinge("training runs", out["per_hinge"])
    if holdout:
        h = out["holdout"]
        print("held-out RMSE per hinge, deg: before " + " ".join(f"{x:.3f}" for x in h["rmse_before_deg"]))
        print("                              after  " + " ".join(f"{x:.3f}" for x in h["rmse_after_deg"]))
        print(f"held-out RMSE overall (every frame of every hinge), deg: {h['overall_before_deg']:.3f} -> "
              f"{h['overall_after_deg']:.3f}")
        _print_per_hinge("held-out run", h["per_hinge"])
    if args.per_hinge:
        _print_hinge_fit(out["per_hinge_fit"], units)
        print(("each hinge's own values kept in device profile " + name if name else
               "each hinge's own values: in --json only (no device profile to keep them in; --device NAME)")
              if out["per_hinge_fit"]["kept"] else
              "each hinge's own values NOT kept: they predict the held-out run worse than the shared ones (more "
              "values fitted to these runs than they show); the profile's twin keeps the shared values")
    print("calibrated spec written to " + ", ".join(written))
    return 0


def _per_hinge(rmse, floor) -> list[dict]:
    """Per hinge: the calibrated twin's RMSE, the floor the encoder and link set, and what neither explains
    (deg; twin.hil.calibration.floor_deg, unexplained)."""
    left = unexplained(rmse, floor)
    return [{"hinge": k, "rmse_deg": round(float(r), 4), "floor_deg": round(float(f), 4),
             "unexplained_deg": round(float(u), 4)} for k, (r, f, u) in enumerate(zip(rmse, floor, left))]


def _print_per_hinge(what: str, rows: list[dict]) -> None:
    print(f"per hinge, {what}: the calibrated twin's RMSE, the floor the encoder's resolution and the link's "
          "timing set, and what no parameter explains, deg")
    for r in rows:
        print(f"  hinge {r['hinge']}: RMSE {r['rmse_deg']:.3f}  floor {r['floor_deg']:.3f}  "
              f"unexplained {r['unexplained_deg']:.3f}")


def _hinge_fit(hc, holdout, shared) -> dict:
    """A per-hinge calibration for JSON: per hinge its parameters (Estimate, SI; the prior the shared value),
    the training runs' RMSE with the shared and the per-hinge twin, the floor and what is left unexplained;
    with a held-out run, the same on it. "kept": whether the profile keeps them: always without a held-out
    run; with one, only where each hinge's own values predict it no worse overall than the shared ones
    (more values fitted to a short run can overfit it)."""
    out = {"evaluations": hc.evaluations, "hinges": [], "kept": True}
    for k, est in enumerate(hc.estimates):
        out["hinges"].append({"hinge": k, "parameters": {p: e.to_json() for p, e in est.items()},
                              "rmse_shared_deg": round(float(hc.rmse_before[k]), 4),
                              "rmse_per_hinge_deg": round(float(hc.rmse_after[k]), 4),
                              "floor_deg": round(float(hc.floor[k]), 4),
                              "unexplained_deg": round(float(unexplained(hc.rmse_after[k], hc.floor[k])), 4)})
    if holdout is not None:
        shared_rmse = trace_rmse(holdout, shared, shared)
        own = trace_rmse(holdout, shared, shared, hc.hinges)
        floor = floor_deg(holdout, shared)
        out["holdout"] = [{"hinge": k, "rmse_shared_deg": round(float(a), 4), "rmse_per_hinge_deg": round(float(b), 4),
                           "floor_deg": round(float(f), 4), "unexplained_deg": round(float(unexplained(b, f)), 4)}
                          for k, (a, b, f) in enumerate(zip(shared_rmse, own, floor))]
        out["kept"] = bool(np.sqrt(np.mean(own ** 2)) <= np.sqrt(np.mean(shared_rmse ** 2)))
    return out


def _print_hinge_fit(fit: dict, units: dict) -> None:
    print("per hinge, each parameter about the shared value (x), its 95 % interval, and its verdict:")
    for h in fit["hinges"]:
        cells = []
        for p, e in h["parameters"].items():
            verdict = "identifiable" if e["identifiable"] else "fitted" if e["value"] != e["prior"] else "shared"
            cells.append(f"{p} {shown(e['value'], units.get(p, ''))} (x{e['value'] / e['prior']:.3f}, "
                         f"x{e['low'] / e['prior']:.2f} .. x{e['high'] / e['prior']:.2f}, {verdict})")
        print(f"  hinge {h['hinge']}: " + "; ".join(cells))
    for label, rows in (("training runs", fit["hinges"]), ("held-out run", fit.get("holdout", []))):
        if rows:
            print(f"per hinge, {label}, deg: RMSE with the shared values -> with each hinge's own; floor; unexplained")
            for r in rows:
                print(f"  hinge {r['hinge']}: {r['rmse_shared_deg']:.3f} -> {r['rmse_per_hinge_deg']:.3f}; "
                      f"floor {r['floor_deg']:.3f}; unexplained {r['unexplained_deg']:.3f}")


def _identify(args, profile, name, new) -> int:
    """`calibrate --serial`: the experiments on the device, each hinge fitted, the profile written (its mount
    flat, as the experiments ran), a report."""
    if not new and profile.name and profile.mount != "flat":  # the experiments raise each flap off a table
        raise UserError(f"the identification experiments run lying flat on a table, and profile {profile.name!r} "
                        f"says the device is {profile.mount}: lay it flat and record that (`vrscroll simulate 0 0 0 0 0 0 "
                        f"--device {profile.name} --mount flat`; docs/device.md, \"Mounts\")")
    quiet = json_to_stdout(args)
    say = None if quiet else (lambda message: print(message, flush=True))
    start = time.monotonic()
    try:
        with device_session(args, profile.spec) as (link, spec):
            if not quiet:
                print(f"device profile: {name or profile.label} (prior: {'spec defaults' if new else profile.label}); "
                      "identifying each hinge, the device lying flat", flush=True)
            moves, device_s = experiments(link.run_program, spec, progress=say)
            port = link.url
        fits = [fit_hinge(m, spec, say) for m in moves.values()]
    except NackError as exc:
        raise UserError(f"the device refused an experiment ({exc}): it runs them IDLE with its zero confirmed, "
                        "lying flat (`vrscroll zero --serial PORT`)") from None
    except LinkError as exc:
        raise UserError(f"link: {exc}") from None
    except ValueError as exc:
        raise UserError(f"identification: {exc}") from None
    wall = time.monotonic() - start
    per_hinge = [estimates(f, spec, MAX_HALFWIDTH) for f in fits]
    shared = shared_estimates([{p: e[p] for p in PROFILED} for e in per_hinge])
    written = []
    if name:
        source = f"identified on {port} (vrscroll calibrate --serial)"
        calibration = Calibration([f"{port}: identification experiments"], shared,
                                  [{p: e[p] for p in PROFILED} for e in per_hinge])
        written.append(str(write_profile(updated(profile, {p: e.value for p, e in shared.items()}, source, name=name,
                                                 calibration=calibration, mount="flat"))))
        set_default(name)
    out = {"device_profile": name or profile.label, "prior": "spec defaults" if new else profile.label,
           "written": written, "port": port,
           "parameters": {p: e.to_json() for p, e in shared.items()},
           "hinges": [{"hinge": f.hinge, "parameters": {p: e.to_json() for p, e in est.items()},
                       "held": {p: {"value": v, "low": lo, "high": hi} for p, (v, lo, hi) in f.held.items()},
                       "rms_speed_rad_s": round(f.rms_speed, 4), "windows": f.windows, "replays": f.replays}
                      for f, est in zip(fits, per_hinge)],
           "device_time_s": round(device_s, 2), "wall_time_s": round(wall, 1)}
    write_json(args.json, out)
    if quiet:
        return 0
    units = spec_units(SPEC_PATH)
    print(f"identified in {wall:.0f} s ({device_s:.1f} s of experiments on the device); per hinge each value in "
          "the spec file's unit, its 95 % interval, and both as multiples of the prior:")
    for f, est in zip(fits, per_hinge):
        print(f"  hinge {f.hinge} (speed residual {f.rms_speed:.2f} rad/s over {f.windows} windows):")
        for p, e in est.items():
            unit = units.get(p, "")
            print(f"    {p:<14} {shown(e.value, unit)}  interval {shown_range(e.low, e.high, unit)}  "
                  f"(x{e.value / e.prior:.3f}, x{e.low / e.prior:.3f} .. x{e.high / e.prior:.3f})  "
                  f"{'identifiable' if e.identifiable else 'NOT IDENTIFIABLE'}")
    print("held, not shown by the experiments (each anywhere in its range widens the intervals above): "
          + ", ".join(f"{p} {shown(v, units.get(p, ''))} (x{lo / v:.2g} .. x{hi / v:.2g})"
                      for p, (v, lo, hi) in fits[0].held.items()))
    print("the profile keeps each hinge's " + ", ".join(PROFILED) + " (the resistance is the winding's now: it "
          "warms and cools with use)")
    print("calibrated spec written to " + (", ".join(written) if written else "nothing (--device NAME keeps it)"))
    return 0
