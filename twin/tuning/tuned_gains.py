"""What `vrscroll tune` does with a device profile: the goal from what the command line states (deg, %, s), the
search over the plants the profile leaves open (twin.tuning.tuner.tune), the gains kept (a gains file, the
profile), and a Report: the summary as JSON and the step before and after, per hinge, in words."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from twin.device.spec import SPEC_PATH
from twin.device.spec_toml import shown_range, spec_units
from twin.errors import UserError
from twin.formats.gains import write_gains
from twin.formats.move_report import move_rows
from twin.formats.profile import write_profile_gains
from twin.records.gains import Gains
from twin.records.profile import Profile
from twin.records.report import Report
from twin.tuning.tuner import TuneGoal, profile_goal, step_report, tune, tuned_summary


def goal_of(profile: Profile, max_overshoot_deg: float, tolerance_pct: float, step_deg: float,
            duration_s: float) -> TuneGoal:
    """The goal over the profile's plants (profile_goal) from the command line's deg, % and s; UserError for a
    step outside the hinge range or inside the settle band (settled before it starts: it tests nothing)."""
    spec = profile.spec
    step = math.radians(step_deg)
    if not abs(step) <= spec.hinge_limit:
        raise UserError(f"--step-deg {step_deg}: outside the hinge range")
    smallest = 2 * spec.settle_band * spec.rad_per_count
    if not abs(step) >= smallest:
        raise UserError(f"--step-deg {step_deg}: a step must leave the settle band to test anything: at least "
                        f"{math.degrees(smallest):.2f} deg (twice the band of {spec.settle_band} counts)")
    return profile_goal(profile, math.radians(max_overshoot_deg), tolerance_pct / 100, step, duration_s)


def ranges_line(profile: Profile, goal: TuneGoal) -> str:
    """The plants tuned over, in words (the spec file's units)."""
    ranges, units = goal.ranges, spec_units(SPEC_PATH)
    return (("calibrated: the twin's values that reproduce its runs" if ranges.calibrated else ranges.what)
            + ": tuned over " + ", ".join(f"{p} {shown_range(lo, hi, units.get(p, ''))}"
                                         for p, (lo, hi) in ranges.shared.items())
            + f" ({2 ** len(ranges.shared) + 1} plants: nominal and corners)"
            + ("; each hinge about its own calibrated values, at its own intervals' corners" if profile.hinges
               else ""))


@dataclasses.dataclass(frozen=True)
class Tuned:
    """A tuning's outcome: the gains (with what they were made for), the limits they break on their worst plant
    (none: every limit kept), for each hinge that breaks one the interval end that sets its worst case
    ({"hinge", "parameter", "end"}: the tuner's range_sensitivity), and the Report, whose doc["gains_files"]
    lists where they are kept so far."""

    gains: Gains
    broken: list[str]
    worst_case: list[dict]
    report: Report

    def keep_in(self, profile: Profile) -> None:
        """Keep the gains in the profile (when it has a name): with --serial, once the device holds them."""
        if profile.name:
            self.report.doc["gains_files"].insert(0, str(write_profile_gains(profile.name, self.gains)))


def tune_profile(profile: Profile, goal: TuneGoal, stated: dict, out: str | None, keep: bool, *, population: int,
                 generations: int, seed: int, nthread: int, backend=None, progress=None) -> Tuned:
    """Tune the profile's gains for `goal` (stated: the goal as the command line gave it, deg and s) and keep them
    in `out` (a gains file; without a profile name, gains.json) and, when keep, in the profile.
    progress(line) per generation, or None."""
    spec, before = profile.spec, profile.gains
    result = tune(spec, goal, population=population, generations=generations, seed=seed, nthread=nthread,
                  start=before, backend=backend,
                  progress=progress and (lambda g, c, t: progress(
                      f"generation {g + 1}/{generations}: worst-plant cost per hinge "
                      + " ".join(f"{x * 1000:5.0f}" for x in c) + f" ms  ({t:.1f} s)")))
    rows_before = move_rows(step_report(spec, before, goal, hinges=profile.hinges)[0])
    rows_after = move_rows(step_report(spec, result.gains, goal, hinges=profile.hinges)[0])
    gains = Gains(result.gains, {"device_profile": profile.label, **tuned_summary(goal, result, stated)})
    written = []
    if out or not profile.name:
        written.append(out or "gains.json")
        write_gains(written[-1], gains)
    worst_case = [{"hinge": h, **result.sensitivity[h]} for h in np.flatnonzero(result.cost >= goal.duration)]
    tuned = Tuned(gains, result.broken, worst_case, Report({"gains_files": written, "before": rows_before, "after": rows_after,
                                                **gains.meta}, []))
    if keep:
        tuned.keep_in(profile)
    tuned.report.lines.extend([
        f"tuned in {result.wall_time:.1f} s ({result.simulations} simulations of {stated['duration_s']} s); "
        f"nominal twin, step to {stated['step_deg']} deg, per hinge settle / overshoot:",
        _step_line("before", rows_before), _step_line("tuned", rows_after),
        "worst plant     " + "  ".join(f"{s * 1000:6.0f} ms {math.degrees(o):5.2f} deg"
                                       for s, o in zip(result.settle, result.overshoot)),
        "worst case set by (each range's ends, one at a time): " + "; ".join(
            f"hinge {h} {r['parameter']} {r['end']}" for h, r in enumerate(result.sensitivity)),
        "every limit kept on every plant" if not result.broken else
        "NOT KEPT on its worst plant (the best the search found):\n  " + "\n  ".join(result.broken),
        "gains written to " + (", ".join(written) if written else
                               f"device profile {profile.name} once the device holds them")])
    return tuned


def _step_line(label: str, rows: list[dict]) -> str:
    """A step's per-hinge settle time (ms) and overshoot (deg) on one line."""
    return f"{label:<16}" + "  ".join(f"{r['settle_time_s'] * 1000:6.0f} ms {r['overshoot_deg']:5.2f} deg"
                                      if not math.isnan(r['settle_time_s']) else f"{'unsettled':>9} "
                                      f"{r['overshoot_deg']:5.2f} deg" for r in rows)
