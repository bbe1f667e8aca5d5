"""What `vrscroll calibrate` does with a fit and says of it: the calibration of a profile from recorded HIL runs
(calibrate_runs) or from the device's own identification experiments (identify), each kept in the device
profile (the Calibration record whole, its shared values in the spec), and each result a Report: the command's
JSON document and its report's lines (deg and the spec file's units). The fits are twin.hil.calibration's and
twin.hil.identification's; this module reads the runs, keeps the result and words it.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from twin.device.profile import profile_dir, set_default
from twin.device.spec import SPEC_PATH
from twin.device.spec_toml import shown, shown_range, spec_units, write_spec_toml
from twin.device.variation import SPREAD
from twin.errors import UserError
from twin.formats.profile import updated, write_profile
from twin.formats.run import read_run
from twin.hil.calibration import (HINGE_RANGE, MAX_HALFWIDTH, calibrate, calibrate_hinges, compared_lines,
                                  compared_rows, floor_deg, trace_rmse, unexplained)
from twin.hil.compare import not_followed
from twin.hil.identification import PROFILED, Move, estimates, experiments, fit_hinge, shared_estimates
from twin.hil.identification_holdout import HOLDOUT_FOLDER, holdout_lines, holdout_report, record_holdout
from twin.link.serial_link import LinkError, NackError
from twin.records.calibration import Calibration, Estimate
from twin.records.profile import Profile
from twin.records.report import Report
from twin.sim.gate import NOT_FLAT_DEPTH, below_table


def read_runs(paths: list[str], holdout: str | None, spec, incomplete: bool, note) -> tuple[list, object]:
    """(the runs, the held-out run or None) read and checked for fitting; note(message) for each warning.
    UserError (one line) for a run that cannot be read or holds nothing to fit."""
    try:
        runs = [read_run(r, spec, incomplete=incomplete) for r in paths]
        held = read_run(holdout, spec, incomplete=incomplete) if holdout else None
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot read a HIL run: {exc}" + ("" if incomplete or "did not complete" not in str(exc)
                                                            else " (--incomplete uses what it recorded)")) from None
    for r in runs + ([held] if held else []):
        if r.status != "complete":
            note(f"note: {r.dir} did not complete (status {r.status!r}); using the "
                 f"{len(r.device.time)} device frames it recorded")
        if len(r.device.time) < 10:
            raise UserError(f"{r.dir}: fewer than 10 device frames; nothing to fit")
        if r.start.before_state is None:
            raise UserError(f"{r.dir}: recorded without the device's state before the run; record it again")
        warning = not_followed([{"hinge": k, "rmse_deg": float(x)} for k, x in enumerate(trace_rmse(r, spec, spec))])
        if warning:
            note(f"vrscroll calibrate: warning: {r.dir}: {warning}")
    return runs, held


def calibrate_runs(profile: Profile, name: str | None, prior: str, paths: list[str], holdout: str | None, *,
                   per_hinge: bool, out: str | None, incomplete: bool = False, population: int = 24,
                   generations: int = 8, nthread: int = 0, progress=None, note=print) -> Report:
    """Fit the profile's plant to the HIL runs at `paths` (and, per_hinge, each hinge's own about it), keep it
    in profile `name` (made the default; None: none) and, with `out` or without a name, in a spec TOML; the
    command's Report. prior: what the fit started from, in words. progress(line) per generation; note(line) for
    each run's note or warning."""
    spec = profile.spec
    runs, held = read_runs(paths, holdout, spec, incomplete, note)
    res = calibrate(runs, spec, population=population, generations=generations, nthread=nthread,
                    progress=progress and (lambda g, c: progress(f"generation {g + 1}/{generations}: best cost {c:.4g}")))
    hc = hinge_fit = None
    if per_hinge:
        hc = calibrate_hinges(runs, res.spec, population=population, generations=generations,
                              shared_estimates=res.estimates, nthread=nthread,
                              progress=progress and (lambda g, c: progress(
                                  f"per hinge, generation {g + 1}/{generations}: best cost {c:.4g}")))
        hinge_fit = _hinge_fit(hc, held, res.spec)
    source = "calibrated from " + ", ".join(str(Path(r).resolve()) for r in paths) + " (vrscroll calibrate)"
    fitted = {p: e.value for p, e in res.estimates.items() if e.fitted}
    written = []
    if name:
        calibration = Calibration([str(Path(r).resolve()) for r in paths], res.estimates,
                                  hc.estimates if hinge_fit and hinge_fit["kept"] else None)
        written.append(str(write_profile(updated(profile, fitted, source, name=name, calibration=calibration))))
        set_default(name)
    if out or not name:
        out = out or "spec.calibrated.toml"
        template = profile.folder / "spec.toml" if profile.folder else SPEC_PATH
        write_spec_toml(out, template, fitted, source,
                        header="Calibrated device spec, written by `vrscroll calibrate` (see "
                               "docs/tuning-hil-calibration.md).")
        written.append(out)
    doc = {"device_profile": name or profile.label, "prior": prior, "written": written,
           "parameters": {p: e.to_json() for p, e in res.estimates.items()},
           "bounded": {p: e.to_json() for p, e in res.bounded.items()},
           "scales": {k: round(v, 4) for k, v in res.scales.items()},
           "singular_values": [round(s, 4) for s in res.singular_values],
           "autocorrelation_frames": round(res.autocorrelation_frames, 1),
           "fit_rmse_deg": {"before": round(res.rmse_before, 4), "after": round(res.rmse_after, 4)},
           "per_hinge": _per_hinge(res.hinge_rmse_after, res.hinge_floor),
           "iterations": res.iterations, "replays": res.evaluations}
    if held:
        before, after = trace_rmse(held, spec, spec), trace_rmse(held, res.spec, spec)
        doc["holdout"] = {"run": holdout, "rmse_before_deg": before.round(4).tolist(),
                          "rmse_after_deg": after.round(4).tolist(),
                          "per_hinge": _per_hinge(after, floor_deg(held, spec)),
                          "overall_before_deg": round(float(np.sqrt(np.mean(before ** 2))), 4),
                          "overall_after_deg": round(float(np.sqrt(np.mean(after ** 2))), 4)}
    if hinge_fit:
        doc["per_hinge_fit"] = hinge_fit
    return Report(doc, _calibration_lines(doc, res, bool(name)))


def _per_hinge(rmse, floor) -> list[dict]:
    """Per hinge: the calibrated twin's RMSE, the floor the encoder and link set, and what neither explains
    (deg; twin.hil.calibration.floor_deg, unexplained)."""
    left = unexplained(rmse, floor)
    return [{"hinge": k, "rmse_deg": round(float(r), 4), "floor_deg": round(float(f), 4),
             "unexplained_deg": round(float(u), 4)} for k, (r, f, u) in enumerate(zip(rmse, floor, left))]


HINGE_KEYS = ("rmse_shared_deg", "rmse_per_hinge_deg")  # a per-hinge fit's RMSE with the shared and its own values


def _hinge_fit(hc, holdout, shared) -> dict:
    """A per-hinge calibration for JSON: per hinge its parameters (Estimate, SI; the prior the shared value),
    the training runs' RMSE with the shared and the per-hinge twin, the floor and what is left unexplained;
    with a held-out run, the same on it. "kept": whether the profile keeps them: always without a held-out
    run; with one, only where each hinge's own values predict it no worse overall than the shared ones
    (more values fitted to a short run can overfit it)."""
    rows = compared_rows(hc.rmse_before, hc.rmse_after, hc.floor, HINGE_KEYS)
    out = {"evaluations": hc.evaluations,
           "hinges": [{"hinge": k, "parameters": {p: e.to_json() for p, e in est.items()},
                       **{c: v for c, v in row.items() if c != "hinge"}}
                      for k, (est, row) in enumerate(zip(hc.estimates, rows))], "kept": True}
    if holdout is not None:
        shared_rmse = trace_rmse(holdout, shared, shared)
        own = trace_rmse(holdout, shared, shared, hc.hinges)
        floor = floor_deg(holdout, shared)
        out["holdout"] = compared_rows(shared_rmse, own, floor, HINGE_KEYS)
        out["kept"] = bool(np.sqrt(np.mean(own ** 2)) <= np.sqrt(np.mean(shared_rmse ** 2)))
    return out


def _estimate_line(p: str, e: dict, unit: str, note: bool = True) -> str:
    """One fitted parameter (an Estimate's JSON form): its value and 95 % interval in the spec file's unit, both
    as multiples of the prior, and its verdict."""
    return (f"{p:<14} {shown(e['value'], unit)}  interval {shown_range(e['low'], e['high'], unit)}  "
            f"(x{e['value'] / e['prior']:.3f}, x{e['low'] / e['prior']:.3f} .. x{e['high'] / e['prior']:.3f})  "
            f"{'identifiable' if e['identifiable'] else 'NOT IDENTIFIABLE'}" + (f": {e['note']}" if note else ""))


def _calibration_lines(doc: dict, res, kept: bool) -> list[str]:
    """calibrate_runs' report in lines (the spec file's units and deg): doc, with res (CalibrationResult) for
    the figures the document rounds; kept: whether a profile keeps the result."""
    units = spec_units(SPEC_PATH)
    lines = [f"device profile: {doc['device_profile']} (prior: {doc['prior']})",
             f"fitted in {doc['iterations']} generations ({doc['replays']} twin replays); each parameter in the spec "
             "file's unit, its 95 % interval, and both as multiples of the prior:"]
    lines += [f"  {_estimate_line(p, e, units.get(p, ''))}" for p, e in doc["parameters"].items()]
    for p, e in doc["bounded"].items():
        unit = units.get(p, "")
        lines.append(f"  {p:<14} {shown(e['value'], unit)}  within {shown_range(e['low'], e['high'], unit)} "
                     f"(x{e['low'] / e['prior']:.3g} .. x{e['high'] / e['prior']:.3g}): {e['note']}")
    lines.append(f"residual autocorrelation {res.autocorrelation_frames:.0f} frames (the intervals allow for it; "
                 "the Hessian's singular values are in --json)")
    lines.append(f"fit RMSE (training runs, hinge angles): {res.rmse_before:.3f} deg -> {res.rmse_after:.3f} deg")
    lines += _per_hinge_lines("training runs", doc["per_hinge"])
    if "holdout" in doc:
        h = doc["holdout"]
        lines += ["held-out RMSE per hinge, deg: before " + " ".join(f"{x:.3f}" for x in h["rmse_before_deg"]),
                  "                              after  " + " ".join(f"{x:.3f}" for x in h["rmse_after_deg"]),
                  f"held-out RMSE overall (every frame of every hinge), deg: {h['overall_before_deg']:.3f} -> "
                  f"{h['overall_after_deg']:.3f}"]
        lines += _per_hinge_lines("held-out run", h["per_hinge"])
    if "per_hinge_fit" in doc:
        lines += _hinge_fit_lines(doc["per_hinge_fit"], units)
        lines.append(("each hinge's own values kept in device profile " + doc["device_profile"] if kept else
                      "each hinge's own values: in --json only (no device profile to keep them in; --device NAME)")
                     if doc["per_hinge_fit"]["kept"] else
                     "each hinge's own values NOT kept: they predict the held-out run worse than the shared ones (more "
                     "values fitted to these runs than they show); the profile's twin keeps the shared values")
    lines.append("calibrated spec written to " + ", ".join(doc["written"]))
    return lines


def _per_hinge_lines(what: str, rows: list[dict]) -> list[str]:
    return [f"per hinge, {what}: the calibrated twin's RMSE, the floor the encoder's resolution and the link's "
            "timing set, and what no parameter explains, deg"] + [
        f"  hinge {r['hinge']}: RMSE {r['rmse_deg']:.3f}  floor {r['floor_deg']:.3f}  "
        f"unexplained {r['unexplained_deg']:.3f}" for r in rows]


def _hinge_fit_lines(fit: dict, units: dict) -> list[str]:
    lines = ["per hinge, each parameter about the shared value (x), its 95 % interval, and its verdict:"]
    for h in fit["hinges"]:
        cells = []
        for p, e in h["parameters"].items():
            verdict = "identifiable" if e["identifiable"] else "fitted" if e["value"] != e["prior"] else "shared"
            cells.append(f"{p} {shown(e['value'], units.get(p, ''))} (x{e['value'] / e['prior']:.3f}, "
                         f"x{e['low'] / e['prior']:.2f} .. x{e['high'] / e['prior']:.2f}, {verdict})")
        lines.append(f"  hinge {h['hinge']}: " + "; ".join(cells))
    for label, rows in (("training runs", fit["hinges"]), ("held-out run", fit.get("holdout", []))):
        if rows:
            lines.append(f"per hinge, {label}, deg: RMSE with the shared values -> with each hinge's own; floor; "
                         "unexplained")
            lines += compared_lines(rows, HINGE_KEYS)
    return lines


def check_lying_flat(profile: Profile) -> None:
    """UserError unless the profile lets the device lie flat: the identification experiments raise each flap off
    a table."""
    if profile.name and profile.mount != "flat":
        raise UserError(f"the identification experiments run lying flat on a table, and profile {profile.name!r} "
                        f"says the device is {profile.mount}: lay it flat and record that (`vrscroll simulate 0 0 0 0 0 0 "
                        f"--device {profile.name} --mount flat`; docs/device.md, \"Mounts\")")


def check_lying_there(spec, counts) -> None:
    """UserError where the device's present angles (counts) put a flap more than the gate's NOT_FLAT_DEPTH below a
    table: it is not lying flat (hanging, its flaps sagged), and the experiments would raise flaps off no table."""
    depth = below_table(spec, np.asarray(counts, float) * spec.rad_per_count)
    j = int(np.argmax(depth))
    if depth[j] > NOT_FLAT_DEPTH:
        raise UserError(f"flap {j} lies {depth[j] * 1000:.0f} mm below the table: the device is not lying flat, as "
                        "the identification experiments need it (hanging? lay it flat, then `vrscroll zero --serial "
                        "PORT`)")


def identify(session, profile: Profile, name: str | None, prior: str, say=None) -> Report:
    """`calibrate --serial`: the experiments on the device `session` opens (a context manager giving (link,
    spec), closed before the fits) and the held-out run after them (twin.hil.identification_holdout), each hinge
    fitted, the profile `name` written (its mount flat, as the experiments ran; made the default; the held-out
    run kept in its folder), the held-out run's RMSE with the prior and the identified values; the command's
    Report. say(line): progress, or None. UserError
    (one line) for a refused experiment, the link, or a fit the experiments cannot give."""
    start = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        held_dir = Path(tmp) / HOLDOUT_FOLDER
        try:
            with session as (link, spec):
                if say:
                    say(f"device profile: {name or profile.label} (prior: {prior}); identifying each hinge, the "
                        "device lying flat")
                check_lying_there(spec, link.get_state().counts)
                ends: dict = {}  # hinge -> how each of its programs ended

                def run_program(hinge, *args):
                    run = link.run_program(hinge, *args)
                    ends.setdefault(hinge, []).append(run.end)
                    return run

                moves, device_s = experiments(run_program, spec, progress=say)
                port = link.url
                if say:
                    say("the held-out run: a closed-loop scenario no fit sees, from flat")
                held, not_recorded = record_holdout(link, spec, held_dir, name or "")
            fits = {k: fit_hinge(m, spec, say) for k, m in moves.items() if moved(m)}
        except NackError as exc:
            raise UserError(f"the device refused an experiment ({exc}): it runs them IDLE with its zero confirmed, "
                            "lying flat (`vrscroll zero --serial PORT`)") from None
        except LinkError as exc:
            raise UserError(f"link: {exc}") from None
        except ValueError as exc:
            raise UserError(f"identification: {exc}") from None
        wall = time.monotonic() - start
        unfitted = {k: not_moved_note(ends.get(k, [])) for k in moves if k not in fits}
        if not fits:
            raise UserError(f"no hinge moved in its identification experiments: hinge 0 {unfitted[0]}")
        per_hinge = [estimates(fits[k], spec, MAX_HALFWIDTH) if k in fits else prior_estimates(spec, unfitted[k])
                     for k in sorted(moves)]
        shared = shared_estimates([{p: e[p] for p in PROFILED} for e in per_hinge])
        calibration = Calibration([f"{port}: identification experiments"], shared,
                                  [{p: e[p] for p in PROFILED} for e in per_hinge])
        fitted = updated(profile, {p: e.value for p, e in shared.items()},
                         f"identified on {port} (vrscroll calibrate --serial)", name=name, calibration=calibration,
                         mount="flat")
        holdout = ({"run": "not kept (--device NAME keeps it)", **holdout_report(held, profile, fitted, spec)}
                   if held is not None else {"not_recorded": not_recorded})
        written = []
        if name:
            written.append(str(write_profile(fitted)))
            set_default(name)
            if held is not None:  # kept in the profile's folder, the last calibration's replaced
                kept = profile_dir(name) / HOLDOUT_FOLDER
                shutil.rmtree(kept, ignore_errors=True)
                holdout["run"] = str(shutil.copytree(held_dir, kept))
    doc = {"device_profile": name or profile.label, "prior": prior, "written": written, "port": port,
            "parameters": {p: e.to_json() for p, e in shared.items()},
            "hinges": [_hinge_doc(k, fits.get(k), est) for k, est in zip(sorted(moves), per_hinge)],
            "holdout": holdout, "device_time_s": round(device_s, 2), "wall_time_s": round(wall, 1)}
    return Report(doc, _identification_lines(doc, wall, device_s) + holdout_lines(holdout))


MIN_TRAVEL = 10  # counts (3 deg at the output): a program that turned its hinge less did not move it


def moved(moves: list[Move]) -> bool:
    """Whether any of a hinge's moves turned it at least MIN_TRAVEL counts: else there is nothing to fit (a jammed
    hinge, a dead encoder, a motor that does not turn)."""
    return any(np.nanmax(m.counts) - np.nanmin(m.counts) >= MIN_TRAVEL for m in moves)


def not_moved_note(ends: list[str]) -> str:
    """Why a hinge has no fit, in words, from how its programs ended (controllers.program's end names)."""
    return (f"not fitted: none of its {len(ends)} programs turned it {MIN_TRAVEL} counts (they ended: "
            f"{', '.join(ends) or 'none ran'}); a jammed hinge, a dead encoder or a motor that does not turn "
            "(`vrscroll bringup --serial PORT` checks each); the prior kept, its interval the prior's range")


def prior_estimates(spec, note: str) -> dict:
    """A hinge the experiments could not fit: each PROFILED value the prior's, its interval what is known of an
    uncalibrated device's hinge (twin.device.variation.SPREAD about the spec, and HINGE_RANGE about that), not
    identifiable, with the note."""
    out = {}
    for p in PROFILED:
        v = float(getattr(spec, p))
        lo, hi = SPREAD[p][0] * HINGE_RANGE[0], SPREAD[p][1] * HINGE_RANGE[1]
        out[p] = Estimate(v, v, v * lo, v * hi, False, note)
    return out


def _hinge_doc(k: int, fit, est: dict) -> dict:
    """One hinge's row of identify's JSON: its estimates and, where it was fitted, what the fit held and how it met
    the device."""
    row = {"hinge": k, "parameters": {p: e.to_json() for p, e in est.items()}}
    if fit is None:
        return row | {"fitted": False}
    return row | {"fitted": True,
                  "held": {p: {"value": v, "low": lo, "high": hi} for p, (v, lo, hi) in fit.held.items()},
                  "rms_speed_rad_s": round(fit.rms_speed, 4), "windows": fit.windows, "replays": fit.replays}


def _identification_lines(doc: dict, wall: float, device_s: float) -> list[str]:
    """identify's report in lines (the spec file's units): doc, with the times (s) it rounds."""
    units = spec_units(SPEC_PATH)
    lines = [f"identified in {wall:.0f} s ({device_s:.1f} s of experiments on the device); "
             "per hinge each value in the spec file's unit, its 95 % interval, and both as multiples of the prior:"]
    for h in doc["hinges"]:
        lines.append(f"  hinge {h['hinge']} (speed residual {h['rms_speed_rad_s']:.2f} rad/s over {h['windows']} "
                     "windows):" if h["fitted"] else f"  hinge {h['hinge']}: NOT FITTED")
        lines += [f"    {_estimate_line(p, e, units.get(p, ''), note=not e['identifiable'])}"  # why not, where not
                  for p, e in h["parameters"].items()]
    held = next(h["held"] for h in doc["hinges"] if h["fitted"])
    lines.append("held, not shown by the experiments (each anywhere in its range widens the intervals above): "
                 + ", ".join(f"{p} {shown(v['value'], units.get(p, ''))} (x{v['low'] / v['value']:.2g} .. "
                             f"x{v['high'] / v['value']:.2g})" for p, v in held.items()))
    lines.append("the profile keeps each hinge's " + ", ".join(PROFILED) + " (the resistance is the winding's now: "
                 "it warms and cools with use)")
    lines.append("calibrated spec written to " + (", ".join(doc["written"]) if doc["written"] else
                                                  "nothing (--device NAME keeps it)"))
    return lines
